"""Small Measurement Sets with known phases for the diagnose tests and benchmark."""

from __future__ import annotations

from itertools import combinations
from pathlib import Path
from typing import Dict, Sequence

import numpy as np

from hitops.io.ms_create import ArrayLayout, Band, Field, create_ms

MJD_2023_04_10 = 60044.0 * 86400.0

#: station codes and ITRF positions (m) of the paper's array (GUIDE.md section 2)
STATIONS = {
    "AP": (2225039.5297, -5441197.6292, -2479303.3597),
    "SM": (-5464555.493, -2492927.989, 2150797.176),
    "PV": (5088967.74544, -301681.18586, 3825012.20561),
    "GL": (541547.0, -1387978.6, 6180982.0),
    "PB": (4524000.43, 468042.14, 4460309.76),
    "KP": (-1995953.2507, -5037384.5859, 3357045.5186),
    "KC": (-3149221.052, 3966404.922, 3864830.701),
    "KY": (-3042281.0183, 4045902.6730, 3867374.3296),
}


def fbm(n: int, n_series: int, t_c: float, dt: float, rng, hurst: float = 5.0 / 6.0):
    """Exact fBm phases with D(lag) = (lag/t_c)^(2H) rad^2 by circulant embedding.

    Davies & Harte (1987): fractional Gaussian noise (the increments) is
    stationary, so its covariance embeds in a 2n circulant whose eigenvalues
    are one FFT; colouring white noise with their square roots gives exact
    samples; the cumulative sum is the fBm.
    """
    k = np.arange(n + 1, dtype=np.float64)
    gamma = 0.5 * ((k + 1) ** (2 * hurst) - 2 * k ** (2 * hurst) + np.abs(k - 1) ** (2 * hurst))
    row = np.concatenate([gamma, gamma[-2:0:-1]])
    eig = np.clip(np.fft.fft(row).real, 0, None)
    m = row.size
    white = rng.standard_normal((n_series, m)) + 1j * rng.standard_normal((n_series, m))
    fgn = np.fft.fft(np.sqrt(eig / m) * white, axis=1).real[:, :n]
    scale = (dt / t_c) ** hurst      # D(dt) of one step
    return np.cumsum(fgn, axis=1) * scale


def build_ms(path: Path, phases: Dict[str, np.ndarray], stations: Sequence[str],
             dt: float = 1.0, corr_types=("RR", "LL"), scan: np.ndarray | None = None,
             flag: np.ndarray | None = None, time_keep: np.ndarray | None = None,
             amplitude: Dict[str, np.ndarray] | None = None, freq_hz: float = 230e9) -> Path:
    """Write an MS whose columns carry exp(i*phase).

    ``phases[col]`` has shape (n_bl, n_time, n_corr) in the baseline order of
    ``combinations(stations, 2)``; the first column becomes DATA's position
    in the dict order but every column keeps its own name (extra columns are
    added after creation with python-casacore).  ``time_keep`` (n_bl, n_time)
    bool drops rows; ``flag`` (n_bl, n_time, n_corr) sets FLAG.
    """
    from casacore import tables as pt

    names = list(stations)
    pairs = list(combinations(range(len(names)), 2))
    cols = list(phases)
    n_bl, n_time, n_corr = phases[cols[0]].shape
    assert n_bl == len(pairs) and n_corr == len(corr_types)
    keep = np.ones((n_bl, n_time), bool) if time_keep is None else time_keep
    # rows in time-major order, as correlators write them
    t_idx, b_idx = np.nonzero(keep.T)
    times = MJD_2023_04_10 + t_idx * dt
    ant1 = np.array([pairs[b][0] for b in b_idx])
    ant2 = np.array([pairs[b][1] for b in b_idx])
    pos = np.array([STATIONS.get(n, (1e6 * i, 2e6, 3e6)) for i, n in enumerate(names)])
    omega = 7.2921e-5 * (t_idx * dt)
    base = pos[ant2] - pos[ant1]
    uvw = np.stack([base[:, 0] * np.cos(omega) - base[:, 1] * np.sin(omega),
                    base[:, 0] * np.sin(omega) + base[:, 1] * np.cos(omega),
                    base[:, 2]], axis=1)

    def col_values(col):
        amp = 1.0 if amplitude is None or col not in amplitude else \
            amplitude[col][b_idx, t_idx][:, None]
        return (amp * np.exp(1j * phases[col][b_idx, t_idx])).astype(np.complex64)

    main = {"TIME": times, "ANTENNA1": ant1, "ANTENNA2": ant2, "UVW": uvw,
            "DATA": col_values(cols[0]) if cols[0] == "DATA" else
            np.ones((times.size, n_corr), np.complex64)}
    if scan is not None:
        main["SCAN_NUMBER"] = scan[t_idx]
    if flag is not None:
        main["FLAG"] = flag[b_idx, t_idx][:, None, :]
    layout = ArrayLayout(names=names, stations=names, positions=pos,
                         diameters=np.full(len(names), 12.0))
    create_ms(path, layout, Band(freq_hz, 2e9, tuple(corr_types)),
              Field("M87", 3.2766, 0.2162), main, overwrite=True)
    with pt.table(str(path), readonly=False, ack=False) as tab:
        for col in cols:
            if col == "DATA":
                continue
            desc = pt.makearrcoldesc(col, 0j, shape=[1, n_corr], valuetype="complex",
                                     options=4)
            tab.addcols(pt.maketabdesc([desc]))
            tab.putcol(col, col_values(col)[:, None, :])
    return path


def baseline_count(n_station: int) -> int:
    return n_station * (n_station - 1) // 2
