"""TensorBoard logging of a Monte Carlo navigation evaluation.

Tags: ``rmse_pos/<method>``, ``rmse_pos_converged/<method>``, ``rmse_vel/<method>`` and
``pcrb_pos`` against the time step; ``final_pos_error/<method>`` histograms;
``summary/<metric>/<method>`` scalars (figures: `StudyOutputs.add_figure`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

import numpy as np

_CURVE_TAGS: dict[str, str] = {
    "rmse_pos_curve": "rmse_pos",
    "rmse_pos_converged_curve": "rmse_pos_converged",
    "rmse_vel_curve": "rmse_vel",
}


def log_navigation(
    writer: Any,
    *,
    curves: Mapping[str, Mapping[str, object]],
    pcrb_pos: object,
    final_errors: Mapping[str, object],
    summary: Mapping[str, Mapping[str, object]] | None = None,
) -> None:
    """Writes the evaluation's curves, histograms and summary scalars into ``writer`` (the
    study's one writer, `StudyOutputs.writer`; figures go through
    `StudyOutputs.add_figure`).

    Non-finite values are skipped (TensorBoard cannot plot them).

    Args:
        writer: A ``torch.utils.tensorboard.SummaryWriter`` (kept open).
        curves: Method -> {``rmse_pos_curve`` | ``rmse_pos_converged_curve`` |
            ``rmse_vel_curve`` -> ``(K+1,)``}.
        pcrb_pos: ``(K+1,)`` horizontal PCRB, metres.
        final_errors: Method -> ``(N,)`` final horizontal error, metres.
        summary: Method -> {metric name -> scalar}, logged as ``summary/<metric>/<method>``.
    """
    for method, method_curves in curves.items():
        for key, values in method_curves.items():
            tag = _CURVE_TAGS.get(key)
            if tag is None:
                continue
            for step, value in enumerate(np.asarray(values, dtype=np.float64).reshape(-1)):
                if math.isfinite(value):
                    writer.add_scalar(f"{tag}/{method}", value, global_step=step)
    for step, value in enumerate(np.asarray(pcrb_pos, dtype=np.float64).reshape(-1)):
        if math.isfinite(value):
            writer.add_scalar("pcrb_pos", value, global_step=step)
    for method, values in final_errors.items():
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        array = array[np.isfinite(array)]
        if array.size:
            writer.add_histogram(f"final_pos_error/{method}", array, global_step=0)
    for method, metrics in (summary or {}).items():
        for key, value in metrics.items():
            if isinstance(value, (int, float, np.integer, np.floating)) and math.isfinite(
                float(value)
            ):
                writer.add_scalar(f"summary/{key}/{method}", float(value), global_step=0)
    writer.flush()
