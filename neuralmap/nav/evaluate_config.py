"""Typed configuration of ``evaluate.py`` (parsed by jsonargparse from YAML and the CLI)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from neuralmap.exceptions import NeuralMapError

#: Methods evaluated when ``--methods`` is not given (issue 3 §5).
DEFAULT_METHODS: tuple[str, ...] = (
    "neural",
    "neural_region",
    "bilinear",
    "nine_point",
    "mean_point",
    "lsq_adaptive",
    "lsq_min",
)

#: Every method name ``evaluate.py`` accepts.
KNOWN_METHODS: tuple[str, ...] = (
    *DEFAULT_METHODS,
    "lsq_max",
    "lsq_mean",
    "bicubic",
)


@dataclass
class EvaluateConfig:
    """Options of the Monte Carlo navigation evaluation.

    Attributes:
        map: Exported neural map (``neural_map.pt``); ``None`` = the newest
            ``<runs_dir>/*/version_*/neural_map.pt``.
        scenario: Scenario name (``configs/scenarios/<name>.yaml``) or a YAML path.
        n_runs: Monte Carlo trajectories (the same truth for every method).
        methods: Linearisation methods to compare; ``neural`` uses the map with autograd.
        experiment: Output folder name: results go to
            ``<runs_dir>/<experiment>/version_<N>/``.
        runs_dir: Root of the run folders (also searched for the newest map).
        seed: Seed of the truth trajectories and noises; ``None`` = the scenario's seed.
        device: Torch device for the filters (``cpu``, ``cuda``, ``cuda:1``...).
        dtype: Filter precision.
        neural_fit_variance: Extra variance (m²) the ``neural`` method adds to R as its
            linearisation variance, on top of the scenario's ``fit_variance_m2`` that every
            method gets (SEEDS 004: the fit error is treated as white noise added to R).
            ``None`` = whatever the scenario's value leaves uncovered of the map's measured
            fit error: ``max(rmse² − fit_variance_m2, 0)`` with ``rmse`` the fit RMSE
            recorded in the map file (``metrics["rmse_m"]``, written by ``train.py``; 0
            when none is recorded).
        threads: ``torch.set_num_threads`` for the run (restored afterwards); ``None``
            keeps torch's setting. 1 is fastest for small runs on a busy machine.
        n_plot_trajectories: Trajectories drawn over the hillshade.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        sigma_factor: Divergence when the final error exceeds this times the filter's own
            3σ horizontal bound.
        progress: Show progress bars.
        tensorboard: Write TensorBoard event files.
    """

    map: str | None = None
    scenario: str = "jacksboro"
    n_runs: int = 1000
    methods: list[str] = field(default_factory=lambda: list(DEFAULT_METHODS))
    experiment: str = "evaluate"
    runs_dir: str = "runs"
    seed: int | None = None
    device: str = "cpu"
    dtype: Literal["float64", "float32"] = "float64"
    neural_fit_variance: float | None = None
    threads: int | None = None
    n_plot_trajectories: int = 5
    pcrb_factor: float = 5.0
    sigma_factor: float = 3.0
    progress: bool = True
    tensorboard: bool = True

    def validate(self) -> None:
        """Checks values; raises :class:`NeuralMapError` naming the option and the fix."""
        if self.n_runs < 1:
            raise NeuralMapError(f"--n_runs must be >= 1, got {self.n_runs}.")
        if not self.methods:
            raise NeuralMapError(
                f"--methods is empty; pick one or more of {', '.join(KNOWN_METHODS)}."
            )
        unknown = [m for m in self.methods if m not in KNOWN_METHODS]
        if unknown:
            raise NeuralMapError(
                f"--methods: unknown method(s) {unknown}; known: {', '.join(KNOWN_METHODS)}."
            )
        if len(set(self.methods)) != len(self.methods):
            raise NeuralMapError(f"--methods lists a method twice: {self.methods}.")
        if not self.experiment or "/" in self.experiment or self.experiment.startswith("."):
            raise NeuralMapError(
                f"--experiment must be a plain folder name, got '{self.experiment}'."
            )
        if self.seed is not None and self.seed < 0:
            raise NeuralMapError(f"--seed must be >= 0 (or null), got {self.seed}.")
        if self.neural_fit_variance is not None and not self.neural_fit_variance >= 0:
            raise NeuralMapError(
                f"--neural_fit_variance must be >= 0 m^2 (or null), got {self.neural_fit_variance}."
            )
        if self.threads is not None and self.threads < 1:
            raise NeuralMapError(f"--threads must be >= 1 (or null), got {self.threads}.")
        if self.n_plot_trajectories < 0:
            raise NeuralMapError(
                f"--n_plot_trajectories must be >= 0, got {self.n_plot_trajectories}."
            )
        if not (self.pcrb_factor > 0 and self.sigma_factor > 0):
            raise NeuralMapError(
                f"--pcrb_factor and --sigma_factor must be > 0, got {self.pcrb_factor}, "
                f"{self.sigma_factor}."
            )
