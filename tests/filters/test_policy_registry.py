"""make_policy: every registry name builds the right policy with the papers' defaults; bad
names and options are clear; studies and the benchmark build from the one registry."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf import BatchedEKF
from neuralmap.filters.policies import (
    IGG3,
    POLICIES,
    POLICY_NAMES,
    ChiSquareGate,
    Compose,
    Huber,
    InnovationInflation,
    QualityR,
    RobustAdaptive,
    SageHusa,
    VariationalAdaptive,
    WindowedInflation,
    YangAdaptive,
    make_policy,
    policy_label,
    quality_members,
)

EXPECTED = {
    "ekf": type(None),
    "chi2": ChiSquareGate,
    "huber": Huber,
    "igg3": IGG3,
    "yang": YangAdaptive,
    "raf": RobustAdaptive,
    "inflation": InnovationInflation,
    "quality": QualityR,
    "quality_gnss": QualityR,
    "raf_quality": Compose,
    "quality_inflation": Compose,
    "quality_gnss_inflation": Compose,
    "windowed_inflation": WindowedInflation,
    "quality_gnss_windowed": Compose,
    "sage_husa": SageHusa,
    "variational": VariationalAdaptive,
}


def _one_update(policy) -> torch.Tensor:  # noqa: ANN001
    """One 2-state, 1-measurement update of 3 samples; returns the posterior P."""
    ekf = BatchedEKF(torch.zeros(3, 2, dtype=torch.float64),
                     torch.eye(2, dtype=torch.float64) * 100.0)
    ekf.predict(torch.eye(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64), policy=policy)
    for taker in quality_members(policy):
        taker.set_quality(torch.tensor([[1.0, 500.0, 1.0]] * 3, dtype=torch.float64)
                          if len(taker.names) == 3 else
                          torch.tensor([[1.5, 0.99, 12.0, 0.03]] * 3, dtype=torch.float64))
    H = torch.tensor([[[1.0, 0.5]]], dtype=torch.float64).expand(3, 1, 2)
    r = torch.tensor([[1.0], [-2.0], [40.0]], dtype=torch.float64)
    ekf.update(r, H, torch.tensor([[4.0]], dtype=torch.float64), policy=policy)
    return ekf.P


def test_every_name_builds_a_fresh_policy_of_its_class_that_runs() -> None:
    assert set(POLICY_NAMES) == set(EXPECTED)
    for name in POLICY_NAMES:
        policy = make_policy(name)
        assert type(policy) is EXPECTED[name] or isinstance(policy, EXPECTED[name]), name
        assert policy_label(name) != name and len(policy_label(name)) > 5
        if policy is not None:
            assert make_policy(name) is not policy  # per-sample state: never shared
            if "windowed" in name:  # default block: position + velocity of the 15-state
                policy = make_policy(name, {"block": [0, 1], "window": 1})
            P = _one_update(policy)
            assert torch.isfinite(P).all() and torch.linalg.eigvalsh(P).min() > 0, name


def test_defaults_are_the_papers_tunings() -> None:
    raf = make_policy("raf")
    igg, yang = raf.policies
    assert (igg.k0, igg.k1) == (1.5, 4.5)
    assert (yang.c0, yang.c1) == (1.5, 8.5)  # SEEDS 002, not the class defaults (1, 3)
    assert make_policy("chi2").p == 0.99 and make_policy("huber").k == 1.345
    assert make_policy("inflation").c0 == 1.2
    sh = make_policy("sage_husa", {"R_min": 2.0, "R_max": 50.0, "adapt_Q": True})
    assert sh.b == 0.97 and sh.adapt_Q
    vb = make_policy("variational")
    assert vb.iterations == 3 and vb.rho == pytest.approx(1.0 - math.exp(-4.0))
    quality, inflation = make_policy("quality_gnss_inflation", {"weight": 0.4, "c0": 1.1}).policies
    assert [i.weight for i in quality.indicators] == [0.4] * 4 and inflation.c0 == 1.1
    # overrides reach the members of a composition
    _, raf_member = make_policy("raf_quality", {"c1": 5.0}).policies
    assert raf_member.policies[1].c1 == 5.0
    assert POLICIES["raf"].defaults == {"k0": 1.5, "k1": 4.5, "c0": 1.5, "c1": 8.5}


@pytest.mark.parametrize(
    ("name", "args", "match"),
    [
        ("kalman", None, r"unknown policy 'kalman'; choose one of ekf, chi2"),
        ("raf", [1.5, 4.5], r"'policy_args' of 'raf' must be a mapping"),
        ("raf", {"k2": 1.0}, r"policy 'raf' has no option\(s\) k2; it accepts: k0, k1, c0, c1"),
        ("chi2", {"p": 1.5}, r"must lie in \(0, 1\)"),
        ("ekf", {"p": 0.9}, "accepts: none"),
    ],
)
def test_bad_names_and_options_are_clear(name: str, args: object, match: str) -> None:
    with pytest.raises(NeuralMapError, match=match):
        make_policy(name, args, where="--policies")  # type: ignore[arg-type]


def test_compose_forwards_quality_into_nested_compositions() -> None:
    """``Compose(QualityR, RobustAdaptive)``: RAF is a composition without a quality member;
    the indicators reach the QualityR and the update uses them."""
    policy = Compose(QualityR.altimeter(), RobustAdaptive(1.5, 4.5, 1.5, 8.5))
    policy.set_quality(torch.tensor([[30.0, 500.0, 1.0]] * 3, dtype=torch.float64))
    assert len(quality_members(policy)) == 1
    with pytest.raises(NeuralMapError, match="no member takes quality"):
        RobustAdaptive().set_quality(torch.zeros(3, 3))


def test_studies_and_benchmark_build_from_the_registry() -> None:
    """The old copies disagreed on RAF (the benchmark's was c0 = 1, c1 = 3)."""
    import importlib.util
    import sys
    from pathlib import Path

    from neuralmap.studies.gnss_ins import GnssInsStudyConfig, build_policy
    from neuralmap.studies.tan_outliers import study_policy
    from neuralmap.studies.wind import DEFAULT_FILTERS
    from neuralmap.wind.comparison import WindFilterSpec
    from neuralmap.wind.comparison import make_policy as wind_policy

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_filter.py"
    spec = importlib.util.spec_from_file_location("bench_filter_registry", path)
    bench = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = bench  # dataclasses resolve the module by name
    spec.loader.exec_module(bench)
    rafs = [
        study_policy("raf", R=100.0),
        build_policy("raf", GnssInsStudyConfig()),
        wind_policy(WindFilterSpec(**next(f for f in DEFAULT_FILTERS if f["name"] == "RAF"))),
        bench.policy_factories()["RobustAdaptive (RAF)"](),
    ]
    for raf in rafs:
        assert [(p.c0, p.c1) for p in raf.policies[1:]] == [(1.5, 8.5)]
    sh = study_policy("sage_husa", R=100.0)
    assert (float(sh.R_min), float(sh.R_max)) == (25.0, 10000.0)
