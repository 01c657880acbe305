"""Shared set-up of the tests: Measurement Sets built once per session, copied where written.

In the manner of dask-ms's conftest (daskms/conftest.py, its ``big_ms``): a
session-scoped fixture writes each set under ``tmp_path_factory`` the first
time a test asks for it.  Building a synthetic pair draws its phases and
writes two Measurement Sets with every subtable; copying the two directories
costs a small part of that, and simulating a scene far more.  So:

* ``new_pair(spec)``: a private copy of the session's build of ``spec`` (a
  :class:`hitops.testing.PairSpec`) in the test's ``tmp_path`` (or a directory
  given), with its own truth arrays; for tests that write into the sets (every
  calibrate run does).  Equal specs are built once in the whole suite.
* ``shared_pair(spec)``: the session's build itself, for tests that only read
  it (a test that writes into it spoils it for every later test).
* stage fixtures of ``hitops calibrate`` (hitops/calibrate/stages.py), so one stage can
  be tested without a whole run: ``calibrate_options(ref_ms, target_ms, **flags)`` is
  stage 1's typed options from the command line's flags; ``planned_run(spec, **flags)``
  runs stages 1-3 on the session's build of ``spec`` (nothing is written) and gives the
  ``RunPlan`` with the pair's truth (:class:`PlannedRun`); ``planned_copy`` the same on a
  private copy, for a test that goes on to stage 4 and writes.
* ``eht_imported``: the EHT's public M87 pair (tests/data/eht2017-m87) through
  CASA importuvfits, once for the suite (tests/test_realdata.py and
  tests/test_verdict.py both start from it); read it, or copy it to write.
* the code under test writes its temporary files (dask's scratch space, the command
  line's traceback files) under the session's base directory, not the machine's /tmp:
  ``TMPDIR`` points there for the whole session (``_session_tmpdir``).
* ``cluster``: a dask LocalCluster of 2 single-threaded worker processes, one per test
  module that asks for it (``--scheduler cluster.scheduler_address``).
"""

from __future__ import annotations

import dataclasses
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Dict, Optional

import numpy as np
import pytest

from hitops.testing import PairSpec, PairTruth, make_pair

#: the EHT's public M87 data of 2017 April 5, both bands (see its README.md)
EHT_DATA = Path(__file__).parent / "data" / "eht2017-m87"
EHT_LO = EHT_DATA / "SR1_M87_2017_095_lo_hops_netcal_StokesI.uvfits"
EHT_HI = EHT_DATA / "SR1_M87_2017_095_hi_hops_netcal_StokesI.uvfits"


class PairStore:
    """Synthetic pairs of one test session, each spec built once under ``root``."""

    def __init__(self, root: Path):
        self.root = root
        self._built: Dict[PairSpec, PairTruth] = {}

    def built(self, spec: PairSpec) -> PairTruth:
        """The session's build of ``spec`` (to read, never to write)."""
        if spec not in self._built:
            self._built[spec] = make_pair(self.root / f"pair{len(self._built)}", spec)
        return self._built[spec]

    def copy(self, spec: PairSpec, directory: Path) -> PairTruth:
        """A copy of the build of ``spec`` in ``directory``, with truth arrays of its own."""
        source = self.built(spec)
        directory.mkdir(parents=True, exist_ok=True)
        paths = {}
        for name in ("ref_ms", "target_ms"):
            built_ms = getattr(source, name)
            paths[name] = directory / built_ms.name
            shutil.copytree(built_ms, paths[name])
        arrays = {f.name: getattr(source, f.name).copy() for f in dataclasses.fields(source)
                  if isinstance(getattr(source, f.name), np.ndarray)}
        return dataclasses.replace(source, **paths, **arrays)


@pytest.fixture(scope="session", autouse=True)
def _session_tmpdir(tmp_path_factory):
    """TMPDIR for the session: under pytest's base directory, which a passing run removes.

    Tools under test and the processes they start (dask workers, CASA) leave files in the
    temporary directory (a traceback file by design, dask's scratch space); they belong to
    the test run, not to the machine's /tmp.
    """
    path = tmp_path_factory.mktemp("tmpdir", numbered=False)
    patch = pytest.MonkeyPatch()
    patch.setenv("TMPDIR", str(path))
    # tempfile caches the directory it found first; None makes it look again
    patch.setattr(tempfile, "tempdir", None)
    yield path
    patch.undo()


@pytest.fixture(scope="session")
def pair_store(tmp_path_factory):
    root = tmp_path_factory.mktemp("pairs")
    yield PairStore(root)
    # the builds (about 1 GB over the suite: casacore allocates whole tiles) go with the
    # session; the tests' own copies go with each passing test (tmp_path_retention_policy)
    shutil.rmtree(root, ignore_errors=True)


@pytest.fixture
def new_pair(pair_store, tmp_path):
    """``new_pair(spec, directory=None)``: a private copy of the pair (default: in tmp_path)."""
    def copy(spec: PairSpec, directory: Optional[Path] = None) -> PairTruth:
        return pair_store.copy(spec, tmp_path if directory is None else Path(directory))
    return copy


@pytest.fixture
def shared_pair(pair_store):
    """``shared_pair(spec)``: the session's build of the pair, read-only."""
    return pair_store.built


@dataclasses.dataclass(frozen=True)
class PlannedRun:
    """Stages 1-3 of a calibrate run on a synthetic pair: the plan, and what the pair is."""

    plan: object          # hitops.calibrate.plan.RunPlan
    truth: PairTruth


@pytest.fixture
def calibrate_options():
    """``calibrate_options(ref_ms, target_ms, **flags)``: stage 1's ``CalibrateOptions`` in
    sections, made from the command line's flags (underscored), the rest the schema's."""
    from hitops.calibrate.inputs import CalibrateOptions

    def make(ref_ms, target_ms, **flags):
        return CalibrateOptions.from_flat(dict(ref_ms=str(ref_ms), target_ms=str(target_ms),
                                               **flags))
    return make


def _plan(truth: PairTruth, opts) -> PlannedRun:
    """Stages 1-3 (options and mode, columns, plan) on a pair: nothing is written."""
    from hitops.calibrate.inputs import check_inputs, parse_methods
    from hitops.calibrate.modes import check_options
    from hitops.calibrate.plan import build_plan

    methods = parse_methods(opts.output.method)
    check_options(opts, methods)
    outputs, columns = check_inputs(opts, methods, opts.ref_ms, opts.target_ms)
    return PlannedRun(build_plan(opts, methods, outputs, opts.ref_ms, opts.target_ms, columns,
                                 {}), truth)


@pytest.fixture
def planned_run(shared_pair, calibrate_options):
    """``planned_run(spec, **flags)``: stages 1-3 on the session's build of ``spec``, read
    only (a :class:`PlannedRun`)."""
    def plan(spec: PairSpec, **flags) -> PlannedRun:
        truth = shared_pair(spec)
        return _plan(truth, calibrate_options(truth.ref_ms, truth.target_ms, **flags))
    return plan


@pytest.fixture
def planned_copy(new_pair, calibrate_options):
    """``planned_copy(spec, **flags)``: stages 1-3 on a private copy of ``spec``'s pair, for
    a test that goes on to write (stage 4 and after)."""
    def plan(spec: PairSpec, **flags) -> PlannedRun:
        truth = new_pair(spec)
        return _plan(truth, calibrate_options(truth.ref_ms, truth.target_ms, **flags))
    return plan


def importuvfits(fits: Path, ms: Path) -> Path:
    """CASA importuvfits in its own process (CASA's logger and state stay out of this one)."""
    code = ("from hitops.casa_env import ensure_casa_offline; ensure_casa_offline(); "
            "from casatasks import importuvfits; import sys; "
            "importuvfits(fitsfile=sys.argv[1], vis=sys.argv[2])")
    subprocess.run([sys.executable, "-c", code, str(fits), str(ms)], check=True,
                   capture_output=True, timeout=300)
    return ms


@pytest.fixture(scope="session")
def fringe_fitted(tmp_path_factory):
    """(pair, table): tests/solutions_scene.py's pair (two 230 GHz windows of 16 channels)
    and CASA fringefit's 4-s solutions of its reference band, made once for the suite;
    read-only (a test that writes copies the set first)."""
    from solutions_scene import fringe_fitted_pair

    return fringe_fitted_pair(tmp_path_factory.mktemp("fringe_fitted"))


@pytest.fixture(scope="session")
def eht_imported(tmp_path_factory):
    """(lo.ms, hi.ms): the EHT pair as CASA importuvfits writes it, read-only."""
    root = tmp_path_factory.mktemp("eht2017")
    return importuvfits(EHT_LO, root / "lo.ms"), importuvfits(EHT_HI, root / "hi.ms")


@pytest.fixture(scope="session")
def short_demo(tmp_path_factory):
    """``hitops simulate``'s demo scene over 10 minutes, simulated once for the suite: the
    sets as the simulator leaves them, each with its flags kept as ``hitops_original``."""
    from hitops.simulate import simulate

    out = tmp_path_factory.mktemp("short-demo")
    simulate("demo", out, duration=600)
    return out


@pytest.fixture
def new_demo(short_demo, tmp_path):
    """A private copy of ``short_demo`` (both sets and their CASA flag versions):
    (reference set, target set)."""
    for item in short_demo.iterdir():
        shutil.copytree(item, tmp_path / item.name)
    return tmp_path / "sim-86.ms", tmp_path / "sim-230.ms"


@pytest.fixture(scope="module")
def cluster():
    """A LocalCluster of 2 single-threaded worker processes for the module's tests."""
    distributed = pytest.importorskip("distributed")
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=None) as local:
        yield local

