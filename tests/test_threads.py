"""Thread control: one thread for small factorisations, the --threads check, cheap checks."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.validation import check_covariance
from neuralmap.threads import SMALL_MATRIX_MAX, one_thread, set_threads


@pytest.fixture
def two_threads():  # noqa: ANN201
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_one_thread_inside_and_restored(two_threads) -> None:  # noqa: ANN001, ARG001
    with one_thread(15):
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError), one_thread():
        raise RuntimeError("restored on error too")
    assert torch.get_num_threads() == 2
    with one_thread(SMALL_MATRIX_MAX + 1):  # large matrices keep the process setting
        assert torch.get_num_threads() == 2


def test_set_threads_names_the_option() -> None:
    before = torch.get_num_threads()
    try:
        set_threads(None)
        assert torch.get_num_threads() == before
        set_threads(1)
        assert torch.get_num_threads() == 1
        for bad in (0, -2, 1.5, True):
            with pytest.raises(NeuralMapError, match="--threads must be an integer >= 1"):
                set_threads(bad)  # type: ignore[arg-type]
    finally:
        torch.set_num_threads(before)


def test_diagonal_covariance_needs_no_factorisation(monkeypatch: pytest.MonkeyPatch) -> None:
    calls = []
    real = torch.linalg.cholesky_ex

    def counted(a: torch.Tensor, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(tuple(a.shape))
        return real(a, *args, **kwargs)

    monkeypatch.setattr(torch.linalg, "cholesky_ex", counted)
    d = torch.diag(torch.tensor([1.0, 2.0, 3.0], dtype=torch.float64))
    assert torch.equal(check_covariance(d, name="R", where="t", definite=True), d)
    assert calls == []
    with pytest.raises(NeuralMapError, match="zero variance"):
        check_covariance(torch.diag(torch.tensor([1.0, 0.0])), name="R", where="t",
                         definite=True)
    with pytest.raises(NeuralMapError, match="negative variance"):
        check_covariance(torch.diag(torch.tensor([1.0, -1.0])), name="Q", where="t",
                         definite=False)
    # off-diagonal terms: factorised (and an indefinite one refused)
    bad = torch.tensor([[1.0, 2.0], [2.0, 1.0]], dtype=torch.float64)
    with pytest.raises(NeuralMapError, match="is not positive definite"):
        check_covariance(bad, name="P0", where="t", definite=True)
    assert calls == [(1, 2, 2)]
