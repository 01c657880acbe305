"""The count tracker behind the one WrapTracker interface (issue 25), as calibrate drives it.

calibrate asks every tracker the same things per chunk: ``track_chunk`` -> a
ChunkTracking, one share per baseline batch (``for_batch``) resolved inside the
group's task, ``absorb`` of what each task carried, ``finish_chunk``.  The count
tracker's shares count inside the tasks from a carried sample; these tests hold
that path to the tracker's own whole-track counting on the grid (``track``), which
in turn tests/test_tracking.py holds to the paper's rule written out.
"""

from __future__ import annotations

import numpy as np
import pytest

from hitops.tracking.base import ChunkTracking, Tracked, TrackedWraps
from hitops.tracking.count import CountTracker
from track_grids import scan_grid  # tests/ is on sys.path (rootdir-relative)


def _phases(seed=5, n_bl=4, n_corr=2, n_time=300):
    """Wrapping phases (steps near pi, so wraps are frequent), flagged runs across chunk
    edges and scans, and four scans."""
    rng = np.random.default_rng(seed)
    true = np.cumsum(rng.normal(0.0, 1.3, (n_bl, n_corr, n_time)), axis=-1)
    phase = np.angle(np.exp(1j * true))
    valid = rng.random((n_bl, n_corr, n_time)) > 0.1
    valid[1, 0, 60:140] = False
    valid[3, :, 200:230] = False
    scan = np.repeat([0, 2, 3, 7], n_time // 4)
    return phase, valid, scan


@pytest.mark.parametrize("chunk", [1, 13, 64, 300])
@pytest.mark.parametrize("groups", [[[0, 1, 2, 3]], [[0], [1, 2], [3]]])
def test_count_shares_in_the_tasks_equal_the_tracker_on_the_whole_grid(chunk, groups):
    phase, valid, scan = _phases()
    n_bl, n_corr, n_time = phase.shape
    whole = CountTracker(scan_grid(scan, n_bl), ["RR", "LL"])
    expected = whole.track(0, 0, n_time, n_time, phase, valid, None).ref_wraps
    assert np.abs(np.diff(expected, axis=-1)).sum() > 50      # the case does wrap

    tracker = CountTracker(scan_grid(scan, n_bl), ["RR", "LL"])
    assert not tracker.grids_reference and not tracker.segmented
    got = np.zeros_like(expected)
    for t0 in range(0, n_time, chunk):
        t1 = min(t0 + chunk, n_time)
        assert tracker.extended(t0, t1) == (t0, t1)
        tracked = tracker.track_chunk(t0, t1, None)
        assert isinstance(tracked, ChunkTracking) and tracked.segment_keys is None
        assert tracked.with_segment_offsets({(0, 0, 5): 3}) is tracked
        shares = [(np.asarray(bls), tracked.for_batch(np.asarray(bls))) for bls in groups]
        for bls, share in shares:   # as the tasks do: every share made before any absorb
            resolved = share.resolve(phase[bls][..., t0:t1], valid[bls][..., t0:t1],
                                     scan[t0:t1])
            assert resolved.ref_phase is not None and resolved.ref_wraps.dtype == np.int64
            got[bls, :, t0:t1] = resolved.ref_wraps
            tracker.absorb(bls, resolved.carry, resolved.wrap_events)
        tracker.finish_chunk(t1)
    assert np.array_equal(got, expected)
    assert np.array_equal(tracker.stats.per_series["wrap_events"],
                          whole.stats.per_series["wrap_events"])
    assert tracker.report(scan)["baselines"] == whole.report(scan)["baselines"]


def test_a_gridded_trackers_share_is_its_slice_with_exclusions_and_model():
    """Tracked (smooth, antenna) -> one TrackedWraps per group: the group's counts, its
    excluded samples left invalid, and antenna mode's model phase transferred instead."""
    rng = np.random.default_rng(3)
    n_bl, n_corr, n_time = 3, 2, 8
    wraps = rng.integers(-3, 4, (n_bl, n_corr, n_time))
    exclude = rng.random((n_bl, n_corr, n_time)) > 0.7
    model = np.where(rng.random((n_bl, n_corr, n_time)) > 0.2,
                     rng.normal(0, 10, (n_bl, n_corr, n_time)), np.nan)
    model[:, 1] = np.nan                                  # a correlation without a model
    keys = np.full((n_bl, n_corr, n_time), 4, np.int64)
    tracked = Tracked(wraps, exclude, keys, model)
    bls = np.array([1, 2])
    share = tracked.for_batch(bls)
    assert isinstance(share, TrackedWraps)
    phase = rng.uniform(-np.pi, np.pi, (2, n_corr, n_time))
    valid = np.ones((2, n_corr, n_time), bool)
    out = share.resolve(phase, valid, np.zeros(n_time, np.int64))
    assert np.array_equal(out.ref_wraps, wraps[bls]) and out.carry is None
    assert not out.wrap_events.any()
    modelled = np.isfinite(model[bls])
    assert np.array_equal(out.ref_valid[:, 0], ~exclude[bls][:, 0] & modelled[:, 0])
    assert np.array_equal(out.ref_valid[:, 1], ~exclude[bls][:, 1])
    assert np.allclose(np.exp(1j * out.ref_phase[:, 0][modelled[:, 0]]),
                       np.exp(1j * model[bls][:, 0][modelled[:, 0]]))
    assert np.array_equal(out.ref_phase[:, 1], phase[:, 1])
    # the writing pass's per-segment integers: k added where the key matches, elsewhere none
    moved = tracked.with_segment_offsets({(2, 0, 4): 5})
    assert np.array_equal(moved.ref_wraps[2, 0], wraps[2, 0] + 5)
    assert np.array_equal(moved.ref_wraps[:2], wraps[:2])
    assert np.array_equal(tracked.ref_wraps, wraps)       # the input is not changed
