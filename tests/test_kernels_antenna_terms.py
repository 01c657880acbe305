"""hitops/kernels/antenna_terms.py: per-antenna phase and delay terms applied to baselines.

The expected values are the formula itself, evaluated per sample with numpy:
V_pq(k) exp(-i [(phi_p - phi_q) + 2 pi (nu_k - nu_0)(tau_p - tau_q)]), each antenna's
term taken for the receptor the correlation asks of it (RL: p's R, q's L).
"""

from __future__ import annotations

import numpy as np
import pytest

from hitops.kernels.antenna_terms import AntennaTerms, apply_antenna_terms

N_ANT, N_TERM, N_REC = 4, 5, 2
#: RR, RL, LR, LL: (receptor of ANTENNA1, receptor of ANTENNA2)
CIRCULAR = np.array([[0, 0], [0, 1], [1, 0], [1, 1]])


def _scene(seed=3, n_chan=8, even=True):
    rng = np.random.default_rng(seed)
    ant1, ant2 = np.triu_indices(N_ANT, 1)
    ant1, ant2 = np.tile(ant1, N_TERM), np.tile(ant2, N_TERM)
    term_index = np.repeat(np.arange(N_TERM), N_ANT * (N_ANT - 1) // 2)
    n_row = ant1.size
    data = (rng.normal(size=(n_row, n_chan, 4)) + 1j * rng.normal(size=(n_row, n_chan, 4)))
    terms = AntennaTerms(rng.uniform(-30, 30, (N_TERM, N_ANT, N_REC)),
                         rng.uniform(-2e-9, 2e-9, (N_TERM, N_ANT, N_REC)),
                         np.ones((N_TERM, N_ANT, N_REC), bool))
    offset = (np.arange(n_chan) - 3.5) * 125e6
    if not even:
        offset = offset + rng.uniform(-20e6, 20e6, n_chan)
    return data.astype(np.complex64), term_index, ant1, ant2, terms, offset


def _expected(data, term_index, ant1, ant2, receptors, terms, offset):
    out = np.zeros(data.shape, np.complex128)
    for r in range(data.shape[0]):
        t, p, q = term_index[r], ant1[r], ant2[r]
        for c, (rp, rq) in enumerate(receptors):
            dphi = terms.phase[t, p, rp] - terms.phase[t, q, rq]
            dtau = terms.delay_s[t, p, rp] - terms.delay_s[t, q, rq]
            out[r, :, c] = data[r, :, c] * np.exp(-1j * (dphi + 2 * np.pi * offset * dtau))
    return out


@pytest.mark.parametrize("even", [True, False])
def test_matches_the_formula_per_receptor_pair(even):
    data, ti, a1, a2, terms, offset = _scene(even=even)
    before = [x.copy() for x in (data, ti, a1, a2, terms.phase, terms.delay_s, offset)]
    got = apply_antenna_terms(data, ti, a1, a2, CIRCULAR, terms, offset)
    assert got.data.dtype == np.complex64 and got.calibrated.all()
    np.testing.assert_allclose(got.data, _expected(data, ti, a1, a2, CIRCULAR, terms, offset),
                               rtol=0, atol=2e-5 * np.abs(data).max())
    # pure: the inputs are as they were
    for old, new in zip(before, (data, ti, a1, a2, terms.phase, terms.delay_s, offset)):
        np.testing.assert_array_equal(old, new)


def test_a_gather_of_one_receptor_for_both_antennas_fails():
    """The plausible wrong gather (ANTENNA1's receptor for both sides) differs on RL/LR."""
    data, ti, a1, a2, terms, offset = _scene()
    got = apply_antenna_terms(data, ti, a1, a2, CIRCULAR, terms, offset)
    wrong = _expected(data, ti, a1, a2, CIRCULAR[:, [0, 0]], terms, offset)
    assert np.abs(got.data[:, :, 1] - wrong[:, :, 1]).max() > 0.1
    np.testing.assert_allclose(got.data[:, :, 0], wrong[:, :, 0], atol=2e-5 * np.abs(data).max())


def test_closure_phases_are_kept():
    """A per-antenna correction leaves every closure phase of a triangle as it was."""
    data, ti, a1, a2, terms, offset = _scene()
    got = apply_antenna_terms(data, ti, a1, a2, CIRCULAR, terms, offset).data
    row = {(int(ti[r]), int(a1[r]), int(a2[r])): r for r in range(ti.size)}

    def closure(v, t):
        return np.angle(v[row[t, 0, 1], :, 0] * v[row[t, 1, 2], :, 0] * np.conj(v[row[t, 0, 2], :, 0]))

    for t in range(N_TERM):
        np.testing.assert_allclose(np.exp(1j * closure(got, t)), np.exp(1j * closure(data, t)),
                                   atol=1e-4)


def test_samples_without_a_term_are_reported_and_zero_or_kept():
    data, ti, a1, a2, terms, offset = _scene()
    solved = terms.solved.copy()
    solved[2, 3, 1] = False                    # antenna 3's L receptor at term 2
    terms = AntennaTerms(terms.phase, terms.delay_s, solved)
    receptors = CIRCULAR.copy()
    receptors[2] = (-1, 0)                     # LR: no receptor of ANTENNA1 known
    got = apply_antenna_terms(data, ti, a1, a2, receptors, terms, offset)
    lost = (ti == 2)[:, None] & (((a1 == 3) | (a2 == 3))[:, None]) & np.array(
        [False, False, False, True])[None, :]
    lost |= (a2 == 3)[:, None] & (ti == 2)[:, None] & np.array([False, True, False, False])
    lost[:, 2] = True
    np.testing.assert_array_equal(got.calibrated, ~lost)
    assert not got.data.transpose(0, 2, 1)[lost].any()
    kept = apply_antenna_terms(data, ti, a1, a2, receptors, terms, offset, keep_uncalibrated=True)
    np.testing.assert_array_equal(kept.data.transpose(0, 2, 1)[lost], data.transpose(0, 2, 1)[lost])
    np.testing.assert_array_equal(kept.data.transpose(0, 2, 1)[~lost],
                                  got.data.transpose(0, 2, 1)[~lost])
