"""The least program that does PWC on a processing-set pair: issue 37's floor plus one kernel.

The zarr floor (:data:`benchmarks.bench_msv4._FLOOR_PROCESS`) reads both bands and
writes one data group, and computes nothing.  This module is the least that a PWC run
must add to it, written as plainly and as fast as this machine allows, so that
``hitops calibrate`` can be judged against what the method itself costs here:

* the floor's reads and writes, in time chunks: one thread reads chunk k+1 while two
  threads run the kernel on chunk k (half the baselines each) and a fourth writes
  chunk k-1;
* the reference phase as NumPy's float64 arctangent (a vector loop on this machine:
  docs/performance.md, "What one process here cannot go below");
* one fused numba kernel per baseline half: a sample is used when both bands' flags
  are clear and the reference is finite and non-zero; the wrap count is carried from
  one used sample to the next (the count tracker's plainest rule: the nearest integer
  to the phase step over 2 pi), and the target is turned by
  ``-R phi_cal + 2 pi eps n`` (paper eq. pwc, hitops/kernels/fpt.py).

What it leaves out, and hitops does not: the input checks and the refusals, the
pairing of partitions, fields, windows, stations and times (it takes one partition per
band holding the same grid, as the benchmark pair does), the tracker's jump and SNR
rules and its context across chunks, the n0 step, staging and rollback (it writes its
arrays straight into the store), the run report and the log.  On the benchmark's pair
its output equals ``hitops calibrate --method pwc``'s data group to float32 rounding
with the same flags (:func:`compare`, which the benchmark runs), so it does the same
work on that pair.

Run as a process: ``python -m benchmarks.least_pwc REF_PS TGT_PS TAG``; it writes
``FLOOR_<TAG>_VISIBILITY_0`` and ``FLOOR_<TAG>_FLAG_0`` into each target partition
(named like the floor's arrays, so that :func:`benchmarks.bench_msv4._floor_arrays_removed`
takes them off again).
"""

from __future__ import annotations

import math
import sys
import warnings
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numba
import numpy as np

TWO_PI = 2.0 * math.pi
#: time steps per chunk (x 28 baselines: 700,000 rows, about hitops's default chunk)
CHUNK_STEPS = 25_000


class WrapState(NamedTuple):
    """What one baseline half carries from a chunk to the next, (n_bl, n_corr) each."""

    last: np.ndarray        # float64: the last used reference phase
    has_last: np.ndarray    # bool
    count: np.ndarray       # int64: wraps so far (n, unwrap(phi) = phi - 2 pi n)


class HalfOutput(NamedTuple):
    vis: np.ndarray         # (n_time, n_bl, n_chan, n_corr) complex64
    flag: np.ndarray        # (n_time, n_bl, n_chan, n_corr) bool
    state: WrapState


@numba.njit(cache=True, nogil=True)
def pwc_cells(ref_phase, ref_vis, ref_flag, tgt_vis, tgt_flag, ratio, eps, last, has_last,
              count):
    """PWC of one chunk's cells; the inputs are not changed.

    ref_phase (n_time, n_bl, n_corr) float64; ref_vis, ref_flag, tgt_vis, tgt_flag
    (n_time, n_bl, 1, n_corr); last, has_last, count (n_bl, n_corr) the carried state.
    Returns the calibrated target, its flags and the state after the chunk."""
    n_time, n_bl, _, n_corr = tgt_vis.shape
    out = np.empty(tgt_vis.shape, np.complex64)
    flag = np.empty(tgt_flag.shape, np.bool_)
    last, has_last, count = last.copy(), has_last.copy(), count.copy()
    two_pi_eps = TWO_PI * eps
    for t in range(n_time):
        for b in range(n_bl):
            for c in range(n_corr):
                r = ref_vis[t, b, 0, c]
                re, im = np.float64(r.real), np.float64(r.imag)
                if (ref_flag[t, b, 0, c] or tgt_flag[t, b, 0, c] or not math.isfinite(re)
                        or not math.isfinite(im) or (re == 0.0 and im == 0.0)):
                    out[t, b, 0, c] = 0
                    flag[t, b, 0, c] = True
                    continue
                phi = ref_phase[t, b, c]
                if has_last[b, c]:
                    # a step of about -2 pi is a wrap upwards: n counts it as -1
                    count[b, c] -= int(math.floor((last[b, c] - phi) / TWO_PI + 0.5))
                last[b, c] = phi
                has_last[b, c] = True
                theta = -ratio * phi + two_pi_eps * count[b, c]
                out[t, b, 0, c] = tgt_vis[t, b, 0, c] * complex(math.cos(theta), math.sin(theta))
                flag[t, b, 0, c] = False
    return out, flag, last, has_last, count


def _half(ref_vis, ref_flag, tgt_vis, tgt_flag, ratio, eps, state: WrapState) -> HalfOutput:
    ref = ref_vis[:, :, 0, :]
    phase = np.arctan2(ref.imag.astype(np.float64), ref.real.astype(np.float64))
    vis, flag, *carried = pwc_cells(phase, ref_vis, ref_flag, tgt_vis, tgt_flag, ratio, eps,
                                    *state)
    return HalfOutput(vis, flag, WrapState(*carried))


def _partitions(ps: Path):
    return sorted(p.name for p in ps.iterdir() if (p / "zarr.json").is_file())


def run(ref_ps: Path, tgt_ps: Path, tag: str) -> None:
    import zarr

    ref_names, tgt_names = _partitions(ref_ps), _partitions(tgt_ps)
    if len(ref_names) != len(tgt_names):
        raise SystemExit(f"{ref_ps} holds {len(ref_names)} partitions and {tgt_ps} "
                         f"{len(tgt_names)}: the least program pairs them in name order, one "
                         "to one (the benchmark's one-channel pair)")
    for ref_name, tgt_name in zip(ref_names, tgt_names):
        ref = zarr.open_group(str(ref_ps), path=ref_name, mode="r", use_consolidated=False)
        tgt = zarr.open_group(str(tgt_ps), path=tgt_name, mode="r+", use_consolidated=False)
        if ref["VISIBILITY"].shape != tgt["VISIBILITY"].shape or tgt["VISIBILITY"].shape[2] != 1:
            raise SystemExit(f"partitions {ref_name} and {tgt_name}: VISIBILITY "
                             f"{ref['VISIBILITY'].shape} against {tgt['VISIBILITY'].shape}; the "
                             "least program takes one channel on the same (time, baseline) grid")
        _run_partition(ref, tgt, tag)


def _run_partition(ref, tgt, tag: str) -> None:
    ratio = float(tgt["frequency"][0]) / float(ref["frequency"][0])
    eps = ratio - math.floor(ratio)
    arrays = (ref["VISIBILITY"], ref["FLAG"], tgt["VISIBILITY"], tgt["FLAG"])
    outputs = [tgt.create_array(f"FLOOR_{tag}_{like}_0", shape=tgt[like].shape,
                                dtype=tgt[like].dtype, chunks=tgt[like].chunks,
                                compressors=tgt[like].compressors)
               for like in ("VISIBILITY", "FLAG")]
    n_time, n_bl, _, n_corr = arrays[2].shape
    halves = ((0, n_bl // 2), (n_bl // 2, n_bl))
    states = [WrapState(np.zeros((hi - lo, n_corr)), np.zeros((hi - lo, n_corr), bool),
                        np.zeros((hi - lo, n_corr), np.int64)) for lo, hi in halves]
    starts = list(range(0, n_time, CHUNK_STEPS))

    def read(t0):
        return [a[t0:t0 + CHUNK_STEPS] for a in arrays]

    def write(t0, vis, flag):
        outputs[0][t0:t0 + vis.shape[0]] = vis
        outputs[1][t0:t0 + vis.shape[0]] = flag

    with ThreadPoolExecutor(1) as reader, ThreadPoolExecutor(2) as kernels, \
            ThreadPoolExecutor(1) as writer:
        pending, written = reader.submit(read, starts[0]), None
        for k, t0 in enumerate(starts):
            chunk = pending.result()
            if k + 1 < len(starts):
                pending = reader.submit(read, starts[k + 1])
            parts = [kernels.submit(_half, *(a[:, lo:hi] for a in chunk), ratio, eps, state)
                     for (lo, hi), state in zip(halves, states)]
            done = [p.result() for p in parts]
            states = [d.state for d in done]
            vis = np.concatenate([d.vis for d in done], axis=1)
            flag = np.concatenate([d.flag for d in done], axis=1)
            if written is not None:
                written.result()
            written = writer.submit(write, t0, vis, flag)
        written.result()


def compare(tgt_ps: Path, tag: str, group: str = "PWC") -> dict:
    """This program's arrays ``tag`` against hitops's data group ``group`` in every target
    partition: the largest difference relative to hitops's amplitude where neither is
    flagged, and whether the flags are the same."""
    import zarr

    worst, same_flags = 0.0, True
    for name in _partitions(tgt_ps):
        part = zarr.open_group(str(tgt_ps), path=name, mode="r", use_consolidated=False)
        ours, theirs = part[f"FLOOR_{tag}_VISIBILITY_0"][...], part[f"VISIBILITY_{group}"][...]
        our_flag, their_flag = part[f"FLOOR_{tag}_FLAG_0"][...], part[f"FLAG_{group}"][...]
        same_flags &= bool(np.array_equal(our_flag, their_flag))
        used = ~our_flag & ~their_flag
        if used.any():
            diff = np.abs(ours[used] - theirs[used]) / np.maximum(np.abs(theirs[used]), 1e-30)
            worst = max(worst, float(diff.max()))
    return {"max_relative": worst, "same_flags": same_flags}


if __name__ == "__main__":
    warnings.filterwarnings("ignore")   # zarr's notes on xradio's string arrays, as the floor
    run(Path(sys.argv[1]), Path(sys.argv[2]), sys.argv[3])
