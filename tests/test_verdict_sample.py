"""What the verdict reads (hitops/calibrate/verdict_sample.py): blocks of times, the same
grid whatever the table's row order, and no increment across two blocks."""

from __future__ import annotations

import numpy as np
import pytest
from casacore import tables as pt

from hitops.testing import PairSpec, Signal, Storage
from hitops.calibrate.verdict_sample import choose_blocks, read_sampled, read_times
from hitops.io.read import MAX_RUNS

N_TIME = 4000


def test_short_tracks_are_read_whole_long_ones_in_even_blocks():
    times = 5.1e9 + np.arange(N_TIME, dtype=float)
    whole = choose_blocks(times[:900], n_window=60, max_pairs=500)
    assert whole.whole and whole.n_time_read == 900
    blocks = choose_blocks(times, n_window=20, max_pairs=500)
    n_block = -(-500 // 21)                   # 21 pairs at lag 19 per 40-time block
    assert blocks.lo.size == n_block and blocks.n_time_read == n_block * 40
    assert np.all(blocks.hi - blocks.lo == 39)            # 2 x n_window consecutive times
    assert np.all(blocks.lo[1:] > blocks.hi[:-1])         # disjoint, in order
    assert blocks.lo[0] == times[0] and blocks.hi[-1] == times[-1]   # spread over the track
    gaps = np.diff(blocks.lo)
    assert gaps.max() - gaps.min() <= 1                    # evenly


@pytest.fixture
def pairs(shared_pair):
    # only read
    kw = dict(n_ant=8, n_time=N_TIME, seed=8, n_scans=3,
              signal=Signal(sigma_ref=0.05, sigma_target=0.1))
    return (shared_pair(PairSpec(storage=Storage(time_order=True), **kw)),
            shared_pair(PairSpec(**kw)))


def test_the_same_grid_from_runs_of_rows_and_from_a_row_selection(pairs):
    """A table in time order is read as runs of rows, a baseline-major one through one row
    selection: the same rows, the same grid."""
    by_time, by_baseline = pairs
    times = np.unique(read_times(str(by_time.target_ms)))
    blocks = choose_blocks(times, n_window=20, max_pairs=500)
    assert not blocks.whole
    # 28 baselines x 24 blocks: more row runs than MAX_RUNS in the baseline-major table
    assert 28 * blocks.lo.size > MAX_RUNS
    grids = [read_sampled(str(p.target_ms), "DATA", read_times(str(p.target_ms)), blocks)
             for p in pairs]
    a, b = grids
    assert a.times.size == blocks.n_time_read
    for name in ("ant1", "ant2", "times", "segment", "flag", "vis", "sigma"):
        assert np.array_equal(getattr(a, name), getattr(b, name), equal_nan=name == "sigma"), name
    # every sampled value is the table's own
    with pt.table(str(by_time.target_ms), ack=False) as t:
        time, data = t.getcol("TIME"), t.getcol("DATA")
        ant1, ant2 = t.getcol("ANTENNA1"), t.getcol("ANTENNA2")
    k = np.flatnonzero((ant1 == a.ant1[1]) & (ant2 == a.ant2[1]) & np.isin(time, a.times))
    assert np.array_equal(a.vis[1], data[k, 0, :])


def test_no_segment_spans_two_blocks(pairs):
    by_time, _ = pairs
    time = read_times(str(by_time.target_ms))
    blocks = choose_blocks(np.unique(time), n_window=20, max_pairs=500)
    grid = read_sampled(str(by_time.target_ms), "DATA", time, blocks)
    block = np.searchsorted(blocks.lo, grid.times, side="right") - 1
    for b in range(grid.n_bl):
        same = grid.segment[b, 1:] == grid.segment[b, :-1]
        assert not np.any(same & (block[1:] != block[:-1]))   # never across a block edge
        assert np.all(same | (block[1:] != block[:-1]) | (np.diff(grid.segment[b]) != 0))
