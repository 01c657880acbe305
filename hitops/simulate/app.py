"""Entry point of ``hitops simulate`` (parameters from hitops/schemas/simulate.yml)."""

from __future__ import annotations

from .api import simulate


def run(scene, outdir, prefix="sim", seed=None, save_truth=False, overwrite=False,
        duration=None, integration=None, coherence_scale=None, no_noise=False,
        no_troposphere=False, stations=None, start=None, scan_length=None, scan_gap=None,
        correlations=None, threads=1):
    return simulate(scene, outdir, prefix=prefix, seed=seed, save_truth=save_truth,
                    overwrite=overwrite, duration=duration, integration=integration,
                    coherence_scale=coherence_scale, no_noise=no_noise,
                    no_troposphere=no_troposphere, stations=stations, start=start,
                    scan_length=scan_length, scan_gap=scan_gap, correlations=correlations,
                    threads=threads)
