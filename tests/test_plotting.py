"""Line-chart panels (jstarid.plotting.draw_panels), the figures of the experiment scripts."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from jstarid.plotting import Panel, Series, draw_panels, save_panels  # noqa: E402


def test_panels_draw_each_series_with_its_axes_settings():
    x = [0.0, 1.0, 2.0]
    panels = [Panel([Series(x, [1.0, None, 3.0], "a", "s--", color="C3"),
                     Series(x, [2.0, 2.0, 2.0], None, "k-")], xlabel="σ (px)", ylabel="rate", title="left",
                    ylim=(-1, 5)),
              Panel([Series([1.0, 10.0], [0.5, 0.9], "b", yerr=[[0.1, -0.2], [0.2, 0.1]])],
                    xscale="log", yscale="log", legend=False)]
    fig = draw_panels(panels, title="both")
    try:
        left, right = fig.axes
        assert (left.get_xlabel(), left.get_ylabel(), left.get_title()) == ("σ (px)", "rate", "left")
        assert left.get_ylim() == (-1, 5)
        a, flat = left.get_lines()
        np.testing.assert_array_equal(a.get_ydata(), [1.0, np.nan, 3.0])  # None is a gap
        assert (a.get_linestyle(), a.get_marker(), a.get_label()) == ("--", "s", "a")
        assert [t.get_text() for t in left.get_legend().get_texts()] == ["a"]  # unlabelled: none
        assert right.get_xscale() == right.get_yscale() == "log" and right.get_legend() is None
        bars = right.containers[0]  # the error bars, the negative one clipped to 0
        low, high = bars.lines[2][0].get_segments()[0][:, 1]
        assert (low, high) == (0.4, 0.7)
        assert fig._suptitle.get_text() == "both"
    finally:
        plt.close(fig)


def test_save_panels_writes_a_png(tmp_path):
    save_panels([Panel([Series([0, 1], [0, 1], "line")])], tmp_path / "fig.png")
    assert (tmp_path / "fig.png").read_bytes()[:4] == b"\x89PNG"
