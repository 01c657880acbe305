"""Side-by-side panels of restored images (e.g. FF+SC, PWC and their difference).

Reads FITS or CASA images through casatools (no astropy dependency), so it
runs wherever the CASA cabs run:

    python -m hitops.compare.figures out/paper/images out.png ffsc pwc
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence

import numpy as np

from ..errors import InputError


def read_image(path: str) -> tuple:
    """(2-D array indexed [y, x], pixel size in microarcsec) of the first plane."""
    from ..casa_env import ensure_casa_offline

    ensure_casa_offline()
    import casatools

    if not Path(path).exists():
        raise InputError(f"image '{path}' does not exist")
    ia = casatools.image()
    try:
        ia.open(str(path))
        pixels = ia.getchunk(dropdeg=True)
        inc = ia.coordsys().increment(type="direction")["numeric"]
    finally:
        ia.done()
    uas = abs(float(inc[0])) * 206264.80624709636e6
    return np.asarray(pixels, dtype=np.float64).T, uas


def image_panels(image_dir: str, out_png: str, labels: Sequence[str] = ("ffsc", "pwc"),
                 half_width: int = 64) -> str:
    """Centre crops of {label}-image.fits, plus the difference of the last two."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    images = [read_image(str(Path(image_dir) / f"{lab}-image.fits")) for lab in labels]
    crops = []
    for data, _ in images:
        cy, cx = data.shape[0] // 2, data.shape[1] // 2
        crops.append(data[cy - half_width:cy + half_width, cx - half_width:cx + half_width])
    panels = list(zip(labels, crops))
    if len(crops) >= 2:
        panels.append((f"{labels[-1]} - {labels[-2]}", crops[-1] - crops[-2]))
    uas = images[0][1]
    extent = [half_width * uas, -half_width * uas, -half_width * uas, half_width * uas]
    vmax = max(float(np.nanmax(c)) for c in crops)
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.0))
    for ax, (name, crop) in zip(np.atleast_1d(axes), panels):
        is_diff = " - " in name
        lim = float(np.nanmax(np.abs(crop))) if is_diff else vmax
        im = ax.imshow(crop, origin="lower", extent=extent, cmap="RdBu_r" if is_diff else "inferno",
                       vmin=-lim if is_diff else min(0.0, float(np.nanmin(crop))), vmax=lim)
        ax.set_title(f"{name}: peak {np.nanmax(crop) * 1e3:.0f} mJy/beam")
        ax.set_xlabel("relative RA (microarcsec)")
        fig.colorbar(im, ax=ax, shrink=0.8, label="Jy/beam")
    np.atleast_1d(axes)[0].set_ylabel("relative Dec (microarcsec)")
    fig.tight_layout()
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
    return out_png


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(__doc__)
        sys.exit(2)
    print(image_panels(sys.argv[1], sys.argv[2], sys.argv[3:] or ("ffsc", "pwc")))
