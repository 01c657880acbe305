"""`hitops compare`: entry point built from hitops/schemas/compare.yml."""

from __future__ import annotations

from .table import compare


def run(fits, labels=None, input_peak=1.0, input_peak_err=0.0, coherence=None,
        reference="none", outdir=".", name="peak-flux", overwrite=False):
    compare(fits, labels=labels, input_peak=input_peak, input_peak_err=input_peak_err,
            coherence=coherence, reference=reference, outdir=outdir, name=name,
            overwrite=overwrite)
