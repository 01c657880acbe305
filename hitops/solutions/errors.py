"""Typed errors of the solution-space transfer: one line each, naming the table and the remedy."""

from __future__ import annotations

from ..errors import HitopsError, InputError


class SolutionTableError(HitopsError):
    """A reference calibration table cannot be used (missing, not a table, empty)."""


class UnsupportedTableError(SolutionTableError):
    """The table's type is not Fringe Jones, G Jones or T Jones."""


class TableMismatchError(SolutionTableError):
    """The table was solved on another set: antennas, fields, windows or times differ from REF_MS."""


class NoSolutionsError(SolutionTableError):
    """A station observed in REF_MS has no unflagged solution in the table."""


class SolutionIntervalError(SolutionTableError):
    """The phase moves by more than pi between solutions: wraps cannot be counted."""


class TransferOptionError(InputError):
    """An option of the transfer is invalid."""
