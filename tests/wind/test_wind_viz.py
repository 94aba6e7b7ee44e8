"""Wind figures: content and input checks."""

from __future__ import annotations

import numpy as np
import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.viz.wind import plot_bands, plot_wind_estimates


def test_estimate_plot_has_truth_measurement_and_filters():
    t = np.arange(50.0)
    truth = 10 + np.sin(t / 5)
    fig = plot_wind_estimates(t, truth, truth + 0.1, {"KF": truth, "RAF": truth + 0.2},
                              outlier=(t > 20) & (t < 25), window=(10.0, 40.0))
    ax = fig.axes[0]
    labels = [line.get_label() for line in ax.get_lines()]
    assert labels == ["measured", "truth", "KF", "RAF"]
    assert len(ax.get_lines()[1].get_xdata()) == 31  # the zoom window, inclusive
    with pytest.raises(NeuralMapError, match="expected 50 values"):
        plot_wind_estimates(t, truth[:-1], truth, {})


def test_band_plot_drops_zeros_on_log_axis():
    t = np.arange(5.0)
    c = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    fig = plot_bands(t, {"x": (c, c * 0.5, c * 2)}, ylabel="e", title="t", log=True)
    y = fig.axes[0].get_lines()[0].get_ydata()
    assert np.isnan(y[0]) and np.allclose(y[1:], c[1:])
    assert fig.axes[0].get_yscale() == "log"
