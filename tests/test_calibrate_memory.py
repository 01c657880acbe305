"""--memory-budget: the rows held at once follow from it; the output does not depend on it."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from hitops.calibrate import calibrate_flat
from hitops.calibrate.memory import bytes_per_row, parse_budget, rows_for_budget
from hitops.testing import PairSpec, Troposphere
from hitops.errors import InputError

from ms_columns import col  # tests/ is on sys.path (rootdir-relative)


def test_budget_sizes_and_refusals():
    assert parse_budget("800MB") == 800_000_000
    assert parse_budget("1.5GiB") == int(1.5 * 2 ** 30)
    assert 0 < parse_budget("auto") <= 1_000_000_000
    for bad in ("lots", "12 parsecs", "100MB"):        # the last is below the fixed part
        with pytest.raises(InputError, match="--memory-budget"):
            parse_budget(bad)
    # more correlations, channels or methods: fewer rows per chunk
    assert bytes_per_row(4, 1, 3) > bytes_per_row(4, 1, 1) > bytes_per_row(2, 1, 1)
    assert bytes_per_row(4, 8, 1) > bytes_per_row(4, 1, 1)
    # the rows both bands keep for the whole run come off the budget first
    assert rows_for_budget(10 ** 9, 10 ** 7, 4, 1, 1) < rows_for_budget(10 ** 9, 10 ** 6, 4, 1, 1)


def test_a_small_budget_chunks_the_run_and_changes_nothing(tmp_path, new_pair):
    truth = new_pair(PairSpec(n_ant=6, n_time=4000, n_scans=2, seed=8,
                              troposphere=Troposphere(phase_offset_rad=1.0)))
    other = tmp_path / "copy.ms"
    shutil.copytree(truth.target_ms, other)
    whole = calibrate_flat(truth.ref_ms, truth.target_ms, method="pwc,cfpt")
    # 15 baselines x 4000 times = 60 000 rows per band: a 310 MB budget leaves room for a
    # few thousand rows per chunk (hitops/calibrate/memory.py)
    small = calibrate_flat(truth.ref_ms, str(other), method="pwc,cfpt", memory_budget="310MB")
    assert whole["chunks"] == 1 and small["chunks"] > 3
    for column in ("PWC_DATA", "CFPT_DATA", "FLAG"):
        np.testing.assert_array_equal(col(str(other), column), col(truth.target_ms, column))


def test_several_chunks_leave_room_for_the_next_chunks_read():
    """A run that fits one chunk gets it whole; one that does not also holds the next
    chunk's read (hitops/calibrate/pipeline.py reads ahead), so its chunks are smaller;
    a table dask-ms must sort costs more per row; the default budget never refuses."""
    from hitops.calibrate.memory import (FIXED_BYTES, MIN_CHUNK_ROWS, ORDER_BYTES_PER_ROW,
                                         read_bytes_per_row)

    per_row = bytes_per_row(4, 1, 1)
    budget = FIXED_BYTES + 1000 * per_row * 1000
    fits = rows_for_budget(budget, 1000, 4, 1, 1)
    assert fits == (budget - FIXED_BYTES - ORDER_BYTES_PER_ROW * 1000) // per_row
    big = 2 * 10 ** 6
    room = budget - FIXED_BYTES - ORDER_BYTES_PER_ROW * big
    assert rows_for_budget(budget, big, 4, 1, 1) == room // (per_row + read_bytes_per_row(4, 1))
    assert rows_for_budget(budget, big, 4, 1, 1, time_ordered=False) < room // (
        per_row + read_bytes_per_row(4, 1))
    # outputs to a processing set: the chunk being written is held beside the next read
    assert rows_for_budget(budget, big, 4, 1, 1, writes_apart=True) == room // (
        2 * per_row + read_bytes_per_row(4, 1))
    assert rows_for_budget(budget, 1000, 4, 1, 1, writes_apart=True) == fits
    with pytest.raises(InputError, match="leave no room"):
        rows_for_budget(budget, 10 ** 8, 4, 1, 1)
    assert rows_for_budget(budget, 10 ** 8, 4, 1, 1, strict=False) == MIN_CHUNK_ROWS


def test_a_tracker_that_grids_the_reference_leaves_room_for_it():
    """The smooth and antenna trackers' chunk work (per target row and correlation) and
    the antenna tracker's whole-track records (every station's phase and segment, 16
    bytes per station, correlation and time step, in two trackers) shrink the chunks;
    the count tracker's work is in bytes_per_row already."""
    from hitops.calibrate.memory import (FIXED_BYTES, LOCAL_ORDER_BYTES_PER_ROW,
                                         TRACKER_BYTES_PER_CORR, read_bytes_per_row,
                                         tracker_bytes)

    n_rows, n_ant, n_corr = 10 ** 7, 8, 2
    count = tracker_bytes("count", n_corr, n_rows, n_ant)
    smooth = tracker_bytes("smooth", n_corr, n_rows, n_ant)
    antenna = tracker_bytes("antenna", n_corr, n_rows, n_ant)
    assert count.per_row == count.per_run == smooth.per_run == 0
    assert smooth.per_row == n_corr * TRACKER_BYTES_PER_CORR["smooth"] > 0
    assert antenna.per_row == n_corr * TRACKER_BYTES_PER_CORR["antenna"] > 0
    # 28 baselines at every step: 357,142.9 steps; two trackers' phases and segments
    assert antenna.per_run == int(2 * 16 * n_ant * n_corr * n_rows / 28)
    budget = 10 ** 9
    args = (budget, 2 * n_rows, n_corr, 1, 1, True, False, True)
    rows = {name: rows_for_budget(*args, tracker=t)
            for name, t in (("count", count), ("smooth", smooth), ("antenna", antenna))}
    assert rows["count"] > rows["smooth"] > rows["antenna"]
    room = budget - FIXED_BYTES - LOCAL_ORDER_BYTES_PER_ROW * 2 * n_rows - antenna.per_run
    assert rows["antenna"] == room // (bytes_per_row(n_corr, 1, 1) + antenna.per_row
                                       + read_bytes_per_row(n_corr, 1))
    # no stations to track: no records
    assert tracker_bytes("antenna", n_corr, n_rows, 1).per_run == 0


def test_the_paper_size_pair_stays_in_one_chunk_with_every_tracker():
    """The paper's scene (8 stations, 43,200 steps, RR LL: 1,209,600 rows per band; its
    one-chunk runs peak at 0.61, 0.84 and 0.93 GB with count, smooth and antenna) is one
    chunk under the default budget whatever the tracker, so its verdict is made."""
    from hitops.calibrate.memory import tracker_bytes

    n_rows = 1_209_600
    for name in ("count", "smooth", "antenna"):
        rows = rows_for_budget(10 ** 9, 2 * n_rows, 2, 1, 3, True, False, True,
                               tracker=tracker_bytes(name, 2, n_rows, 8))
        assert rows >= n_rows, name
