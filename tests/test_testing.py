"""The test support itself: hitops.testing stays out of production, and the session's
shared pairs (tests/conftest.py) are what a fresh build would give and stay unspoilt."""

from __future__ import annotations

import numpy as np

from hitops.testing import PairSpec, Storage, Troposphere, make_pair
from ms_columns import col, put  # tests/ is on sys.path (rootdir-relative)
from test_layout import import_graph


def test_production_code_never_imports_the_test_support():
    graph = import_graph()
    assert "hitops.testing.pairs" in graph and "hitops.testing.slips" in graph
    users = {name: sorted(d for d in deps if d.startswith("hitops.testing"))
             for name, deps in graph.items() if not name.startswith("hitops.testing")}
    assert {name: deps for name, deps in users.items() if deps} == {}


def test_a_copy_is_a_fresh_build_and_writing_into_it_spoils_nothing(pair_store, new_pair,
                                                                  tmp_path):
    spec = PairSpec(n_time=30, seed=4, troposphere=Troposphere(phase_offset_rad=1.0),
                    storage=Storage(shuffle_target=True))
    fresh = make_pair(tmp_path / "fresh", spec)
    copy = new_pair(spec, tmp_path / "copy")
    built = pair_store.built(spec)
    assert copy.target_ms.parent == tmp_path / "copy" and copy.ref_ms != built.ref_ms
    for name in ("TIME", "ANTENNA1", "ANTENNA2", "DATA", "FLAG"):
        for ms in ("ref_ms", "target_ms"):
            assert np.array_equal(col(getattr(copy, ms), name), col(getattr(fresh, ms), name))
    np.testing.assert_array_equal(copy.source_phase, fresh.source_phase)
    # a test writes into its copy and its truth: the session's build keeps what it had
    put(copy.target_ms, "DATA", np.zeros_like(col(copy.target_ms, "DATA")))
    copy.time[:] = 0.0
    assert np.array_equal(col(built.target_ms, "DATA"), col(fresh.target_ms, "DATA"))
    assert np.array_equal(built.time, fresh.time)
    assert pair_store.built(spec) is built                  # built once per session
