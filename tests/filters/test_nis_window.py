"""The windowed-NIS lost-lock test (`NisWindow`): the test on constructed NIS sequences, and
its window mean, cap and threshold against a NumPy/SciPy reference on random sequences
with random update masks."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from neuralmap.filters.nis_window import NisWindow

D = torch.float64


def test_lost_lock_test_on_constructed_nis() -> None:
    w = 10
    win = NisWindow(3, w, 0.999)
    assert win.threshold == pytest.approx(chi2.ppf(0.999, w) / w, rel=1e-12)
    assert win.cap == float("inf")  # uncapped
    values = torch.tensor([1.0, 5.0, 50.0], dtype=D)  # consistent (χ²₁ mean 1), lost, short
    for k in range(w):
        win.add(values, torch.tensor([True, True, k < 3]))
        if k < w - 1:
            assert not bool(win.fired().any())  # no window full yet
    assert win.fired().tolist() == [False, True, False]  # the last window is not full yet
    assert win.mean().tolist() == pytest.approx([1.0, 5.0, 50.0])
    win.clear(torch.tensor([False, True, False]))
    assert win.fired().tolist() == [False, False, False]
    assert bool(win.mean()[1].isnan())
    off = NisWindow(1, 0, 0.999)  # disabled: never fires
    for _ in range(5):
        off.add(torch.tensor([1e6], dtype=D), torch.tensor([True]))
    assert not bool(off.fired().any()) and float(off.mean()[0]) == 1e6


def test_window_mean_cap_and_test_equal_a_numpy_reference() -> None:
    gen = torch.Generator().manual_seed(0)
    n, w, prob, steps = 4, 6, 0.99, 30
    win = NisWindow(n, w, prob, capped=True)
    threshold = chi2.ppf(prob, w) / w
    assert win.cap == pytest.approx(2.0 * threshold, rel=1e-12)
    history: list[list[float]] = [[] for _ in range(n)]
    for _ in range(steps):
        nis = torch.rand(n, generator=gen, dtype=D) * 8.0
        upd = torch.rand(n, generator=gen) < 0.7
        win.add(torch.where(upd, nis, float("nan")), upd)
        for i in range(n):
            if bool(upd[i]):
                history[i].append(min(float(nis[i]), 2.0 * threshold))
        for i in range(n):
            last = history[i][-w:]
            mean = float(win.mean()[i])
            if last:
                assert mean == pytest.approx(np.mean(last), rel=1e-12)
            else:
                assert np.isnan(mean)
            fired = len(history[i]) >= w and np.mean(last) > threshold
            assert bool(win.fired()[i]) == fired
