"""Bad filter input raises NeuralMapError saying what is wrong (and expected vs got shapes)."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF

F64 = torch.float64


def _ekf(batch: int = 4, n: int = 3) -> BatchedEKF:
    return BatchedEKF(torch.zeros(batch, n, dtype=F64), torch.eye(n, dtype=F64))


@pytest.mark.parametrize(
    ("P0", "match"),
    [
        (torch.tensor([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]), "not symmetric"),
        (torch.diag(torch.tensor([1.0, -2.0, 1.0])), "negative variance"),
        (torch.diag(torch.tensor([1.0, 0.0, 1.0])), "zero variance"),
        (torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
         "not positive definite"),
        (torch.full((3, 3), float("nan")), "NaN or infinite"),
        (torch.eye(4), r"shape \(4, 4\), expected \(3, 3\) or \(N, 3, 3\) = \(4, 3, 3\)"),
        (torch.eye(3).expand(5, 3, 3), r"shape \(5, 3, 3\)"),
    ],
)
def test_bad_initial_covariance(P0: torch.Tensor, match: str) -> None:
    with pytest.raises(NeuralMapError, match=match):
        BatchedEKF(torch.zeros(4, 3, dtype=F64), P0)


def test_bad_covariance_in_batch_names_the_sample() -> None:
    P0 = torch.eye(3, dtype=F64).expand(6, 3, 3).clone()
    P0[4, 0, 1] = P0[4, 1, 0] = 3.0
    with pytest.raises(NeuralMapError, match=r"'P0' is not positive definite \(sample 4\)"):
        BatchedEKF(torch.zeros(6, 3, dtype=F64), P0)


def test_bad_initial_state() -> None:
    with pytest.raises(NeuralMapError, match=r"'x0' has shape \(3,\), expected \(N, n\)"):
        BatchedEKF(torch.zeros(3), torch.eye(3))
    with pytest.raises(NeuralMapError, match="NaN or infinite"):
        BatchedEKF(torch.tensor([[0.0, float("nan")]]), torch.eye(2))
    with pytest.raises(NeuralMapError, match="dtype"):
        BatchedEKF(torch.zeros(2, 2), torch.eye(2), dtype=torch.int32)


def test_bad_predict_inputs() -> None:
    ekf = _ekf()
    Q = 0.1 * torch.eye(3)
    with pytest.raises(NeuralMapError, match=r"'F' has shape \(2, 2\), expected \(3, 3\)"):
        ekf.predict(torch.eye(2), Q)
    with pytest.raises(NeuralMapError, match="'F' contains NaN"):
        ekf.predict(torch.full((3, 3), float("nan")), Q)
    with pytest.raises(NeuralMapError, match="'Q' has a negative variance"):
        ekf.predict(torch.eye(3), torch.diag(torch.tensor([1.0, -1.0, 1.0])))
    with pytest.raises(NeuralMapError, match="'Q' is not positive semi-definite"):
        ekf.predict(torch.eye(3), torch.tensor([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0, 0, 1.0]]))
    with pytest.raises(NeuralMapError, match="'Q' is not symmetric"):
        ekf.predict(torch.eye(3), torch.tensor([[1.0, 0.3, 0.0], [0.0, 1.0, 0.0], [0, 0, 1.0]]))
    ekf.predict(torch.eye(3), torch.zeros(3, 3))  # zero process noise is a valid PSD Q
    assert bool(ekf.healthy.all())


def test_bad_update_inputs() -> None:
    ekf = _ekf()
    r, H = torch.zeros(4), torch.ones(4, 3)
    expected = r"'residual' has shape \(5,\), expected \(N,\) or \(N, m\)"
    with pytest.raises(NeuralMapError, match=expected):
        ekf.update(torch.zeros(5), H, 1.0)
    expected = r"'H' has shape \(4, 2\), expected \(N, m, n\) = \(4, 1, 3\)"
    with pytest.raises(NeuralMapError, match=expected):
        ekf.update(r, torch.ones(4, 2), 1.0)
    with pytest.raises(NeuralMapError, match=r"'H' has shape \(4, 2, 3\)"):
        ekf.update(torch.zeros(4, 3), torch.ones(4, 2, 3), torch.eye(3))
    with pytest.raises(NeuralMapError, match="not a valid measurement variance"):
        ekf.update(r, H, -1.0)
    with pytest.raises(NeuralMapError, match="not a valid measurement variance"):
        ekf.update(r, H, 0.0)
    with pytest.raises(NeuralMapError, match="'R' has a negative variance -2.0 at sample 2"):
        ekf.update(r, H, torch.tensor([1.0, 1.0, -2.0, 1.0]))
    with pytest.raises(NeuralMapError, match=r"'R' has shape \(3,\)"):
        ekf.update(r, H, torch.ones(3))
    with pytest.raises(NeuralMapError, match="'R' is not positive definite"):
        ekf.update(torch.zeros(4, 2), torch.ones(4, 2, 3), torch.tensor([[1.0, 3.0], [3.0, 1.0]]))
    with pytest.raises(NeuralMapError, match=r"'R' is not positive definite \(sample 1\)"):
        R = torch.eye(2).expand(4, 2, 2).clone()
        R[1] = torch.tensor([[1.0, 3.0], [3.0, 1.0]])
        ekf.update(torch.zeros(4, 2), torch.ones(4, 2, 3), R)
    with pytest.raises(NeuralMapError, match="'mask' must be a bool tensor"):
        ekf.update(r, H, 1.0, mask=torch.ones(4))
    with pytest.raises(NeuralMapError, match=r"'mask' has shape \(3,\)"):
        ekf.update(r, H, 1.0, mask=torch.ones(3, dtype=torch.bool))
    assert bool(ekf.healthy.all()) and torch.equal(ekf.x, torch.zeros(4, 3, dtype=F64))


def test_state_assignment_shape_checked() -> None:
    ekf = _ekf()
    with pytest.raises(NeuralMapError, match=r"'P' has shape \(4, 2, 2\), expected \(N, n, n\)"):
        ekf.P = torch.eye(2).expand(4, 2, 2)
    with pytest.raises(NeuralMapError, match=r"'x' has shape \(3, 3\)"):
        ekf.x = torch.zeros(3, 3)
    ekf.x = torch.ones(4, 3)
    assert torch.equal(ekf.x, torch.ones(4, 3, dtype=F64))
