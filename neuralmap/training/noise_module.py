"""NoiseLearningModule: learn the TAN filter's Q and R from flights with Lightning.

``python train.py noise --config configs/learn_noise.yaml`` trains it on
`FlightDataModule` (`neuralmap.training.cli.NoiseMode`).
Each training batch of flights is cut into windows of ``tbptt_steps`` filter steps
(truncated back-propagation through time, manual optimisation: one optimiser step per
window, the filter state carried detached). The loss is the negative innovation
log-likelihood per update (`neuralmap.learning.likelihood.tan_log_likelihood`).

TensorBoard: ``train/nll``, ``val/nll`` (whole validation flights), ``val/nees`` (when the
truth is known) and ``params/Q_<i>``, ``params/R`` beside ``truth/Q_<i>``, ``truth/R`` and
their ratios ``ratio/Q_<i>``, ``ratio/R`` (learned / truth). At the end of fitting, the
learned filter settings are written as a scenario YAML (``learned_scenario.yaml`` in the run
folder) that ``evaluate.py --scenario <that file>`` flies.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.covariance import COVARIANCE_KINDS
from neuralmap.learning.likelihood import tan_log_likelihood
from neuralmap.learning.noise_fit import make_optimizer, nees_summary
from neuralmap.learning.noise_model import NoiseModel

__all__ = ["NoiseLearningModule", "learned_scenario"]

_STATE_NAMES = ("x", "y", "h", "vx", "vy")


def learned_scenario(scenario: Any, noise: NoiseModel, *, name: str | None = None) -> Any:
    """A copy of ``scenario`` whose filter uses the learned Q and R.

    ``Q_diag`` = the learned diagonal (a log-Cholesky Q's correlations cannot be written in
    a scenario and are dropped); ``R_m2 + fit_variance_m2`` = the learned R (the map fit
    variance is kept when smaller than R, else set to 0). ``P0_diag`` is not learned.
    """
    import dataclasses

    values = noise.values()
    r = float(values["R"])
    fit = float(scenario.fit_variance_m2) if scenario.fit_variance_m2 < r else 0.0
    return dataclasses.replace(
        scenario, name=name or f"{scenario.name}_learned",
        description=f"{scenario.name} with Q and R learned by maximum likelihood through the "
                    "TAN filter (neuralmap.learning).",
        Q_diag=[float(v) for v in values["Q_diag"]], R_m2=r - fit, fit_variance_m2=fit,
    ).validate()


class NoiseLearningModule(pl.LightningModule):
    """Maximum-likelihood Q and R of the TAN EKF (SEEDS 004 model) through the filter.

    Args:
        scenario: Scenario name or YAML (Φ, P0, the truth for the logs, the tile).
        method: Map linearisation method (``neuralmap.linearize`` names).
        map: Neural map file for ``neural*`` methods.
        q_kind: ``log_diagonal`` or ``log_cholesky``.
        q_scale: Start Q = ``q_scale ×`` the scenario's ``Q_diag`` (mis-specified start).
        r_scale: Start R = ``r_scale ×`` the scenario's ``R_m2 + fit_variance_m2``.
        lr: Learning rate on the log-parameters.
        optimizer: ``adam`` or ``sgd``.
        tbptt_steps: Truncation window, filter steps (None = whole flights).

    Raises:
        NeuralMapError: Bad option values.
    """

    def __init__(self, scenario: str = "jacksboro", method: str = "bilinear",
                 map: str | None = None, q_kind: str = "log_diagonal", q_scale: float = 0.1,
                 r_scale: float = 10.0, lr: float = 0.1, optimizer: str = "adam",
                 tbptt_steps: int | None = 50) -> None:
        super().__init__()
        if q_kind not in COVARIANCE_KINDS:
            raise NeuralMapError(f"--model.q_kind must be one of {COVARIANCE_KINDS}, got {q_kind!r}.")
        if not (q_scale > 0 and r_scale > 0 and lr > 0):
            raise NeuralMapError(
                f"--model.q_scale, r_scale and lr must be > 0, got {q_scale}, {r_scale}, {lr}.")
        if tbptt_steps is not None and tbptt_steps < 1:
            raise NeuralMapError(f"--model.tbptt_steps must be >= 1 (or null), got {tbptt_steps}.")
        self.save_hyperparameters()
        self.automatic_optimization = False
        from neuralmap.lab.scenario import load_scenario
        from neuralmap.tan.model import TanModel

        self.scenario = load_scenario(scenario)
        self.tan = TanModel.from_scenario(self.scenario)
        q0 = [q_scale * q for q in self.tan.Q]
        if min(q0) <= 0.0:
            raise NeuralMapError(
                f"scenario {self.scenario.name!r}: Q_diag {list(self.tan.Q)} has a zero "
                "variance; the log parametrisations need every start variance > 0.")
        self.noise = NoiseModel(q0, r_scale * self.tan.base_R, q_kind=q_kind)
        self.linearizer: Any = None
        self.learned_path: Path | None = None
        #: filter updates the training made (a fit of zero updates exports nothing)
        self.n_updates_seen = 0

    # ------------------------------------------------------------------ setup
    def setup(self, stage: str) -> None:
        """Checks the flights' world against the filter's; builds the linearizer on the
        scenario's tile (and map).

        Raises:
            NeuralMapError: The data module's scenario has another tile or time step
                (`check_same_world`).
        """
        data_scenario = getattr(getattr(self.trainer, "datamodule", None), "scenario", None)
        if data_scenario is not None:
            from neuralmap.training.flight_datamodule import check_same_world

            check_same_world(self.scenario, data_scenario)
        if self.linearizer is not None:
            return
        from neuralmap.lab.scenario import scenario_tile
        from neuralmap.linearize.factory import TERRAIN_MODEL_METHODS, make_linearizer

        tile = scenario_tile(self.scenario)
        method = self.hparams.method
        if method in TERRAIN_MODEL_METHODS:
            if not self.hparams.map:
                raise NeuralMapError(
                    f"--model.method {method} needs --model.map <neural_map.pt> (a map of the "
                    f"{tile.name} tile from python train.py).")
            from neuralmap.terrain.export import load_map

            terrain = load_map(self.hparams.map)
            self.linearizer = make_linearizer(method, tile=tile, terrain=terrain)
        else:
            self.linearizer = make_linearizer(method, tile=tile)

    def _matrices(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.tan.transition(), self.tan.filter_prior()

    def _flights(self, which: str, index: torch.Tensor) -> Any:
        dm = self.trainer.datamodule
        flights = dm.train_flights if which == "train" else dm.val_flights
        return flights.subset(index.cpu())

    # ------------------------------------------------------------------ steps
    def training_step(self, batch: Any, batch_idx: int) -> None:
        (index,) = batch
        flights = self._flights("train", index)
        opt = self.optimizers()
        F, P0 = self._matrices()
        window = self.hparams.tbptt_steps or flights.n_steps
        state, total, count = None, 0.0, 0
        for start in range(1, flights.n_steps + 1, window):
            stop = min(start + window, flights.n_steps + 1)
            run = tan_log_likelihood(flights, self.linearizer, F=F, Q=self.noise.Q(),
                                     R=self.noise.R(), P0=P0, state=state, start=start,
                                     stop=stop)
            n_upd = int(run.n_updates.sum())
            if n_upd > 0:
                loss = -run.log_likelihood.sum() / n_upd
                opt.zero_grad()
                self.manual_backward(loss)
                opt.step()
                total += float(loss.detach()) * n_upd
                count += n_upd
                self.n_updates_seen += n_upd
            state = run.state.detach()
        self.log("train/nll", total / max(count, 1), on_step=False, on_epoch=True,
                 prog_bar=True, batch_size=flights.n_flights)

    def validation_step(self, batch: Any, batch_idx: int) -> None:
        (index,) = batch
        flights = self._flights("val", index)
        F, P0 = self._matrices()
        run = tan_log_likelihood(flights, self.linearizer, F=F, Q=self.noise.Q(),
                                 R=self.noise.R(), P0=P0)
        n_upd = max(int(run.n_updates.sum()), 1)
        metrics = {"val/nll": float(-run.log_likelihood.sum()) / n_upd}
        nees = nees_summary(run.nees)
        if nees == nees:
            metrics["val/nees"] = nees
        values = self.noise.values()
        truth_q, truth_r = self.tan.truth_Q, self.tan.truth_R + self.tan.fit_variance
        for i, name in enumerate(_STATE_NAMES):
            metrics[f"params/Q_{name}"] = values["Q_diag"][i]
            metrics[f"truth/Q_{name}"] = truth_q[i]
            if truth_q[i] > 0:
                metrics[f"ratio/Q_{name}"] = values["Q_diag"][i] / truth_q[i]
        metrics.update({"params/R": values["R"], "truth/R": truth_r,
                        "ratio/R": values["R"] / truth_r})
        self.log_dict(metrics, batch_size=flights.n_flights)

    def configure_optimizers(self) -> Any:
        return make_optimizer(self.hparams.optimizer, self.noise.parameters(), self.hparams.lr)

    def on_fit_end(self) -> None:
        """Writes ``learned_scenario.yaml`` into the run folder."""
        from neuralmap.lab.scenario import save_scenario

        if not self.trainer.is_global_zero:
            return
        if self.n_updates_seen == 0:
            raise NeuralMapError(
                "the fit made no filter update (every altimeter reading was missing or off "
                "the map), so Q and R are still the starting guess; nothing was exported. "
                "Check the flights' radar column and that ins_x / ins_y lie on the tile.")
        log_dir = getattr(self.trainer.logger, "log_dir", None) if self.trainer.logger else None
        folder = Path(log_dir or self.trainer.default_root_dir)
        folder.mkdir(parents=True, exist_ok=True)
        self.learned_path = save_scenario(learned_scenario(self.scenario, self.noise),
                                          folder / "learned_scenario.yaml")
