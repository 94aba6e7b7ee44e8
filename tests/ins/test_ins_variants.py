"""Variants in lockstep (one IMU simulation for all filters) and the study on a Dask
cluster: the same numbers as each filter run on its own (bit-identical in float64), and
the tiny config's results as before the speed work."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.gnss import UrbanEffects, simulate_gnss
from neuralmap.ins.imu_model import ImuErrorProcess
from neuralmap.ins.loosely_coupled import (
    LooselyCoupledConfig,
    LooselyCoupledVariant,
    run_loosely_coupled,
    run_loosely_coupled_variants,
)
from neuralmap.ins.trajectory import short_drive
from neuralmap.studies.gnss_ins import GnssInsStudyConfig, build_policy

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY = REPO_ROOT / "configs" / "gnss_ins_tiny.yaml"
FIELDS = ("position_error", "velocity_error", "attitude_error", "std", "nees_position",
          "nees_navigation", "nis", "applied", "healthy")
# configs/gnss_ins_tiny.yaml, results of the study before the lockstep variants and the
# worker processes (each variant simulated and filtered on its own, one process):
# rmse_horizontal_m, spike_degraded_mean_m, nees_position_mean, rmse_heading_deg
BEFORE = {
    "plain": (0.028329228585585717, 0.10197207776172959, 2.9118141610063355,
              0.15834365548195484),
    "r_scaled": (0.03324554641724218, 0.12142481514991582, 0.7251916961750743,
                 0.18392443002413664),
    "inflation": (0.15346845785089477, 0.7899950345703459, 3.407270216762201,
                  4.540744840552257),
    "quality": (0.02712469831524975, 0.09121022839066048, 2.870629058439126,
                0.15720337781656843),
    "quality_inflation": (0.061610713824010975, 0.3216363293574411, 2.613064197520108,
                          0.8529086021753729),
    "windowed": (0.046943987042656184, 0.19261857931774481, 3.0557290296027113,
                 0.19033490424075367),
    "quality_windowed": (0.040145357303386676, 0.15102866184138192, 3.000613244643831,
                         0.18000887203030688),
    "raf": (0.029872534640678464, 0.10398527110746536, 3.0491680262338323,
            0.15942789747256206),
    "variational": (0.18323701237420215, 0.3745307017325521, 3.430016306866824,
                    0.17432514041178862),
}


def _case(seed: int = 3):  # type: ignore[no-untyped-def]
    traj = short_drive(duration=15.0, dt=0.05)
    gen = torch.Generator().manual_seed(seed)
    imu = ImuErrorProcess("tactical_mems", n_runs=5, dt=0.05, generator=gen)
    rec = simulate_gnss(traj, n_runs=5, lever_arm=[0.5, 0.2, -1.2], generator=gen,
                        effects=UrbanEffects.urban(traj.duration))
    return traj, imu, rec, gen


def test_lockstep_equals_each_variant_alone() -> None:
    study = GnssInsStudyConfig()
    names = ["plain", "r_scaled", "quality_windowed", "variational"]

    def variant(name: str) -> LooselyCoupledVariant:
        cfg = LooselyCoupledConfig(propagate_every=4, r_scale=2.5 if name == "r_scaled" else 1)
        return LooselyCoupledVariant(cfg, policy=build_policy(name, study))

    traj, imu, rec, gen = _case()
    together = run_loosely_coupled_variants(traj, imu, rec, {n: variant(n) for n in names},
                                            generator=gen)
    for name in names:
        traj, imu, rec, gen = _case()
        v = variant(name)
        alone = run_loosely_coupled(traj, imu, rec, v.config, generator=gen, policy=v.policy)
        for field in FIELDS:
            a, b = getattr(together[name], field), getattr(alone, field)
            assert torch.equal(torch.nan_to_num(a), torch.nan_to_num(b)), (name, field)
            assert torch.equal(a.isnan(), b.isnan()), (name, field)
        assert together[name].counts == alone.counts
    # the draws differ with the seed: the comparison can fail
    traj, imu, rec, gen = _case(seed=4)
    other = run_loosely_coupled(traj, imu, rec, variant("plain").config, generator=gen)
    assert not torch.equal(other.position_error, together["plain"].position_error)


def test_shared_policy_is_refused() -> None:
    traj, imu, rec, gen = _case()
    policy = build_policy("quality_windowed", GnssInsStudyConfig())
    cfg = LooselyCoupledConfig()
    with pytest.raises(NeuralMapError, match="share one policy"):
        run_loosely_coupled_variants(traj, imu, rec, {
            "a": LooselyCoupledVariant(cfg, policy=policy),
            "b": LooselyCoupledVariant(cfg, policy=policy)}, generator=gen)
    with pytest.raises(NeuralMapError, match="at least one"):
        run_loosely_coupled_variants(traj, imu, rec, {}, generator=gen)


def _study(tmp_path: Path, name: str, *extra: str) -> dict:  # type: ignore[type-arg]
    import neuralmap.studies.cli as cli

    assert cli.main(["--config", str(TINY), "--runs_dir", str(tmp_path), "--experiment", name,
                     *extra]) == 0
    return json.loads((tmp_path / name / "version_0" / "results.json").read_text())


@pytest.mark.slow
def test_tiny_config_as_before_and_a_dask_cluster_changes_nothing(tmp_path: Path) -> None:
    one = _study(tmp_path, "one")
    for name, values in BEFORE.items():
        s = one["variants"][name]
        got = (s["rmse_horizontal_m"], s["spike_degraded_mean_m"], s["nees_position_mean"],
               s["rmse_heading_deg"])
        assert got == pytest.approx(values, rel=1e-9, abs=0), name
    pytest.importorskip("distributed")
    two = _study(tmp_path, "two", "--cluster", "local:2")
    assert two["variants"] == one["variants"]
    assert two["curves"] == one["curves"]


def test_bad_cluster_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    import neuralmap.studies.cli as cli

    assert cli.main(["--config", str(TINY), "--cluster", "local:0"]) == 2
    assert "--cluster" in capsys.readouterr().err


def test_variants_are_dealt_by_cost() -> None:
    from neuralmap.studies.gnss_ins import VARIANTS, deal_variants

    groups = deal_variants(list(VARIANTS), 2)
    assert sorted(v for g in groups for v in g) == sorted(VARIANTS)
    assert all(g == sorted(g, key=list(VARIANTS).index) for g in groups)
    assert [len(g) for g in groups] == [4, 5]  # the costlier variational filter: 4 + 1.2
    assert deal_variants(["plain"], 2) == [["plain"]]
    assert deal_variants(list(VARIANTS), 1) == [list(VARIANTS)]
