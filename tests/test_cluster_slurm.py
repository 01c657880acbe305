"""Against a real one-node slurm cluster (scripts/slurm-local.sh: Debian's
slurm-wlm and munge, as root).  Skipped where those are missing, e.g. in CI;
`make slurm-check` runs the full demo the same way.

* `stimela run --slurm -s simulate`: the step runs through a real srun;
* `calibrate_flat(..., scheduler="slurm:2")`: two dask workers as sbatch jobs through
  dask-jobqueue; the output equals the threaded run's.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from casacore import tables as pt

from hitops.testing import PairSpec

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
SLURM_LOCAL = ROOT / "scripts" / "slurm-local.sh"

_missing = [c for c in ("munged", "slurmctld", "slurmd", "srun", "sbatch")
            if shutil.which(c, path=os.environ.get("PATH", "") + ":/usr/sbin:/sbin") is None]
pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(bool(_missing), reason=f"slurm not installed ({', '.join(_missing)} "
                                              f"missing: apt-get install slurm-wlm munge)"),
    pytest.mark.skipif(hasattr(os, "geteuid") and os.geteuid() != 0,
                       reason="a local slurmd needs root"),
]


def _env():
    env = dict(os.environ)
    env["PATH"] = f"{BIN}:{env.get('PATH', '')}:/usr/sbin:/sbin"
    env.setdefault("NUMBA_CACHE_DIR", str(ROOT / ".venv" / "numba-cache"))
    return env


def test_stimela_step_runs_through_a_real_srun(tmp_path):
    out = tmp_path / "out"
    # the job list (jobcomp) is read inside the cluster's lifetime
    script = (f"cd {tmp_path} && {BIN / 'stimela'} run --slurm -s simulate "
              f"{ROOT / 'recipes' / 'fpt-demo.yml'} dir={out} && "
              f"cat $(dirname $SLURM_CONF)/jobcomp.log")
    done = subprocess.run(["bash", str(SLURM_LOCAL), "run", "--", "bash", "-c", script],
                          env=_env(), capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    assert "Name=simulate.fpt-demo" in done.stdout and "JobState=COMPLETED" in done.stdout
    assert (out / "sim-86.ms").is_dir() and (out / "sim-230.ms").is_dir()


def test_calibrate_scheduler_slurm_matches_threads(tmp_path, new_pair):
    pytest.importorskip("dask_jobqueue", reason="dask-jobqueue missing: pip install 'hitops[hpc]'")
    from hitops.calibrate import calibrate_flat

    truth = new_pair(PairSpec(n_time=200, seed=43, n_scans=2))
    work = tmp_path / "slurm"
    work.mkdir()
    for ms in (truth.ref_ms, truth.target_ms):
        shutil.copytree(ms, work / Path(ms).name)
    calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    code = textwrap.dedent(f"""
        from hitops.calibrate import calibrate_flat
        calibrate_flat({str(work / 'ref.ms')!r}, {str(work / 'target.ms')!r}, method="pwc,cfpt",
                  scheduler="slurm:2")
    """)
    done = subprocess.run(["bash", str(SLURM_LOCAL), "run", "--", sys.executable, "-c", code],
                          env=_env(), cwd=work, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    # the workers were slurm jobs: each wrote its slurm-<jobid>.out in the cwd
    outs = sorted(work.glob("slurm-*.out"))
    assert len(outs) == 2, outs
    assert all("Starting Worker" in p.read_text() or "Start worker" in p.read_text()
               for p in outs), outs[0].read_text()[-2000:]
    for c in ("PWC_DATA", "CFPT_DATA", "FLAG"):
        with pt.table(str(truth.target_ms), ack=False) as a, \
                pt.table(str(work / "target.ms"), ack=False) as b:
            assert np.array_equal(a.getcol(c), b.getcol(c)), c
