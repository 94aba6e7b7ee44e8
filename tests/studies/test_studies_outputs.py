"""The outputs writer's verdict rule: one vocabulary, too few runs give no verdict,
numerical failures are named."""

from __future__ import annotations

from pathlib import Path

import pytest

from neuralmap.outputs import (
    VERDICTS,
    RunCounts,
    StudyOutputs,
    check_verdict,
    verdict,
)


def test_verdict_words_and_the_run_rule() -> None:
    assert verdict(True) == "holds" and verdict(False) == "does not hold"
    assert verdict(False, partly=True) == "partly" and verdict(None) == "not measured"
    assert verdict(False, detail="by 12 %") == "does not hold (by 12 %)"
    assert verdict(True, runs=RunCounts(30, 60)) == "holds"
    # 29 of 40: too few; 30 of 61: less than half
    assert verdict(True, runs=RunCounts(29, 40)) == (
        "not enough converged runs (29 of 40; a verdict needs ≥ 30 and half)")
    assert verdict(True, runs=RunCounts(30, 61)).startswith("not enough converged runs (30 of 61")
    assert verdict(True, runs=RunCounts(0, 8, failed=8)).startswith(
        "not enough converged runs (0 of 8, 8 failed numerically")
    assert RunCounts(3, 100).all_runs().enough() and not RunCounts(3, 8).all_runs().enough()
    assert RunCounts.weakest(RunCounts(50, 60), RunCounts(40, 60)) == RunCounts(40, 60)
    assert RunCounts(50, 60, failed=4).bad_rate == pytest.approx(10 / 60)
    metrics = {"n_included": 90, "n_nonfinite": 10, "n_unhealthy": 5, "n_converged": 70}
    assert RunCounts.from_metrics(metrics) == RunCounts(70, 100, 15)
    for word in VERDICTS:
        assert check_verdict(word) == word
    for bad in ("reproduced", "not enough data", "not checked", "holds!"):
        with pytest.raises(ValueError, match="vocabulary"):
            check_verdict(bad)


def test_add_claim_applies_the_rule(tmp_path: Path) -> None:
    with StudyOutputs(tmp_path, config={"study": "x"}, title="t", echo=False,
                      tensorboard=False) as outputs:
        few = outputs.add_claim("SEEDS 002", "c", "1.0 m", "holds", runs=RunCounts(6, 8))
        failed = outputs.add_claim("SEEDS 002", "c", "1.0 m", "does not hold",
                                   runs=RunCounts(40, 50, failed=3))
        with pytest.raises(ValueError):
            outputs.add_claim("SEEDS 002", "c", "1.0 m", "reproduced")
    assert few.verdict.startswith("not enough converged runs (6 of 8")
    assert failed.verdict == "does not hold"
    assert failed.measured == "1.0 m; 3 of 50 runs failed numerically"
