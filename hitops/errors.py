"""Typed exceptions for bad input.

Every error a user can cause is a ``HitopsError``; the CLI prints its
message (which names the file, column, station or value and the remedy)
and exits with status 2.  Programming errors are left to surface as
ordinary exceptions.
"""


class HitopsError(Exception):
    """Base class: a problem with the user's input or environment."""

    exit_code = 2


class InputError(HitopsError):
    """A parameter value or combination of parameters is invalid."""


class MeasurementSetError(HitopsError):
    """A Measurement Set is missing, malformed or incompatible."""


class TimeChangedError(MeasurementSetError):
    """A set's TIME column changed while this run was reading it (another writer)."""

    def __init__(self, ms):
        self.ms = ms
        super().__init__(f"{ms}: TIME changed while it was being read; run again when "
                         "nothing else writes to the set")

    def __reduce__(self):   # pickled by its set, not its message
        return type(self), (self.ms,)


class ColumnError(MeasurementSetError):
    """A column is missing, or exists when it should not."""


class StationError(MeasurementSetError):
    """Stations of the two bands cannot be paired."""


class SceneError(HitopsError):
    """A simulation scene file is invalid."""


class OutputExistsError(HitopsError):
    """An output exists and --overwrite was not given."""


class ExternalToolError(HitopsError):
    """CASA, WSClean or another external tool failed."""


class RollbackError(HitopsError):
    """A run failed and could not undo what it had begun; the message says what is left."""

    exit_code = 1


class ProcessingSetError(MeasurementSetError):
    """An MSv4 processing set (zarr) is foreign, of another schema version or half-written."""
