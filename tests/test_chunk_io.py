"""The chunk loop's I/O thread and the chunk rows taken from the index pass.

* :class:`hitops.calibrate.chunk_io.ChunkIO` runs the reads and writes of a pass on
  one thread in the order they are asked for: a read and a write never overlap, the
  write of chunk k runs after the read of chunk k+1 and ends before the read of
  chunk k+2 starts (two chunks in memory, as the budget assumes), and a failed job
  raises in the caller.  With ``writes_apart`` (outputs to a processing set) the
  writes run on a second thread, one at a time and in chunk order, beside the reads.
* A time-ordered set read in several chunks takes each chunk's baselines and times
  from the index pass (:meth:`hitops.calibrate.chunks.GroupMatch.rows_from_index`)
  instead of reading ANTENNA1/2 again: the rows must be exactly those the re-read gives,
  and a TIME changed after the index pass must still be refused.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from casacore import tables as pt

from hitops.calibrate import calibrate_flat
from hitops.calibrate.chunk_io import ChunkIO
from hitops.errors import MeasurementSetError
from hitops.testing import PairSpec
from hitops.testing.pairs import Storage

from ms_columns import col  # tests/ is on sys.path (rootdir-relative)


class _Recorder:
    """Reads and writes that log when they start and end, and on which thread."""

    def __init__(self):
        self.events, self.active, self.threads = [], 0, set()
        self.lock = threading.Lock()

    def _job(self, name):
        with self.lock:
            self.active += 1
            overlap = self.active > 1
            self.events.append(("start", name))
            self.threads.add(threading.current_thread().name)
        time.sleep(0.01)
        with self.lock:
            self.active -= 1
            self.events.append(("end", name))
        if overlap:
            raise AssertionError(f"{name} overlapped another job")

    def read(self, k):
        self._job(f"r{k}")
        return k

    def write(self, k):
        self._job(f"w{k}")


def _loop(io: ChunkIO, rec: _Recorder, n: int):
    """The pipeline's order of asking: chunk k, its kernels, read k+1, write k."""
    for k in range(n):
        assert io.chunk(k) == k
        io.read_ahead(k + 1)
        io.write(rec.write, k)


def test_reads_and_writes_run_one_at_a_time_in_the_pipelines_order():
    rec = _Recorder()
    with ChunkIO(rec.read, 5) as io:
        _loop(io, rec, 5)
    starts = [name for kind, name in rec.events if kind == "start"]
    assert starts == ["r0", "r1", "w0", "r2", "w1", "r3", "w2", "r4", "w3", "w4"]
    # one job at a time, each ended before the next started, all on the I/O thread
    assert all(a[0] == "start" and b == ("end", a[1])
               for a, b in zip(rec.events[::2], rec.events[1::2]))
    assert len(rec.threads) == 1 and next(iter(rec.threads)).startswith("hitops-io")


class _Apart(_Recorder):
    """Reads and writes on their own threads: a read and a write may overlap, two reads
    or two writes may not."""

    def __init__(self):
        super().__init__()
        self.active_of = {"r": 0, "w": 0}
        self.overlapped = []
        self.thread_of = {}

    def _job(self, name):
        kind = name[0]
        with self.lock:
            if self.active_of[kind]:
                self.overlapped.append(name)
            self.active_of[kind] += 1
            self.events.append(("start", name))
            self.thread_of[name] = threading.current_thread().name
        # long enough that a read and a write asked for together are seen at once, even
        # on a loaded machine
        time.sleep(0.05)
        with self.lock:
            self.active_of[kind] -= 1
            self.events.append(("end", name))


def test_writes_apart_run_on_their_own_thread_in_chunk_order_beside_the_reads():
    rec = _Apart()
    with ChunkIO(rec.read, 6, writes_apart=True) as io:
        _loop(io, rec, 6)
    assert not rec.overlapped                      # one read at a time, one write at a time
    writes = [name for kind, name in rec.events if kind == "start" and name[0] == "w"]
    assert writes == [f"w{k}" for k in range(6)]
    assert {rec.thread_of[f"w{k}"] for k in range(6)} == {"hitops-write_0"}
    assert {rec.thread_of[f"r{k}"] for k in range(6)} == {"hitops-io_0"}
    # a write ends before the next is asked for: at most one chunk held for writing
    for k in range(1, 6):
        assert rec.events.index(("end", f"w{k - 1}")) < rec.events.index(("start", f"w{k}"))
    # the one-thread order would never have a read start while a write runs
    running, beside = set(), 0
    for kind, name in rec.events:
        if kind == "start" and name[0] == "r" and any(n[0] == "w" for n in running):
            beside += 1
        (running.add if kind == "start" else running.discard)(name)
    assert beside > 0


def test_one_chunk_is_read_and_written_on_the_calling_thread():
    """Nothing to overlap: no thread (a fresh thread's allocations cost more, measured)."""
    rec = _Recorder()
    with ChunkIO(rec.read, 1) as io:
        _loop(io, rec, 1)
    assert [name for kind, name in rec.events if kind == "start"] == ["r0", "w0"]
    assert rec.threads == {threading.current_thread().name}

    def failing(k):
        raise OSError("disk full (simulated)")

    with pytest.raises(OSError, match="simulated"):
        with ChunkIO(rec.read, 1) as io:
            io.chunk(0)
            io.write(failing, 0)


@pytest.mark.parametrize("apart", [False, True], ids=["one-thread", "writes-apart"])
def test_a_failed_write_raises_in_the_caller_and_later_jobs_do_not_run(apart):
    rec = _Apart() if apart else _Recorder()

    def failing_write(k):
        if k == 1:
            raise OSError("disk full (simulated)")
        rec.write(k)

    with pytest.raises(OSError, match="simulated"):
        with ChunkIO(rec.read, 6, writes_apart=apart) as io:
            for k in range(6):
                io.chunk(k)
                io.read_ahead(k + 1)
                io.write(failing_write, k)
    written = [name for kind, name in rec.events if kind == "start" and name[0] == "w"]
    assert written == ["w0"]
    read = [name for kind, name in rec.events if kind == "start" and name[0] == "r"]
    assert read[-1] in ("r2", "r3")     # nothing asked after the failure showed


def test_a_failed_read_raises_where_the_chunk_is_taken():
    def read(k):
        if k == 2:
            raise MeasurementSetError("x.ms: TIME changed while it was being read")
        return k

    with pytest.raises(MeasurementSetError, match="TIME changed"):
        with ChunkIO(read, 4) as io:
            for k in range(4):
                io.chunk(k)
                io.read_ahead(k + 1)


def test_chunk_rows_from_the_index_are_those_a_reread_gives(new_pair):
    """A time-ordered pair with flagged rows and a missing baseline, cut into chunks: the
    rows taken from the index equal index_rows on the re-read metadata, chunk by chunk."""
    import hitops.calibrate.chunk_read as chunk_read

    truth = new_pair(PairSpec(n_time=300, seed=31, storage=Storage(time_order=True)))
    with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
        flag_row = t.getcol("FLAG_ROW")
        flag_row[::11] = True
        t.putcol("FLAG_ROW", flag_row)
    compared = []
    original = chunk_read._chunk_rows

    def both(match, which, rows, meta):
        got = original(match, which, rows, meta)
        band = match.tgt if which == "tgt" else match.ref
        if band.pair_key is not None:
            reread = match.index_rows(which, match.read_meta(
                which, rows, ["TIME", "ANTENNA1", "ANTENNA2", "SCAN_NUMBER", "FLAG_ROW",
                              "ROWID"]))
            for name in ("rows", "bl", "time", "swapped", "flag_row"):
                a, b = getattr(got, name), getattr(reread, name)
                assert (a is None and b is None) or np.array_equal(a, b), (which, name)
                assert a is None or a.dtype == b.dtype, (which, name)
            compared.append(which)
        return got

    chunk_read._chunk_rows = both
    try:
        report = calibrate_flat(truth.ref_ms, truth.target_ms, chunk_rows=400)
    finally:
        chunk_read._chunk_rows = original
    assert report["chunks"] > 2 and {"tgt", "ref"} <= set(compared)


def test_a_time_changed_after_the_index_pass_is_refused_and_nothing_is_written(new_pair,
                                                                              monkeypatch):
    import hitops.calibrate.chunks as chunks

    truth = new_pair(PairSpec(n_time=300, seed=32, storage=Storage(time_order=True)))
    before = {c: col(truth.target_ms, c) for c in ("DATA", "FLAG")}
    original = chunks.GroupMatch.check

    def check_then_change(self, *args, **kwargs):
        out = original(self, *args, **kwargs)
        with pt.table(str(truth.target_ms), readonly=False, ack=False) as t:
            last = t.nrows() - 1
            t.putcell("TIME", last, t.getcell("TIME", last) + 0.25)
        return out

    monkeypatch.setattr(chunks.GroupMatch, "check", check_then_change)
    with pytest.raises(MeasurementSetError, match="TIME changed while it was being read"):
        calibrate_flat(truth.ref_ms, truth.target_ms, chunk_rows=400)
    with pt.table(str(truth.target_ms), ack=False) as t:
        assert "PWC_DATA" not in t.colnames()
    for c, value in before.items():
        assert np.array_equal(col(truth.target_ms, c), value), c


def test_cell_kernels_agree_with_the_numpy_form():
    """band_cells / mark_cells / count_marked against the NumPy statements they replace,
    on random chunks with pairs that have no baseline and repeated cells."""
    from hitops.kernels.cells import band_cells, count_marked, mark_cells

    rng = np.random.default_rng(7)
    for _ in range(20):
        n_key, n_bl, n_u = 36, 15, int(rng.integers(1, 40))
        pair_bl = np.where(rng.random(n_key) < 0.2, -1, rng.integers(0, n_bl, n_key))
        time_rows = rng.integers(1, 9, n_u)
        t0 = int(rng.integers(0, 50))
        time_index = t0 + np.sort(rng.choice(60, n_u, replace=False))
        n_t = int(time_index.max()) - t0 + 1
        key = rng.integers(0, n_key, int(time_rows.sum())).astype(np.uint16)
        # the NumPy form: a repeat of each time's index, the pair's baseline, the cell
        time = np.repeat(time_index, time_rows)
        bl = pair_bl[key]
        expected = np.where(bl >= 0, bl * n_t + (time - t0), -1)
        cells = band_cells(key, pair_bl, time_rows, time_index, t0, n_t)
        assert np.array_equal(cells, expected)
        used = cells[cells >= 0]
        held, shared = mark_cells(cells, n_bl * n_t)
        numpy_held = np.zeros(n_bl * n_t, bool)
        numpy_held[used] = True
        assert np.array_equal(held, numpy_held)
        assert shared == used.size - np.count_nonzero(numpy_held)
        other = rng.random(n_bl * n_t) < 0.5
        assert count_marked(cells, other) == np.count_nonzero(other[used])
        # cell -1 must not count: read as an index it would be the last cell
        assert count_marked(np.array([-1], np.int64), np.ones(3, bool)) == 0
