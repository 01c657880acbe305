"""Benchmarks of the MERRA-2 weather work (section ``weather-forecast`` of docs/forecast.md).

1. ``hitops simulate paper``: the paper's scene with MERRA-2 weather, 28 baselines,
   1 209 600 rows per band, both bands with troposphere, noise and truth, as its own
   process (wall, CPU, peak RSS), and in-process (best of 3); the tri-band scene too.
2. ``hitops forecast`` over the paper's eight stations and every month with data, and
   over all eleven stations, as processes.
3. The forecast's slip model against a direct simulation (hitops simulate + hitops
   calibrate --tracker count) on three baselines with the weather of 2018-04-10.

Run: ``python benchmarks/bench_forecast.py`` (about 2 minutes).
"""

from __future__ import annotations

import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import ROOT, machine_line, replace_section, run_process  # noqa: E402

DOC = ROOT / "docs" / "forecast.md"
HITOPS = [sys.executable, "-m", "hitops.cli"]


def main() -> None:
    from hitops.forecast.validate import direct_check
    from hitops.simulate import simulate

    rows, checks = [], []
    with tempfile.TemporaryDirectory(prefix="bench-forecast-") as tmp:
        work = Path(tmp)
        for scene in ("paper", "triband"):
            res = run_process([*HITOPS, "simulate", scene, "--outdir", work / scene, "--save-truth",
                               "--overwrite"])
            rows.append((f"`hitops simulate {scene}` (process, truth included)", res))
        best = float("inf")
        for _ in range(3):
            t0 = time.perf_counter()
            simulate("paper", work / "inproc", overwrite=True, save_truth=True)
            best = min(best, time.perf_counter() - t0)
        rows.append(("`simulate('paper')` in-process, best of 3", {"wall_s": best, "cpu_s": float("nan"),
                                                                  "peak_rss_mb": float("nan")}))
        for stations in ("paper", "all"):
            res = run_process([*HITOPS, "forecast", "--stations", stations, "--outdir",
                               work / f"fc-{stations}", "--overwrite"])
            rows.append((f"`hitops forecast --stations {stations}` (all months with data)", res))
        for codes, start in ((["PV", "PB"], "2018-04-10T00:00:00"),
                             (["AP", "GL"], "2018-04-10T02:00:00"),
                             (["KP", "SM"], "2018-04-10T06:00:00")):
            checks.append(direct_check(codes, work / "check", start=start, target_rho=2.0))

    lines = [f"Machine: {machine_line()}", "",
             "| run | wall (s) | CPU (s) | peak RSS (MB) |", "|---|---|---|---|"]
    for label, res in rows:
        lines.append(f"| {label} | {res['wall_s']:.2f} | {res['cpu_s']:.2f} | "
                     f"{res['peak_rss_mb']:.0f} |")
    lines += ["", "Slip model against a direct simulation (1 h at 1 s, RR and LL, MERRA-2 weather "
              "of 2018-04-10, 86 GHz flux scaled to a median per-sample SNR of 2):", "",
              "| baseline | start (UTC) | 86 GHz flux (Jy) | predicted failures | measured | "
              "(measured - predicted) / sqrt(predicted) |", "|---|---|---|---|---|---|"]
    for c, start in zip(checks, ("00:00", "02:00", "06:00")):
        lines.append(f"| {c['baseline']} | {start} | {c['flux_86_jy']:.4f} | "
                     f"{c['predicted_failures']:.1f} | {c['measured_failures']:.0f} | {c['z']:+.2f} |")
    text = "\n".join(lines)
    print(text)
    replace_section("weather-forecast", text, doc=DOC)


if __name__ == "__main__":
    main()
