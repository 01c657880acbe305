"""Source models: noise-free Stokes I visibilities per row and channel.

A point source at the phase centre plus any number of components:

* gaussian: V = F exp(-pi^2 (a^2 u'^2 + b^2 v'^2) / (4 ln 2)) exp(+2 pi i (u l + v m)),
  a/b the FWHM along the major/minor axis (u', v' rotated by the position angle);
* ring: a thin ring of diameter d blurred by a circular Gaussian of FWHM w,
  V = F J0(pi d rho) exp(-(pi w rho)^2 / (4 ln 2)) exp(+2 pi i (u l + v m)),
  rho = sqrt(u^2 + v^2) (Thompson, Moran & Swenson 2017, Table 10.1 for the ring's
  Hankel transform; the EHT's M87* ring models, EHT Collaboration 2019 Paper VI);
  a point (fwhm 0) at an offset gives a two-component source.

u, v are the stored UVW (= uvw(ANT1) - uvw(ANT2)) in wavelengths of each channel,
so the structure phase changes across a band.  In terms of the baseline X2 - X1
this is the usual exp(-2 pi i (u l + v m)) (Thompson, Moran & Swenson 2017,
eq. 3.7); WSClean images a component at +l (east), +m (north)
(tests/test_simulate_tools.py).
"""

from __future__ import annotations

import numpy as np

C_LIGHT = 299792458.0
#: one microarcsecond in radians
UAS = np.radians(1.0 / 3600e6)


def model_visibilities(scene, band_name: str, uvw: np.ndarray,
                       chan_freq: np.ndarray) -> np.ndarray:
    """Noise-free visibilities (Jy) of the target, complex128 (n_row, n_chan), at
    ``chan_freq`` (Hz)."""
    return field_visibilities(scene.flux, scene.components, band_name, uvw, chan_freq)


def field_visibilities(flux, components, band_name: str, uvw: np.ndarray,
                       chan_freq: np.ndarray) -> np.ndarray:
    """Noise-free visibilities (Jy), complex128 (n_row, n_chan), of a point of ``flux``
    (Jy per band) at the phase centre plus ``components`` (the target's or a
    calibrator's, each seen at its own phase centre)."""
    n_row = uvw.shape[0]
    model = np.full((n_row, chan_freq.size), flux[band_name], dtype=np.complex128)
    if not components:
        return model
    u = uvw[:, 0, None] * chan_freq[None, :] / C_LIGHT
    v = uvw[:, 1, None] * chan_freq[None, :] / C_LIGHT
    for comp in components:
        shift = np.exp(2j * np.pi * (u * comp.offset_ra * UAS + v * comp.offset_dec * UAS))
        model += comp.flux[band_name] * _shape(comp, u, v) * shift
    return model


def _shape(comp, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The component's visibility at its own centre (real: both shapes are symmetric)."""
    gauss = np.pi ** 2 / (4.0 * np.log(2.0))
    if comp.shape == "ring":
        from scipy.special import j0

        rho = np.hypot(u, v)
        return j0(np.pi * comp.diameter * UAS * rho) * np.exp(
            -gauss * (comp.fwhm_major * UAS * rho) ** 2)
    pa = np.radians(comp.position_angle)
    along_major = u * np.sin(pa) + v * np.cos(pa)
    along_minor = u * np.cos(pa) - v * np.sin(pa)
    return np.exp(-gauss * ((comp.fwhm_major * UAS * along_major) ** 2 +
                            (comp.fwhm_minor * UAS * along_minor) ** 2))
