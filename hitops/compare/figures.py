"""Side-by-side panels of restored images (e.g. FF+SC, PWC and their difference).

Reads FITS or CASA images through casatools (no astropy dependency), so it
runs wherever the CASA cabs run:

    python -m hitops.compare.figures out/demo/images out/demo/images.png raw ffsc cfpt pwc

Each panel has its own colour scale (a diverged CLEAN of 1e21 Jy/beam beside a
1 Jy source would otherwise leave every other panel black).  An image whose
CLEAN diverged (renamed X-image.diverged.fits by the imfit step, or with
|values| above ``max_abs`` Jy/beam) is not shown as if usable: its dirty image
is drawn instead and the panel title says so.  The difference of the last two
panels is drawn only when both are restored images.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Sequence, Tuple

import numpy as np

from ..errors import InputError

#: |pixel| above this (Jy/beam) in a restored image means its CLEAN diverged
MAX_ABS = 5.0


def read_image(path: str) -> tuple:
    """(2-D array indexed [y, x], pixel size in microarcsec) of the first plane."""
    from ..casa_env import ensure_casa_offline
    from ..casa.fits import conform_header

    ensure_casa_offline()
    import casatools

    if not Path(path).exists():
        raise InputError(f"image '{path}' does not exist")
    conform_header(path)   # WSClean's CDELT cards, or CASA logs a warning per read
    ia = casatools.image()
    try:
        ia.open(str(path))
        pixels = ia.getchunk(dropdeg=True)
        inc = ia.coordsys().increment(type="direction")["numeric"]
    finally:
        ia.done()
    uas = abs(float(inc[0])) * 206264.80624709636e6
    return np.asarray(pixels, dtype=np.float64).T, uas


def pick_image(image_dir: str, label: str, max_abs: float = MAX_ABS) -> Tuple[str, str]:
    """(path, what) of the image to show for ``label``: the restored one, or the dirty one
    with the reason when the CLEAN diverged."""
    base = Path(image_dir)
    restored = base / f"{label}-image.fits"
    dirty = base / f"{label}-dirty.fits"
    if restored.exists():
        data, _ = read_image(str(restored))
        finite = np.isfinite(data)
        if finite.any() and float(np.nanmax(np.abs(data))) <= max_abs:
            return str(restored), "restored"
        why = "CLEAN diverged" if finite.any() else "CLEAN gave NaN"
    elif (base / f"{label}-image.diverged.fits").exists():
        why = "CLEAN diverged"
    else:
        raise InputError(f"no image {restored} (nor {label}-image.diverged.fits) in {image_dir}")
    if not dirty.exists():
        raise InputError(f"{restored}: {why}, and there is no dirty image {dirty} to show")
    return str(dirty), f"dirty: {why}"


def _jy(value: float) -> str:
    """A flux density with 3 significant digits in a readable unit."""
    if not np.isfinite(value):
        return "nan"
    if abs(value) >= 1e3:
        return f"{value:.2e} Jy/beam"
    if abs(value) >= 0.1:
        return f"{value:.3f} Jy/beam"
    return f"{value * 1e3:.3g} mJy/beam"


def image_panels(image_dir: str, out_png: str, labels: Sequence[str] = ("ffsc", "pwc"),
                 half_width: int = 64, max_abs: float = MAX_ABS) -> str:
    """Centre crops of {label}-image.fits (or the dirty image, marked), plus the
    difference of the last two; every panel scaled by itself."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    picked = [pick_image(image_dir, lab, max_abs) for lab in labels]
    images = [read_image(path) for path, _ in picked]
    crops = []
    for data, _ in images:
        cy, cx = data.shape[0] // 2, data.shape[1] // 2
        crops.append(data[cy - half_width:cy + half_width, cx - half_width:cx + half_width])
    panels = [(lab, what, crop) for lab, (_, what), crop in zip(labels, picked, crops)]
    if len(crops) >= 2 and picked[-1][1] == picked[-2][1] == "restored":
        panels.append((f"{labels[-1]} - {labels[-2]}", "difference", crops[-1] - crops[-2]))
    uas = images[0][1]
    extent = [half_width * uas, -half_width * uas, -half_width * uas, half_width * uas]
    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), 4.3), squeeze=False)
    for ax, (name, what, crop) in zip(axes[0], panels):
        finite = crop[np.isfinite(crop)]
        is_diff = what == "difference"
        if is_diff:
            lim = float(np.max(np.abs(finite))) if finite.size else 1.0
            vmin, vmax, cmap = -lim, lim, "RdBu_r"
        else:
            vmax = float(finite.max()) if finite.size else 1.0
            vmin = min(0.0, float(finite.min())) if finite.size else 0.0
            cmap = "inferno"
        if vmax <= vmin:
            vmax = vmin + 1e-12
        im = ax.imshow(crop, origin="lower", extent=extent, cmap=cmap, vmin=vmin, vmax=vmax)
        peak = float(finite.max()) if finite.size else float("nan")
        if is_diff:
            title = f"{name}: max |diff| {_jy(float(np.max(np.abs(finite))) if finite.size else np.nan)}"
        elif what.startswith("dirty"):
            title = f"{name}: DIRTY image, max {_jy(peak)}\n({what[len('dirty: '):]})"
        else:
            title = f"{name}: max {_jy(peak)}"
        ax.set_title(title, fontsize=10)
        ax.set_xlabel("relative RA (microarcsec)")
        fig.colorbar(im, ax=ax, shrink=0.8, label="Jy/beam")
    axes[0][0].set_ylabel("relative Dec (microarcsec)")
    fig.tight_layout()
    fig.savefig(out_png, dpi=90)
    plt.close(fig)
    return out_png


if __name__ == "__main__":
    if len(sys.argv) < 3:
        print(__doc__)
        sys.exit(2)
    try:
        print(image_panels(sys.argv[1], sys.argv[2], sys.argv[3:] or ("ffsc", "pwc")))
    except InputError as err:
        sys.exit(f"hitops.compare.figures: {err}")
