"""The run's FITS images as pictures: one colour scale per row, beam drawn, peak marked.

Read with hitops.io.fits (numpy, no astropy); drawn with matplotlib's Agg backend into
PNG files beside the page.  Every image of a row shares one colour scale (the input
peak, or the largest fitted peak), so a weaker recovery looks weaker.  A CLEAN that
diverged or an image with no source above the noise says so on the picture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..io.fits import read_headers
from .collect import ImageFit

#: milliarcseconds per degree
_MAS = 3.6e6


@dataclass(frozen=True)
class Picture:
    """A rendered image: the PNG beside the page, what it shows, and its caption."""

    label: str
    png: Path
    fits: Path
    shown: str          # "restored" or "dirty (CLEAN diverged)"
    caption: str


def read_image(path: Path):
    """(2-D float array, header) of the first Stokes plane of a FITS image."""
    header, offset, n_bytes = read_headers(path)[0]
    bitpix = int(header["BITPIX"])
    dtype = {-32: ">f4", -64: ">f8", 16: ">i2", 32: ">i4"}[bitpix]
    shape = [int(header[f"NAXIS{k}"]) for k in range(int(header["NAXIS"]), 0, -1)]
    with open(path, "rb") as fh:
        fh.seek(offset)
        data = np.frombuffer(fh.read(n_bytes), dtype=dtype).reshape(shape)
    plane = data.reshape(-1, shape[-2], shape[-1])[0].astype(np.float64)
    return plane * float(header.get("BSCALE", 1.0)) + float(header.get("BZERO", 0.0)), header


#: a restored image brighter than this many times the row's scale is a diverged CLEAN (the
#: image-fit recipe's max_abs_peak is 5 Jy/beam for a 1-Jy source)
DIVERGED_FACTOR = 5.0


def _state(fit: dict, scale_jy: float = 1.0) -> str:
    method = str(fit.get("method", ""))
    if fit.get("diverged") or "diverged" in str(fit.get("note", "")) or method == "max-pixel":
        return "diverged"
    # a fit that found "no source" in an image whose brightest pixel is absurd: CLEAN diverged
    if abs(float(fit.get("brightest") or 0.0)) > DIVERGED_FACTOR * scale_jy:
        return "diverged"
    if method in ("no-source",) or fit.get("peak") is None:
        return "no source"
    return "fit"


def _shown_file(item: ImageFit, state: str) -> Path:
    # a diverged CLEAN's fit was made on the dirty image (the restored one was renamed)
    fitted = Path(str(item.fit.get("fallback_image") or item.fit.get("image") or item.fits_path))
    dirty = item.fits_path.parent / f"{item.label}-dirty.fits"
    first = [dirty] if state == "diverged" else []
    for candidate in (*first, fitted, item.fits_path.parent / fitted.name, item.fits_path):
        if candidate.is_file():
            return candidate
    return item.fits_path


def render_row(items: List[ImageFit], out_dir: Path, scale_jy: Optional[float]) -> List[Picture]:
    """One PNG per image, all on the colour scale [-0.1, 1] x ``scale_jy``."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Ellipse

    out_dir.mkdir(parents=True, exist_ok=True)
    peaks = [float(i.fit["peak"]) for i in items if i.fit.get("peak") is not None
             and str(i.fit.get("method")) == "gaussian"]
    vmax = scale_jy or (max(peaks) if peaks else 1.0)
    pictures = []
    for item in items:
        state = _state(item.fit, vmax)
        path = _shown_file(item, state)
        if not path.is_file():
            continue
        image, header = read_image(path)
        n_y, n_x = image.shape
        dx = abs(float(header.get("CDELT1", 0.0))) * _MAS or 1.0
        dy = abs(float(header.get("CDELT2", 0.0))) * _MAS or 1.0
        cx, cy = float(header.get("CRPIX1", n_x / 2)) - 1, float(header.get("CRPIX2", n_y / 2)) - 1

        def ra(col):    # relative RA grows to the left (east), as on the sky
            return -(col - cx) * dx

        def dec(row):
            return (row - cy) * dy

        extent = [ra(-0.5), ra(n_x - 0.5), dec(-0.5), dec(n_y - 0.5)]
        fig, ax = plt.subplots(figsize=(3.4, 3.4), dpi=110)
        shown = ax.imshow(image, origin="lower", cmap="inferno", vmin=-0.1 * vmax, vmax=vmax,
                          extent=extent, interpolation="nearest")
        if state == "fit" and item.fit.get("x_pix") is not None:
            ax.plot([ra(float(item.fit["x_pix"]))], [dec(float(item.fit["y_pix"]))], marker="+",
                    color="cyan", markersize=14, mew=1.5)
        bmaj, bmin = header.get("BMAJ"), header.get("BMIN")
        if bmaj and bmin:
            major, minor = float(bmaj) * _MAS, float(bmin) * _MAS
            pa = math.radians(float(header.get("BPA", 0.0)))   # east of north
            # the beam's half extents on the axes, so it sits whole in the bottom-left corner
            half_x = math.hypot(major / 2 * math.sin(pa), minor / 2 * math.cos(pa))
            half_y = math.hypot(major / 2 * math.cos(pa), minor / 2 * math.sin(pa))
            margin = 0.04 * (extent[3] - extent[2])
            centre = (extent[0] - half_x - margin, extent[2] + half_y + margin)
            # angle counter-clockwise from +x in data coordinates; RA grows to the left
            ax.add_patch(Ellipse(centre, minor, major, angle=-math.degrees(pa), fill=False,
                                 edgecolor="white", lw=1.2))
        ax.set_xlim(extent[0], extent[1])
        ax.set_ylim(extent[2], extent[3])
        text = {"diverged": "CLEAN diverged: dirty image shown", "no source":
                "no source above the noise"}.get(state)
        if text:
            ax.text(0.5, 0.93, text, transform=ax.transAxes, ha="center", va="top",
                    color="white", fontsize=8, bbox=dict(facecolor="black", alpha=0.6, lw=0))
        ax.set_xlabel("relative RA (mas)", fontsize=8)
        ax.set_ylabel("relative Dec (mas)", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.set_title(item.label, fontsize=10)
        fig.colorbar(shown, ax=ax, fraction=0.046, pad=0.03).ax.tick_params(labelsize=7)
        fig.tight_layout()
        png = out_dir / f"image-{item.label}.png"
        fig.savefig(png)
        plt.close(fig)
        caption = _caption(item.fit, state)
        pictures.append(Picture(item.label, png, path,
                                "restored" if state != "diverged" else "dirty (CLEAN diverged)",
                                caption))
    return pictures


def _caption(fit: dict, state: str) -> str:
    if state == "fit":
        peak, err = float(fit["peak"]), float(fit.get("peak_err") or math.nan)
        snr = fit.get("snr")
        return (f"imfit peak {peak:.4f} ± {err:.4f} Jy/beam"
                + (f", SNR {float(snr):.0f}" if snr else ""))
    if state == "diverged":
        peak = fit.get("peak") if fit.get("method") == "max-pixel" else None
        brightest = fit.get("brightest")
        return ("CLEAN diverged; " + (f"brightest dirty pixel {float(peak):.3f} Jy/beam"
                                      if peak is not None else
                                      f"restored image's brightest pixel {float(brightest):.3g} "
                                      "Jy/beam; the dirty image is shown"
                                      if brightest is not None else "the dirty image is shown"))
    return str(fit.get("reason") or fit.get("note") or "no source above the noise")
