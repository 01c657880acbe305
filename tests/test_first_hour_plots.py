"""Plots with one colour per method, identical series kept visible, legends that
explain every line (issue 17), on a small grid built here."""

from __future__ import annotations

import numpy as np
import pytest

from hitops.diagnose import plots as P


class _Result:
    """The part of diagnose's CoherenceResult the coherence plots read."""

    def __init__(self, curves, intervals):
        self.columns = list(curves)
        self._curves = curves
        self.intervals = np.asarray(intervals, dtype=float)

    def curve(self, col):
        return self._curves[col]


def _curves(order, n_bl=5):
    t = np.array([2.0, 10.0, 60.0, 300.0])
    base = {"DATA": np.exp(-t / 30.0), "CORRECTED_DATA": 0.9 + 0 * t,
            "CFPT_DATA": np.exp(-t / 300.0), "PWC_DATA": 0.99 + 0 * t,
            "CWU_DATA": 0.99 + 0 * t}        # CWU identical to PWC, as on the demo
    return _Result({c: np.tile(base[c], (n_bl, 1)) for c in order}, t)


def _line_colours(ax):
    from matplotlib.colors import to_hex

    return {line.get_label(): to_hex(line.get_color()) for line in ax.lines
            if not line.get_label().startswith("_")}


@pytest.mark.parametrize("order", [
    ["DATA", "CORRECTED_DATA", "CFPT_DATA", "PWC_DATA", "CWU_DATA"],
    ["PWC_DATA", "CWU_DATA", "CFPT_DATA", "DATA", "CORRECTED_DATA"],
])
def test_a_method_has_the_same_colour_whatever_the_column_order(order):
    from matplotlib.colors import to_hex

    res = _curves(order)
    fig = P.coherence_figure(res, 0, "AP-PV", [{"columns": {c: {"tau_c_bound": ">",
                                                                "tau_c_s": None}
                                                            for c in order}}])
    colours = {label.split(" ")[0]: c for label, c in _line_colours(fig.axes[0]).items()}
    for col, method in P.COLUMN_METHODS.items():
        if col in order:
            assert colours[col] == to_hex(P.METHOD_COLOURS[method]), (col, order)
    assert len(set(P.METHOD_COLOURS.values())) == len(P.METHOD_COLOURS)
    assert not set(P.METHOD_COLOURS.values()) & set(P.OTHER_COLOURS)


def test_identical_series_stay_visible_and_say_so():
    res = _curves(["DATA", "PWC_DATA", "CWU_DATA"])
    fig = P.coherence_figure(res, 0, "AP-PV", [{"columns": {
        "DATA": {"tau_c_bound": "=", "tau_c_s": 20.0},
        "PWC_DATA": {"tau_c_bound": ">", "tau_c_s": None},
        "CWU_DATA": {"tau_c_bound": ">", "tau_c_s": None}}}])
    ax = fig.axes[0]
    cwu = next(l for l in ax.lines if l.get_label().startswith("CWU_DATA"))
    pwc = next(l for l in ax.lines if l.get_label() == "PWC_DATA")
    assert cwu.get_label() == "CWU_DATA (= PWC_DATA)"
    # drawn on top, dashed with open markers, so the curve beneath shows through
    assert cwu.get_linestyle() == "--" and cwu.get_markerfacecolor() == "none"
    assert ax.lines.index(cwu) > ax.lines.index(pwc)
    legend = [t.get_text() for t in ax.get_legend().get_texts()]
    assert any("tau_c" in t for t in legend)            # the dashed verticals explained
    assert "1/e" in legend


def test_overview_has_one_readable_legend_in_the_free_cells():
    res = _curves(["DATA", "CORRECTED_DATA", "PWC_DATA"], n_bl=10)
    names = [f"B{i}" for i in range(10)]
    fig = P.coherence_overview(res, names)
    panels = [ax for ax in fig.axes if ax.axison]
    assert len(panels) == 10
    spare = [ax for ax in fig.axes if not ax.axison]
    assert len(spare) == 1 and spare[0].get_legend() is not None   # 3 x 4 grid: 2 free cells
    legend = spare[0].get_legend()
    assert [t.get_text() for t in legend.get_texts()] == ["DATA", "CORRECTED_DATA",
                                                          "PWC_DATA", "1/e"]
    assert legend.get_texts()[0].get_fontsize() >= 9
    assert all(ax.get_legend() is None for ax in panels)
    # a baseline without data says so instead of an empty panel
    res._curves["DATA"][3] = np.nan
    res._curves["CORRECTED_DATA"][3] = np.nan
    res._curves["PWC_DATA"][3] = np.nan
    fig = P.coherence_overview(res, names)
    assert any(t.get_text() == "no unflagged data" for t in fig.axes[3].texts)


def test_unknown_columns_get_colours_no_method_uses():
    colours = P.column_colours(["PWC230_DATA", "DATA", "MY_DATA"])
    assert colours["DATA"] == P.METHOD_COLOURS["raw"]
    assert colours["PWC230_DATA"] == P.OTHER_COLOURS[0] and colours["MY_DATA"] == P.OTHER_COLOURS[1]
