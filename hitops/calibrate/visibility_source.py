"""The visibility reference source: REF_MS's visibilities tracked, per group pair.

The run skeleton's (hitops/calibrate/skeleton.py) first source: each group pair's chunks
read, tracked and transferred by :func:`hitops.calibrate.pipeline.run_group` (with the n0
step between its passes), then ``--calibrator-field``'s step over the staged columns
(:mod:`hitops.calibrate.phaseref`), all into one transaction; the report from each group's
result (hitops/calibrate/report.py).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Dict, List, Optional, Tuple

from ..io import read as msio
from .output import OutputTransaction, release_cluster_tables
from .output_msv4 import DataGroupTransaction, data_groups_entry, transaction_class
from .plan import RunPlan
from .files import PreparedInputs

log = logging.getLogger("hitops.calibrate")


@dataclass(frozen=True)
class VisibilitySource:
    """A planned visibility run: the plan, the cluster (None: this process) and the
    calibrator step's check, made before anything is written."""

    run: RunPlan
    client: object
    started: float
    prepared: PreparedInputs
    calibrator: object          # phaseref.check_calibrator_field's result (None without it)

    @classmethod
    def of(cls, run: RunPlan, client, started: float,
           prepared: PreparedInputs) -> "VisibilitySource":
        from .phaseref import check_calibrator_field

        # --calibrator-field, before anything is written
        return cls(run, client, started, prepared, check_calibrator_field(run))

    @property
    def reads_tables(self) -> bool:
        """A cluster runs and a band is a Measurement Set v2 (whose table handles the
        cluster must let go of before the commit; a processing set has none)."""
        from .passes import workers_do_io

        return self.client is not None and not workers_do_io(self.run)

    def open_transaction(self) -> OutputTransaction:
        run, client = self.run, self.client
        # everything this run changes in the target set: a Measurement Set v2's new columns
        # (hitops/calibrate/output.py), a processing set's new data groups
        # (hitops/calibrate/output_msv4.py)
        if transaction_class(run.target_ms) is DataGroupTransaction:
            tx = DataGroupTransaction(run.target_ms, run.outputs, run.columns.target_data,
                                      [g.match.datasets["tgt"] for g in run.groups],
                                      run.chunk_rows, bool(run.opts.output.overwrite))
        else:
            tx = OutputTransaction(run.target_ms, run.outputs, run.columns.target_data, None,
                                   run.chunk_rows,
                                   direct_writes=client is None and all(
                                       isinstance(g.match.datasets["tgt"], msio.StorageRows)
                                       for g in run.groups))
        tx.check_space()
        if self.reads_tables:
            release_cluster_tables(client)   # stale handles of an earlier run on this cluster
        # a target not stored in time order and cut into chunks is written in scattered rows
        created = tx.create_columns(scattered=any(
            g.n_chunks > 1 and not g.match.tgt.time_ordered for g in run.groups))
        if client is not None:
            log.info("created %s in %s before sending work to the cluster", ", ".join(created),
                     run.target_ms)
        return tx

    def stage(self, tx: OutputTransaction) -> Tuple[List, Optional[Dict]]:
        """Every group pair's passes, then the calibrator step on the staged columns:
        (each group's GroupResult, the phase referencing's report or None)."""
        from .phaseref import phase_reference
        from .passes import run_groups

        results = run_groups(self.run, tx, self.client)
        # the instrumental term solved on the calibrator, applied to the staged columns
        referencing = phase_reference(self.run, tx, self.calibrator)
        if self.reads_tables:
            release_cluster_tables(self.client)
        return results, referencing

    def after_commit(self) -> str:
        return "the report" if self.run.opts.run.no_verdict else "the verdict and the report"

    def report(self, tx: OutputTransaction, staged: Tuple[List, Optional[Dict]]) -> Dict:
        from .phaseref import settle_n0_warnings
        from .report import combined_report, group_report, finish_after_commit

        run, (results, referencing) = self.run, staged
        reports = [group_report(run, group, result, tx, self.started)
                   for group, result in zip(run.groups, results)]
        report = reports[0] if len(reports) == 1 else combined_report(run, reports)
        if isinstance(tx, DataGroupTransaction):   # where a processing set's results are
            report["data_groups"] = data_groups_entry(tx)
        if referencing is not None:
            report["phase_referencing"] = referencing
            settle_n0_warnings(report, self.calibrator)
        return finish_after_commit(run, report, results[0] if len(reports) == 1 else None,
                                   self.started, self.prepared, results)
