"""Wideband simulated sets through real CASA: listobs sees every window, fringefit finds the
instrumental delay the scene put in (truth: the scene)."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from hitops.simulate import simulate
from hitops.simulate.scene import load_scene_mapping

CASA_SCRIPT = r"""
import json, sys
from hitops.casa_env import ensure_casa_offline
ensure_casa_offline()
from casatasks import listobs, fringefit
from casatools import table
ms, work = sys.argv[1:3]
summary = listobs(vis=ms, listfile=f"{work}/listobs.txt", overwrite=True)
fringefit(vis=ms, caltable=f"{work}/ff.tbl", solint="inf", refant="PV", minsnr=3,
          combine="")
tb = table()
tb.open(f"{work}/ff.tbl")
out = {"listobs": open(f"{work}/listobs.txt").read(),
       "ant": tb.getcol("ANTENNA1").tolist(), "spw": tb.getcol("SPECTRAL_WINDOW_ID").tolist(),
       "flag": tb.getcol("FLAG")[:, 0, :].tolist(), "fparam": tb.getcol("FPARAM")[:, 0, :].tolist()}
tb.close()
print("RESULT" + json.dumps(out))
"""


@pytest.mark.slow
def test_casa_fringefit_recovers_the_instrumental_delay(tmp_path):
    scene, _ = load_scene_mapping("demo")
    scene["observation"].update({"duration": 600, "integration": 2})
    for key in ("scan_length", "scan_gap"):
        scene["observation"].pop(key)
    scene["bands"] = [{"name": "86", "freq_ghz": 86, "bandwidth_ghz": 2},
                      {"name": "230", "freq_ghz": 228.1, "bandwidth_ghz": 2, "n_chan": 32,
                       "windows_ghz": [227.1, 229.1]}]
    scene["corruptions"].update({"noise": False, "troposphere": False})
    delays_ns = {"AP": 0.4, "GL": -0.25, "PB": 0.1, "KP": 0.0}
    scene["stations"] = [{"code": c, "bands": {"230": {"instrumental": {"delay_ns": d}}}}
                         for c, d in delays_ns.items()] + ["PV"]
    paths = simulate(scene, tmp_path)
    proc = subprocess.run([sys.executable, "-c", CASA_SCRIPT, str(paths["230"]), str(tmp_path)],
                          capture_output=True, text=True, cwd=tmp_path, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout.split("RESULT", 1)[1])
    assert "(2 unique spectral windows" in out["listobs"]
    assert sorted(set(out["spw"])) == [0, 1]
    codes = ["AP", "GL", "PB", "KP", "PV"]            # ANTENNA order = scene order
    fparam = np.array(out["fparam"])                 # (4 per pol: phase, delay, rate, disp; row)
    for row, (ant, spw) in enumerate(zip(out["ant"], out["spw"])):
        code = codes[ant]
        found = fparam[1, row]                          # RR delay, ns, relative to PV (0)
        assert not out["flag"][0][row]
        # CASA's antenna delay tau_p enters V_pq as exp(i 2 pi nu (tau_p - tau_q))
        # with the same sign as the simulator's (checked: both windows, every station)
        assert found == pytest.approx(delays_ns.get(code, 0.0), abs=2e-3), (code, spw, found)
