"""Differentiable TAN: learned noise model and refined map against hand and adaptive tuning.

On the same Monte Carlo draws the 5-state TAN EKF (SEEDS 004) flies with

* **hand-tuned**: paper 004's own P0, Q and R (``configs/scenarios/paper.yaml``);
* **consistent**: the truth's Q and R (the scenario's filter);
* **learned**: Q and R learned by maximum likelihood through the filter
  (`neuralmap.learning`) on *other* simulated flights, from a mis-specified start
  (Q × ``q_scale``, R × ``r_scale``);
* **variational**: the variational-Bayes adaptive filter (Huang et al. 2018) from the same
  mis-specified start (it adapts R and P⁻ online);
* **learned + refined map**: on a map carrying a known systematic error (a region biased by
  ``bias_m``), the learned filter on the original biased map and on the map refined from
  flights (`neuralmap.learning.map_refine.refine_map`), scored on draws not used for
  the refinement.

A linear-Gaussian anchor compares the gradient answer with EM (Shumway–Stoffer).
Targets: learned Q, R within ``target_param_rel`` of the truth; the learned filter's
time-averaged NEES in its 95 % band; gradient = EM fixed point to ``target_em_rel``;
map refinement divides the map error along the flown corridors of the biased region by
at least 2.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies import make_policy
from neuralmap.lab.metrics import divergence_rule, navigation_metrics
from neuralmap.lab.monte_carlo import FilterJob, run_filters
from neuralmap.lab.pcrb import pcrb, pcrb_position
from neuralmap.lab.scenario import load_scenario
from neuralmap.lab.simulator import simulate
from neuralmap.learning.covariance import COVARIANCE_KINDS
from neuralmap.learning.em import em_noise
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.likelihood import linear_log_likelihood
from neuralmap.learning.map_correction import BiasedTerrain, CorrectedTerrain
from neuralmap.learning.map_refine import refine_map
from neuralmap.learning.noise_fit import fit_noise
from neuralmap.learning.noise_model import NoiseModel
from neuralmap.linearize.factory import make_linearizer
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.studies.cluster_options import ClusterOptions
from neuralmap.studies.setup import prepare_tan
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain
from neuralmap.viz.navigation import plot_error_vs_time

__all__ = ["LearnedStudyConfig", "run"]

_STATES = ("x", "y", "h", "vx", "vy")


@dataclass
class LearnedStudyConfig(ClusterOptions):
    """Options of the learned-filter study (``study: learned``).

    Attributes:
        scenario: Scenario name or YAML (the truth and the consistent filter).
        hand_scenario: Scenario whose P0, Q, R are the hand tuning (paper 004's).
        map_source: ``neural`` (the trained map, ``map``) or ``grid`` (bicubic DEM).
        map: Neural map file (None = newest of the tile under ``runs_dir``).
        method: Linearisation of the map: ``neural`` or ``neural_region``.
        neural_fit_variance: Extra R of the neural map (None = measured).
        map_error_points: Points for that measurement.
        n_runs: Monte Carlo test draws (every configuration flies these).
        n_train_flights: Simulated flights for noise learning (other seeds).
        epochs, lr, tbptt_steps, batch_size, q_kind: Noise learning settings (also the
            refinement's flights per step). Default 200 flights per step: a step's cost is
            mostly fixed, so a flight costs about 1/2.3 of its cost in 100-flight steps
            and 1/10 of it in 25-flight steps (measured on jacksboro).
        lr_min_ratio: Cosine decay of the learning rate to ``lr · lr_min_ratio`` (1 = none).
        q_scale, r_scale: Mis-specified start: Q × q_scale, R × r_scale.
        vb_iterations: Variational-Bayes iterations per update.
        bias_m: Systematic map error of the refinement scenario, m (0 = no refinement).
        bias_box: ``[xmin, xmax, ymin, ymax]`` of the biased region, m from the tile origin.
        n_refine_flights: Flights for the refinement (their own seed).
        refine_epochs, refine_lr, correction_spacing_m, prior_sigma_m: Refinement settings.
        em_flights, em_steps, em_max_iter: The linear-Gaussian EM comparison.
        target_param_rel, target_em_rel, target_map_ratio: Targets.
        pcrb_factor, divergence_sigma: Divergence rule (as the tan study).
        cluster: Where the configurations' test filters run (one task per configuration on
            a Dask cluster, `neuralmap.lab.monte_carlo.run_filters`; bit-identical);
            default this process. Noise learning, refinement and EM run here.
    """

    study: str = "learned"
    experiment: str = "learned"
    threads: int | None = 1
    scenario: str = "jacksboro"
    hand_scenario: str = "paper"
    map_source: str = "neural"
    map: str | None = None
    method: str = "neural_region"
    neural_fit_variance: float | None = None
    map_error_points: int = 20000
    n_runs: int = 200
    n_train_flights: int = 1000
    epochs: int = 8
    lr: float = 0.1
    lr_min_ratio: float = 0.01
    tbptt_steps: int | None = 50
    batch_size: int | None = 200
    q_kind: str = "log_diagonal"
    q_scale: float = 0.1
    r_scale: float = 10.0
    vb_iterations: int = 3
    bias_m: float = 20.0
    bias_box: list[float] = field(default_factory=lambda: [17000.0, 23000.0, 13500.0, 18500.0])
    n_refine_flights: int = 200
    refine_epochs: int = 6
    refine_lr: float = 2.0
    correction_spacing_m: float = 500.0
    prior_sigma_m: float = 10.0
    em_flights: int = 8
    em_steps: int = 50
    em_max_iter: int = 20000
    target_param_rel: float = 0.10
    target_em_rel: float = 1e-3
    target_map_ratio: float = 0.5
    pcrb_factor: float = 5.0
    divergence_sigma: float = 9.0

    @property
    def methods(self) -> list[str]:
        """The linearisers `neuralmap.studies.setup.prepare_tan` builds."""
        return [self.method] if self.map_source == "neural" else ["bilinear"]

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option."""
        super().validate()
        if self.map_source not in ("neural", "grid"):
            raise NeuralMapError(f"--map_source must be neural or grid, got {self.map_source!r}.")
        if self.method not in ("neural", "neural_region"):
            raise NeuralMapError(f"--method must be neural or neural_region, got {self.method!r}.")
        if self.q_kind not in COVARIANCE_KINDS:
            raise NeuralMapError(f"--q_kind must be one of {COVARIANCE_KINDS}, got {self.q_kind!r}.")
        for name in ("n_runs", "n_train_flights", "epochs", "n_refine_flights", "refine_epochs",
                     "em_flights", "em_steps", "em_max_iter", "vb_iterations"):
            if getattr(self, name) < 1:
                raise NeuralMapError(f"--{name} must be >= 1, got {getattr(self, name)}.")
        for name in ("lr", "lr_min_ratio", "q_scale", "r_scale", "refine_lr", "correction_spacing_m",
                     "prior_sigma_m", "target_param_rel", "target_em_rel", "target_map_ratio"):
            if not getattr(self, name) > 0:
                raise NeuralMapError(f"--{name} must be > 0, got {getattr(self, name)}.")
        if len(self.bias_box) != 4 or not (self.bias_box[0] < self.bias_box[1]
                                           and self.bias_box[2] < self.bias_box[3]):
            raise NeuralMapError(
                f"--bias_box must be [xmin, xmax, ymin, ymax] with min < max, got {self.bias_box}.")


# ---------------------------------------------------------------------- helpers
def _check_bias_box(box: list[float], tile: Any) -> None:
    """The biased region must lie on the tile (offsets from its origin), else the
    refinement claims would be judged on no point at all.

    Raises:
        NeuralMapError: The box leaves the tile.
    """
    width = float(tile.extent[1] - tile.extent[0])
    height = float(tile.extent[3] - tile.extent[2])
    if not (0.0 <= box[0] and box[1] <= width and 0.0 <= box[2] and box[3] <= height):
        raise NeuralMapError(
            f"--bias_box {list(box)} leaves the tile '{tile.name}' (offsets from its origin "
            f"must lie in [0, {width:g}] x [0, {height:g}] m); give a box inside the tile or "
            "--bias_m 0 to skip the map refinement."
        )


def _with_tuning(scenario: Any, *, Q: list[float], R: float, P0: list[float] | None = None) -> Any:
    fit = scenario.fit_variance_m2 if scenario.fit_variance_m2 < R else 0.0
    return dataclasses.replace(scenario, Q_diag=[float(q) for q in Q], R_m2=float(R) - fit,
                               fit_variance_m2=fit,
                               P0_diag=list(P0 or scenario.P0_diag)).validate()


def _linear_problem(n_flights: int, n_steps: int, seed: int) -> dict[str, np.ndarray]:
    """A constant-velocity state observed through time-varying rows (the EM anchor)."""
    rng = np.random.default_rng(seed)
    F = np.array([[1.0, 1.0], [0.0, 1.0]])
    Q = np.diag([0.5, 0.02])
    P0 = np.diag([10.0, 1.0])
    x = rng.multivariate_normal(np.zeros(2), P0, size=n_flights)
    z = np.full((n_flights, n_steps + 1), np.nan)
    H = np.zeros((n_flights, n_steps + 1, 2))
    H[..., 0] = 1.0
    H[..., 1] = 0.3 * np.sin(np.arange(n_steps + 1) / 7.0)
    for k in range(1, n_steps + 1):
        x = x @ F.T + rng.multivariate_normal(np.zeros(2), Q, size=n_flights)
        z[:, k] = np.einsum("ni,ni->n", H[:, k], x) + 2.0 * rng.standard_normal(n_flights)
    return {"z": z, "H": H, "F": F, "Q": Q, "R": 4.0, "P0": P0}


def _em_comparison(config: LearnedStudyConfig, seed: int) -> dict[str, Any]:

    prob = _linear_problem(config.em_flights, config.em_steps, seed)
    q0 = np.diag(prob["Q"]) * 10.0
    r0 = prob["R"] * 10.0
    tick = time.perf_counter()
    noise = NoiseModel(torch.tensor(q0), r0)
    zt, Ht = torch.tensor(prob["z"]), torch.tensor(prob["H"])
    Ft, P0t = torch.tensor(prob["F"]), torch.tensor(prob["P0"])
    opt = torch.optim.LBFGS(noise.parameters(), lr=1, max_iter=100, tolerance_grad=1e-9,
                            tolerance_change=1e-14, line_search_fn="strong_wolfe")

    def closure() -> torch.Tensor:
        opt.zero_grad()
        loss = -linear_log_likelihood(zt, Ht, F=Ft, Q=noise.Q(), R=noise.R(),
                                      P0=P0t).log_likelihood.sum()
        loss.backward()
        return loss

    for _ in range(10):  # L-BFGS restarts until the gradient vanishes
        opt.step(closure)
        if max(float(p.grad.abs().max()) for p in noise.parameters()) < 1e-8:
            break
    grad_s = time.perf_counter() - tick
    g = noise.values()
    tick = time.perf_counter()
    em = em_noise(prob["z"], prob["H"], F=prob["F"], Q0=np.diag(q0), R0=r0, x0=np.zeros(2),
                  P0=prob["P0"], max_iter=config.em_max_iter, tol=1e-10)
    em_s = time.perf_counter() - tick
    grad_vals = np.array([*g["Q_diag"], g["R"]])
    em_vals = np.array([*np.diag(em.Q), em.R])
    rel = np.abs(grad_vals - em_vals) / np.abs(em_vals)
    return {
        "names": ["Q_pos", "Q_vel", "R"], "truth": [*np.diag(prob["Q"]).tolist(), prob["R"]],
        "gradient": grad_vals.tolist(), "em": em_vals.tolist(), "rel_diff": rel.tolist(),
        "max_rel_diff": float(rel.max()), "em_iterations": em.iterations,
        "em_converged": em.converged, "em_log_likelihood": em.log_likelihood,
        "em_R_path": em.R_path, "em_Q_path": em.Q_path, "gradient_s": grad_s, "em_s": em_s,
    }


def _corridor_error(biased: Any, refined: Any, world: Any, pos: torch.Tensor
                    ) -> dict[str, float]:
    """RMS map error (map − truth) at flown points inside the biased region."""
    with torch.no_grad():
        p = pos[..., :2].reshape(-1, 2).double()
        inside = biased.error(p) >= 0.999 * abs(biased.bias_m)
        if not bool(inside.any()):
            return {"n_points": 0, "original_rms_m": float("nan"), "refined_rms_m": float("nan"),
                    "ratio": float("nan")}
        p = p[inside]
        t = world(p).double()
        e0 = float((biased(p) - t).square().mean().sqrt())
        e1 = float((refined(p) - t).square().mean().sqrt())
    return {"n_points": int(p.shape[0]), "original_rms_m": e0, "refined_rms_m": e1,
            "ratio": e1 / e0 if e0 > 0 else float("nan")}


def _unflown_drift(correction: Any, flown: torch.Tensor, *, distance_m: float) -> dict[str, float]:
    """Largest |offset| at correction nodes farther than ``distance_m`` from every flown point."""
    nodes = correction.nodes().reshape(-1, 2)
    pts = flown[..., :2].reshape(-1, 2).double()
    pts = pts[:: max(pts.shape[0] // 20000, 1)]
    far = torch.ones(nodes.shape[0], dtype=torch.bool)
    for chunk in pts.split(4096):
        far &= torch.cdist(nodes, chunk).min(dim=1).values > distance_m
    offsets = correction.offsets.detach().reshape(-1)
    return {"n_unflown_nodes": int(far.sum()),
            "max_abs_offset_unflown_m": float(offsets[far].abs().max()) if bool(far.any())
            else float("nan"),
            "max_abs_offset_m": float(offsets.abs().max())}


# ---------------------------------------------------------------------- run

def _nees_text(nees: float | None, band: list[float] | None) -> str:
    """``NEES 3.84, band [4.75, 5.25]`` (``n/a`` for a missing value)."""
    nees_text = "n/a" if nees is None else f"{nees:.2f}"
    band_text = "n/a" if not band else "[" + ", ".join(f"{b:.2f}" for b in band) + "]"
    return f"NEES {nees_text}, band {band_text}"

def run(config: LearnedStudyConfig, outputs: StudyOutputs) -> None:
    """Learns, refines, flies every configuration on the same draws and fills ``outputs``."""

    started = time.perf_counter()
    timing: dict[str, float] = {}
    setup = prepare_tan(scenario=config.scenario, methods=config.methods, map_path=config.map,
                        runs_dir=config.runs_dir, seed=config.seed,
                        neural_fit_variance=config.neural_fit_variance,
                        map_error_points=config.map_error_points, device=config.torch_device)
    setup.pin(config)
    scenario, tile, seed, world = setup.scenario, setup.tile, setup.seed, setup.truth_terrain
    if config.bias_m != 0.0:
        _check_bias_box(config.bias_box, tile)  # before minutes of learning, not after
    dtype = config.torch_dtype
    if config.map_source == "neural":
        map_model, fit_var = setup.terrain_map, setup.fit_variance
    else:
        map_model, fit_var = GridTerrain(tile, method="bicubic", dtype=torch.float64), 0.0
    linearizer = make_linearizer(config.method, tile=tile, terrain=map_model, fit_variance=fit_var)
    consistent = TanModel.from_scenario(scenario)
    F, P0 = consistent.transition(dtype=dtype), consistent.filter_prior(dtype=dtype)
    truth_q = list(consistent.truth_Q)
    truth_r = consistent.truth_R + consistent.fit_variance
    print(f"learned: scenario {scenario.name}, map {config.map_source} ({config.method}), "
          f"{config.n_train_flights} training flights, {config.n_runs} test draws", flush=True)

    # ---- noise learning on flights other than the test draws
    tick = time.perf_counter()
    train_truth = simulate(scenario, tile, n_runs=config.n_train_flights, seed=seed + 1000,
                           dtype=dtype, truth_terrain=world)
    flights = FlightBatch.from_truth(train_truth)
    noise = NoiseModel([config.q_scale * q for q in consistent.Q],
                       config.r_scale * consistent.base_R, q_kind=config.q_kind)

    def log_epoch(epoch: int, rec: dict[str, Any]) -> None:
        outputs.log_scalar("learn/log_likelihood_per_update", rec["log_likelihood_per_update"],
                           epoch)
        outputs.log_scalar("learn/nees", rec["nees"], epoch)
        for i, name in enumerate(_STATES):
            if truth_q[i] > 0:
                outputs.log_scalar(f"learn/ratio_Q_{name}", rec["Q_diag"][i] / truth_q[i], epoch)
        outputs.log_scalar("learn/ratio_R", rec["R"] / truth_r, epoch)
        if config.progress:
            print(f"  epoch {epoch}: loglik/update {rec['log_likelihood_per_update']:.4f}, "
                  f"R {rec['R']:.2f}, Q {[round(q, 4) for q in rec['Q_diag']]}", flush=True)

    fit = fit_noise(flights, linearizer, noise, F=F, P0=P0, epochs=config.epochs, lr=config.lr,
                    tbptt_steps=config.tbptt_steps, batch_size=config.batch_size, seed=seed,
                    eval_flights=min(200, config.n_train_flights),
                    lr_min_ratio=config.lr_min_ratio, callback=log_epoch)
    timing["learn_noise"] = time.perf_counter() - tick
    learned = fit.history[-1]
    learned_q, learned_r = learned["Q_diag"], learned["R"]
    param_rows, param_rel = [], {}
    for i, name in enumerate(_STATES):
        rel = abs(learned_q[i] - truth_q[i]) / truth_q[i] if truth_q[i] > 0 else float("nan")
        param_rel[f"Q_{name}"] = rel
        param_rows.append([f"Q_{name}", truth_q[i], config.q_scale * consistent.Q[i],
                           learned_q[i], rel])
    param_rel["R"] = abs(learned_r - truth_r) / truth_r
    param_rows.append(["R (altimeter + fit variance)", truth_r,
                       config.r_scale * consistent.base_R, learned_r, param_rel["R"]])

    # ---- the test draws, every configuration
    tick = time.perf_counter()
    test = simulate(scenario, tile, n_runs=config.n_runs, seed=seed, dtype=dtype,
                    truth_terrain=world)
    kept = test.on_map.all(dim=1)
    if not bool(kept.any()):
        raise NeuralMapError(
            f"no run could be scored: all {config.n_runs} test trajectories left the tile "
            f"{tile.name!r} or started off it (--scenario {config.scenario}). Move the "
            "scenario's start_xy/waypoints inside the tile, shorten duration_s, or lower "
            "start_spread_m.")
    bound = pcrb(test, scenario, world.model, runs=kept)
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64)
    hand = load_scenario(config.hand_scenario)
    misspecified = _with_tuning(scenario, Q=[config.q_scale * q for q in consistent.Q],
                                R=config.r_scale * consistent.base_R)
    configurations: dict[str, tuple[Any, Any, Any, str]] = {
        "hand-tuned (paper 004)": (_with_tuning(scenario, Q=hand.Q_diag,
                                                R=hand.R_m2 + hand.fit_variance_m2,
                                                P0=hand.P0_diag), linearizer, None, "DEM map"),
        "consistent (truth)": (scenario, linearizer, None, "DEM map"),
        "mis-specified start": (misspecified, linearizer, None, "DEM map"),
        "learned": (_with_tuning(scenario, Q=learned_q, R=learned_r), linearizer, None,
                    "DEM map"),
        "variational (from start)": (misspecified, linearizer,
                                     make_policy("variational", {"iterations": config.vb_iterations},
                                                 where="learned.vb_iterations"), "DEM map"),
    }
    refine_info: dict[str, Any] = {}
    if config.bias_m != 0.0:
        tock = time.perf_counter()
        ox, oy = float(tile.extent[0]), float(tile.extent[2])
        box = (ox + config.bias_box[0], ox + config.bias_box[1], oy + config.bias_box[2],
               oy + config.bias_box[3])
        biased = BiasedTerrain(map_model, box, bias_m=config.bias_m)
        biased_lin = make_linearizer(config.method, tile=tile, terrain=biased,
                                     fit_variance=fit_var)
        refine_truth = simulate(scenario, tile, n_runs=config.n_refine_flights,
                                seed=seed + 2000, dtype=dtype, truth_terrain=world)
        learned_scn = _with_tuning(scenario, Q=learned_q, R=learned_r)
        learned_model = TanModel.from_scenario(learned_scn)
        refined = refine_map(
            FlightBatch.from_truth(refine_truth), biased_lin, extent=tuple(tile.extent), F=F,
            Q=learned_model.filter_process_noise(dtype=dtype), R=learned_model.base_R, P0=P0,
            spacing_m=config.correction_spacing_m, prior_sigma_m=config.prior_sigma_m,
            epochs=config.refine_epochs, lr=config.refine_lr, tbptt_steps=config.tbptt_steps,
            batch_size=config.batch_size, seed=seed)
        refined_map = CorrectedTerrain(biased, refined.correction)
        for rec in refined.history:
            outputs.log_scalar("refine/nll_per_update", rec["nll_per_update"], int(rec["epoch"]))
        refine_info = {
            "box_m": list(box), "bias_m": config.bias_m, "history": refined.history,
            "corridor_train": _corridor_error(biased, refined_map, world.model,
                                              refine_truth.pos),
            "corridor_test": _corridor_error(biased, refined_map, world.model, test.pos),
            "unflown": _unflown_drift(refined.correction, refine_truth.pos,
                                      distance_m=4.0 * config.correction_spacing_m),
        }
        timing["refine_map"] = time.perf_counter() - tock
        configurations["learned, biased map"] = (learned_scn, biased_lin, None,
                                                 f"map + {config.bias_m:g} m region")
        configurations["learned + refined map"] = (learned_scn, refined.linearizer, None,
                                                   "refined map")

    metrics: dict[str, Any] = {}
    rows = []
    filter_runs = run_filters(
        test, {name: FilterJob(lin, scn, policy=policy)
               for name, (scn, lin, policy, _) in configurations.items()},
        cluster=config.cluster, progress=config.progress)
    for name, (_, _, _, map_label) in configurations.items():
        run_ = filter_runs[name]
        m = navigation_metrics(run_, pcrb_pos, pcrb_factor=config.pcrb_factor,
                               divergence_sigma=config.divergence_sigma)
        metrics[name] = m
        for k, value in enumerate(m["rmse_pos_curve"]):
            if value is not None:
                outputs.log_scalar(f"rmse_pos/{name}", value, k)
        rows.append([name, map_label, m["rmse_pos_m"], m["final_pos_m"], m["divergence_rate"],
                     m.get("nees_time_avg"), m.get("nees_time_in_band")])
    timing["monte_carlo"] = time.perf_counter() - tick

    tick = time.perf_counter()
    em = _em_comparison(config, seed)
    timing["em"] = time.perf_counter() - tick

    # ---- report
    outputs.add_text(
        f"Scenario **{scenario.name}** (truth: {world.description}); map: "
        f"{config.map_source} ({config.method}). Noise learning: {config.n_train_flights} "
        f"simulated flights (seed {seed + 1000}), {config.epochs} epochs of Adam "
        f"(lr {config.lr}, cosine decay to ×{config.lr_min_ratio:g}; {config.batch_size} "
        f"flights per step; per-epoch records on the first 200 flights), TBPTT window {config.tbptt_steps}, {config.q_kind} Q, start "
        f"Q × {config.q_scale:g}, R × {config.r_scale:g}. Every configuration flies the "
        f"same {config.n_runs} test draws (seed {seed}). Divergence rule: "
        f"{divergence_rule(config.pcrb_factor, config.divergence_sigma)}")
    outputs.add_table("Learned noise parameters against the truth",
                      ["parameter", "truth", "start", "learned", "relative error"], param_rows,
                      note="R's truth is the altimeter variance plus the scenario's map fit "
                           "variance (what the consistent filter uses; the neural map's "
                           "measured extra variance is added by the linearizer for all).")
    outputs.add_table("Navigation on the same draws (horizontal position)",
                      ["configuration", "map", "RMSE all steps (m)", "final RMSE (m)",
                       "divergence", "time-avg NEES", "NEES in band"], rows)
    outputs.add_table("Linear-Gaussian anchor: gradient answer against EM (Shumway–Stoffer)",
                      ["parameter", "truth", "gradient (L-BFGS)", "EM fixed point",
                       "relative difference"],
                      [[n, t, g, e, r] for n, t, g, e, r in zip(
                          em["names"], em["truth"], em["gradient"], em["em"], em["rel_diff"],
                          strict=True)],
                      note=f"EM: {em['em_iterations']} iterations ({em['em_s']:.1f} s, "
                           f"converged: {em['em_converged']}); gradient {em['gradient_s']:.1f} s.")
    if refine_info:
        ct, cr = refine_info["corridor_test"], refine_info["corridor_train"]
        uf = refine_info["unflown"]
        outputs.add_table(
            "Map refinement: map error in the biased region along flown corridors",
            ["flights", "points", "original RMS (m)", "refined RMS (m)", "ratio"],
            [["refinement flights", cr["n_points"], cr["original_rms_m"], cr["refined_rms_m"],
              cr["ratio"]],
             ["held-out test draws", ct["n_points"], ct["original_rms_m"], ct["refined_rms_m"],
              ct["ratio"]]],
            note=f"Unflown correction nodes (> {4 * config.correction_spacing_m:g} m from every "
                 f"refinement flight): {uf['n_unflown_nodes']}, largest |offset| "
                 f"{uf['max_abs_offset_unflown_m']:.3g} m (largest anywhere "
                 f"{uf['max_abs_offset_m']:.3g} m).")

    # ---- targets
    learned_runs = RunCounts.from_metrics(metrics["learned"])
    worst = max(v for v in param_rel.values() if v == v)
    note = (f" ({config.n_train_flights} flights, not the target's 1000)"
            if config.n_train_flights < 1000 else "")
    outputs.add_claim("toolkit target", "learned Q and R within "
                      f"{config.target_param_rel:.0%} of the truth{note}",
                      ", ".join(f"{k} {v:.1%}" for k, v in param_rel.items()),
                      verdict(worst <= config.target_param_rel))
    nees_ok = metrics["learned"].get("nees_time_in_band")
    outputs.add_claim("toolkit target", "learned filter's time-averaged NEES in its 95 % band",
                      _nees_text(metrics["learned"].get("nees_time_avg"),
                                 metrics["learned"].get("nees_time_band_runs")),
                      verdict(None if nees_ok is None else bool(nees_ok)), runs=learned_runs)
    outputs.add_claim("toolkit target", "gradient answer = EM fixed point "
                      f"(linear-Gaussian) to {config.target_em_rel:g} relative",
                      f"max relative difference {em['max_rel_diff']:.2e}",
                      verdict(em["max_rel_diff"] <= config.target_em_rel))
    if refine_info:
        ratio = refine_info["corridor_test"]["ratio"]
        n_points = refine_info["corridor_test"]["n_points"]
        outputs.add_claim("toolkit target", "map refinement halves the map error along the "
                          "flown corridors of the biased region",
                          f"RMS {refine_info['corridor_test']['original_rms_m']:.2f} → "
                          f"{refine_info['corridor_test']['refined_rms_m']:.2f} m (×{ratio:.2f}, "
                          f"{n_points} points)",
                          verdict(ratio <= config.target_map_ratio) if n_points and ratio == ratio
                          else verdict(None, detail="no flown point in the biased region"))
        a = metrics["learned, biased map"]["rmse_pos_m"]
        b = metrics["learned + refined map"]["rmse_pos_m"]
        outputs.add_claim("toolkit target", "navigation on the refined map beats the original "
                          "map on draws not used for refinement",
                          f"RMSE {a:.2f} → {b:.2f} m",
                          verdict(None if a is None or b is None else b < a),
                          runs=RunCounts.weakest(
                              RunCounts.from_metrics(metrics["learned, biased map"]),
                              RunCounts.from_metrics(metrics["learned + refined map"])).all_runs())

    # ---- figures
    _figures(outputs, fit.history, truth_q, truth_r, metrics, em)
    outputs.results.update({
        "parameters": {"truth": {"Q_diag": truth_q, "R": truth_r},
                       "start": {"Q_diag": [config.q_scale * q for q in consistent.Q],
                                 "R": config.r_scale * consistent.base_R},
                       "learned": {"Q_diag": learned_q, "R": learned_r},
                       "relative_error": param_rel},
        "learning_history": fit.history,
        "navigation": {k: {kk: vv for kk, vv in v.items()
                           if not isinstance(vv, (list, dict)) or kk == "nees_time_band_runs"}
                       for k, v in metrics.items()},
        "curves": {"t": test.t.cpu().tolist(),
                   **{k: v["rmse_pos_curve"] for k, v in metrics.items()}},
        "em": {k: v for k, v in em.items() if k not in ("em_Q_path",)},
        "refinement": refine_info,
        "timing_s": {**timing, "total": time.perf_counter() - started},
    })


def _figures(outputs: StudyOutputs, history: list[dict[str, Any]], truth_q: list[float],
             truth_r: float, metrics: dict[str, Any], em: dict[str, Any]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    epochs = [h["epoch"] for h in history]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4))
    axes[0].plot(epochs, [h["log_likelihood_per_update"] for h in history], marker="o")
    axes[0].set_xlabel("epoch")
    axes[0].set_ylabel("log-likelihood per update")
    axes[0].set_title("Innovation log-likelihood (training flights)")
    for i, name in enumerate(_STATES):
        if truth_q[i] > 0:
            axes[1].plot(epochs, [h["Q_diag"][i] / truth_q[i] for h in history], label=f"Q_{name}")
    axes[1].plot(epochs, [h["R"] / truth_r for h in history], label="R", linewidth=2, color="k")
    axes[1].axhline(1.0, color="grey", linestyle="--")
    axes[1].set_yscale("log")
    axes[1].set_xlabel("epoch")
    axes[1].set_ylabel("learned / truth")
    axes[1].legend(fontsize=8)
    axes[1].set_title("Parameter trajectories")
    fig.tight_layout()
    outputs.add_figure("learning", fig, "Likelihood and parameter trajectories of noise learning")
    plt.close(fig)

    curves = {name: m["rmse_pos_curve"] for name, m in metrics.items()}
    steps = len(next(iter(curves.values())))
    fig = plot_error_vs_time(np.arange(steps), curves, None, xlabel="step",
                             title="Horizontal position error vs time, same draws")
    outputs.add_figure("error_vs_time", fig, "Horizontal position RMSE vs time, same draws")

    fig, ax = plt.subplots(figsize=(7, 4))
    path = np.asarray(em["em_R_path"])
    ax.plot(np.arange(1, len(path) + 1), np.abs(path - em["gradient"][-1]) / em["gradient"][-1],
            label="EM iterate R")
    ax.axhline(1e-3, color="grey", linestyle="--", label="1e-3")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("EM iteration")
    ax.set_ylabel("|R_EM − R_gradient| / R_gradient")
    ax.legend()
    fig.tight_layout()
    outputs.add_figure("em_vs_gradient", fig,
                       "EM (Shumway–Stoffer) iterates approach the gradient answer")
    plt.close(fig)
