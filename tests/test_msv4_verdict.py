"""The verdict of a run on MSv4 processing sets equals the verdict on the v2 sets they came from.

Truth: the same run on the Measurement Sets v2 that xradio converted (the verdict's
statistics are checked against the physics in tests/test_verdict.py).  Two synthetic
pairs with thermal noise and 3% of both bands' samples flagged: a short track the
verdict reads whole, and one long enough (9,000 steps) that it reads blocks of times
spread over it.  The report's verdict (per baseline and hand: the thermal scatter, the
window variances, the predicted change, the word; the closure check; what was sampled)
must be the v2 run's; with the v2 reference and the v4 target too.  Cost: about 15 s.
"""

from __future__ import annotations

import math

import pytest

pytest.importorskip("xradio")

from hitops.calibrate import calibrate_flat  # noqa: E402
from hitops.testing import PairSpec, Signal, Storage, Troposphere  # noqa: E402
from msv4_sets import convert, copies_of  # noqa: E402
from test_msv4_calibrate import _flag_some  # noqa: E402

pytestmark = pytest.mark.filterwarnings("ignore:.*Zarr V3 specification",
                                        "ignore:Consolidated metadata is currently not part")

NOISE = Signal(sigma_ref=0.05, sigma_target=0.08)
SPECS = {
    "whole": PairSpec(n_ant=4, n_time=600, n_scans=2, seed=21, signal=NOISE,
                      troposphere=Troposphere(phase_offset_rad=0.7)),
    "sampled": PairSpec(n_ant=4, n_time=9000, n_scans=3, seed=22, signal=NOISE,
                        storage=Storage(time_order=True)),
}


@pytest.fixture(scope="module")
def pairs(pair_store, tmp_path_factory):
    """{name: (v2 ref, v2 target, v4 ref, v4 target)}, built and converted once."""
    out = {}
    for name, spec in SPECS.items():
        root = tmp_path_factory.mktemp(f"v4verdict-{name}")
        pair = pair_store.copy(spec, root)
        _flag_some(pair.ref_ms, pair.target_ms)
        out[name] = (str(pair.ref_ms), str(pair.target_ms),
                     str(convert(pair.ref_ms, root / "ref.ps.zarr")),
                     str(convert(pair.target_ms, root / "tgt.ps.zarr")))
    return out



def assert_same_numbers(a, b, where: str = "verdict") -> None:
    """Equal numbers to float32 rounding of the visibilities (NaN = NaN), all else exactly."""
    if isinstance(a, dict):
        assert set(a) == set(b), where
        for k in a:
            assert_same_numbers(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same_numbers(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float):
        assert (math.isnan(a) and math.isnan(b)) or a == pytest.approx(b, rel=1e-5,
                                                                        abs=1e-9), where
    else:
        assert a == b, where


@pytest.mark.parametrize("name, reference", [("whole", "v4"), ("sampled", "v4"),
                                             ("sampled", "v2")])
def test_v4_verdict_is_the_v2_verdict(pairs, tmp_path, name, reference):
    ref2, tgt2, ref4, tgt4 = copies_of(pairs[name], tmp_path)
    r2 = calibrate_flat(ref2, tgt2, method="pwc", chunk_rows=10 ** 6)
    r4 = calibrate_flat(ref4 if reference == "v4" else ref2, tgt4, method="pwc",
                        chunk_rows=10 ** 6)
    v2, v4 = r2["verdict"], r4["verdict"]
    assert "error" not in v4 and len(v4["baselines"]) == 12     # 6 baselines x RR, LL
    assert v4["sampled"]["times_read"] < v4["sampled"]["times"] if name == "sampled" else \
        v4["sampled"]["times_read"] == v4["sampled"]["times"]
    assert any(math.isfinite(e["predicted_change"]) for e in v4["baselines"])
    assert_same_numbers(v4, v2)
