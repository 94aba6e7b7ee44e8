"""Least-squares plane over the window Omega = 6 sigma_x x 6 sigma_y (SEEDS 000, LCK = 0)."""

from __future__ import annotations

import torch

from neuralmap.linearize.window import WindowPlaneLinearizer


class PlaneFitLinearizer(WindowPlaneLinearizer):
    """Least-squares plane through ``n x n`` DEM samples of the window around the estimate.

    SEEDS 000 stochastic linearisation, LCK = 0: minimise ``sum (h_k - f(x_k, y_k))^2``
    over the window Omega = ``6 sigma_x x 6 sigma_y`` (SEEDS 000's region); slopes
    ``h_x, h_y`` are the plane's. Fixed windows: Omega_max (``sigma=400``), Omega_mean (240),
    Omega_min (80) m; ``sigma="adaptive"`` gives Omega_adp from the filter's covariance. The
    normal matrix of the symmetric pattern is constant and diagonal, so the solution is the
    closed form ``(X^T X)^-1 X^T h`` with a precomputed ``(3, n^2)`` matrix: one matmul per
    batch. Variance = residual variance ``sum(r^2) / (n^2 - 3)``.

    See `WindowPlaneLinearizer` for the arguments
    (``tile``, ``sigma``, ``n_samples``, ``min_sigma``, ``max_sigma``, ``dtype``).
    """

    def make_solver(self, pattern: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """Least-squares rule ``(X^T X)^-1 X^T``, shape ``(3, n^2)``."""
        gram = design.T @ design
        return torch.linalg.solve(gram, design.T)
