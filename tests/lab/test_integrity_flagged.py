"""Diverged runs flagged first (`neuralmap.lab.integrity.integrity_metrics`): a diverged run
must say so (status not tracking, or an HPL that still contains its error) before its error
leaves its HPL; counted here against hand-built flights whose answer is known."""

from __future__ import annotations

from types import SimpleNamespace

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.integrity import integrity_metrics
from neuralmap.nav.fix import STATUS_CODE

TRACKING, LOST = STATUS_CODE["tracking"], STATUS_CODE["lost"]


def _run(errors: list[list[float]], statuses: list[list[int]], hpl: float = 10.0):
    """A flight of ``N`` runs: horizontal errors (east only) and statuses per epoch, epoch 0
    the prior (not scored), a constant HPL."""
    e = torch.tensor(errors, dtype=torch.float64)
    n, k = e.shape
    err = torch.zeros(n, k, 5, dtype=torch.float64)
    err[..., 0] = e
    return SimpleNamespace(err=err, status=torch.tensor(statuses),
                           off_map=torch.zeros(n, dtype=torch.bool),
                           protection={0.01: torch.full((n, k), hpl, dtype=torch.float64)})


def test_diverged_runs_flagged_first_are_counted() -> None:
    t, lost = TRACKING, LOST
    run = _run([[0, 1, 2, 50, 90],    # silent: tracking when its error leaves the HPL
                [0, 1, 20, 60, 90],   # flagged: lost at the first exceedance
                [0, 1, 2, 3, 4],      # never exceeds the HPL: flagged
                [0, 30, 40, 50, 60]],  # not diverged (ignored)
               [[t, t, t, t, lost],
                [t, t, lost, lost, lost],
                [t, t, t, t, t],
                [t, t, t, t, t]])
    out = integrity_metrics(run, alert_limit_m=100.0, diverged=[True, True, True, False])
    assert out["risks"]["0.01"]["diverged_flagged"] == {"runs": 3, "flagged": 2}
    # without the flags the entry is absent, the rest unchanged
    plain = integrity_metrics(run, alert_limit_m=100.0)
    assert plain["risks"]["0.01"]["diverged_flagged"] is None
    assert plain["risks"]["0.01"]["misleading"] == out["risks"]["0.01"]["misleading"]


def test_diverged_flags_must_match_the_runs() -> None:
    run = _run([[0, 1], [0, 2]], [[TRACKING] * 2] * 2)
    with pytest.raises(NeuralMapError, match="diverged has 3 runs"):
        integrity_metrics(run, alert_limit_m=100.0, diverged=[True, False, True])
