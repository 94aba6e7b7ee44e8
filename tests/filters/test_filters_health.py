"""Per-sample health flags: a broken sample is flagged and frozen; the others are untouched.

"Untouched" is checked bit for bit: the healthy samples of a run with one broken sample
equal (torch.equal) those of the same run without the breakage.
"""

from __future__ import annotations

import torch

from neuralmap.filters import BatchedEKF

F64 = torch.float64
BATCH, N_STATE = 16, 5


def _problem(seed: int, steps: int, dtype: torch.dtype = F64) -> dict[str, object]:
    gen = torch.Generator().manual_seed(seed)
    F = torch.eye(N_STATE, dtype=F64)
    F[0, 3] = F[1, 4] = 1.0
    Q = torch.diag(torch.tensor([4.0, 4.0, 1.0, 0.1, 0.1], dtype=F64))
    P0 = torch.diag(torch.tensor([1e4, 1e4, 100.0, 4.0, 4.0], dtype=F64))
    H = torch.zeros(steps, BATCH, N_STATE, dtype=F64)
    H[..., :2] = 0.2 * torch.randn(steps, BATCH, 2, generator=gen, dtype=F64)
    H[..., 2] = 1.0
    r = 10.0 * torch.randn(steps, BATCH, generator=gen, dtype=F64)
    R = 100.0 + torch.rand(steps, BATCH, generator=gen, dtype=F64)
    x0 = torch.randn(BATCH, N_STATE, generator=gen, dtype=F64)
    cast = {k: v.to(dtype) for k, v in dict(F=F, Q=Q, P0=P0, H=H, r=r, R=R, x0=x0).items()}
    return cast


def _run(prob: dict, steps: int, *, hook=None) -> tuple[BatchedEKF, list[torch.Tensor]]:
    ekf = BatchedEKF(prob["x0"], prob["P0"])
    healthy = []
    for k in range(steps):
        ekf.predict(prob["F"], prob["Q"])
        r, H, R = prob["r"][k].clone(), prob["H"][k].clone(), prob["R"][k].clone()
        if hook is not None:
            r, H, R = hook(k, ekf, r, H, R)
        ekf.update(r, H, R)
        healthy.append(ekf.healthy.clone())
    return ekf, healthy


def _check_isolated(broken: BatchedEKF, clean: BatchedEKF, bad: int) -> None:
    others = torch.arange(BATCH) != bad
    assert bool(broken.healthy[others].all()) and not bool(broken.healthy[bad])
    assert torch.equal(broken.x[others], clean.x[others])
    assert torch.equal(broken.P[others], clean.P[others])
    # the frozen sample keeps its last healthy (finite) values
    assert bool(torch.isfinite(broken.x).all()) and bool(torch.isfinite(broken.P).all())


def test_nan_residual_flags_and_freezes_one_sample() -> None:
    steps, bad, at = 30, 3, 10
    for dtype in (F64, torch.float32):
        prob = _problem(0, steps, dtype)
        clean, _ = _run(prob, steps)
        frozen: dict[str, torch.Tensor] = {}

        def hook(k, ekf, r, H, R, frozen=frozen):
            if k == at:
                frozen["x"], frozen["P"] = ekf.x[bad].clone(), ekf.P[bad].clone()  # prior
                r[bad] = float("nan")
            return r, H, R

        broken, healthy = _run(prob, steps, hook=hook)
        assert bool(healthy[at - 1][bad]) and not bool(healthy[at][bad])
        _check_isolated(broken, clean, bad)
        # frozen at its last healthy values (the prior of the failed update): finite
        assert torch.equal(broken.x[bad], frozen["x"])
        assert torch.equal(broken.P[bad], frozen["P"])
        assert bool(torch.isfinite(broken.P).all()) and bool(torch.isfinite(broken.x).all())


def test_nan_jacobian_and_nan_variance_are_flagged() -> None:
    steps = 12
    prob = _problem(1, steps)
    clean, _ = _run(prob, steps)

    def hook(k, ekf, r, H, R):
        if k == 4:
            H[5, 0] = float("nan")
            R[9] = float("nan")
        return r, H, R

    broken, _ = _run(prob, steps, hook=hook)
    others = torch.ones(BATCH, dtype=torch.bool)
    others[[5, 9]] = False
    assert torch.equal(broken.healthy, others)
    assert torch.equal(broken.x[others], clean.x[others])
    assert torch.equal(broken.P[others], clean.P[others])


def test_injected_non_positive_definite_covariance_is_flagged_at_predict() -> None:
    steps, bad, at = 20, 7, 5
    prob = _problem(2, steps)
    clean, _ = _run(prob, steps)
    injected: dict[str, torch.Tensor] = {}

    def hook(k, ekf, r, H, R):
        if k == at:  # after this step's predict: break P of one sample, update runs next
            P = ekf.P.clone()
            P[bad] = torch.diag(torch.tensor([1e4, -50.0, 100.0, 4.0, 4.0], dtype=F64))
            ekf.P = P  # assignment is not validated: the health check must catch it
            injected["x"], injected["P"] = ekf.x[bad].clone(), P[bad].clone()
        return r, H, R

    broken, healthy = _run(prob, steps, hook=hook)
    assert not bool(healthy[at][bad])
    others = torch.arange(BATCH) != bad
    # the other samples' P was re-assigned to the same values: still bit-identical
    assert torch.equal(broken.x[others], clean.x[others])
    assert torch.equal(broken.P[others], clean.P[others])
    assert torch.equal(broken.P[bad], injected["P"])
    assert torch.equal(broken.x[bad], injected["x"])


def test_non_positive_definite_innovation_covariance_vector_update() -> None:
    gen = torch.Generator().manual_seed(3)
    P0 = torch.eye(4, dtype=F64).expand(6, 4, 4).clone()
    ekf = BatchedEKF(torch.zeros(6, 4, dtype=F64), P0)
    P = ekf.P.clone()
    P[2] = -5.0 * torch.eye(4, dtype=F64)  # makes S = H P Hᵀ + R indefinite for sample 2
    ekf.P = P
    H = torch.randn(6, 2, 4, generator=gen, dtype=F64)
    diag = ekf.update(torch.randn(6, 2, generator=gen, dtype=F64), H, 0.5 * torch.eye(2))
    expected = torch.ones(6, dtype=torch.bool)
    expected[2] = False
    assert torch.equal(diag.healthy, expected) and torch.equal(diag.applied, expected)
    assert torch.equal(ekf.P[2], P[2]) and torch.equal(ekf.x[2], torch.zeros(4, dtype=F64))
    ref = BatchedEKF(torch.zeros(6, 4, dtype=F64), P0)
    ref.update(diag.innovation, H, 0.5 * torch.eye(2))
    assert torch.equal(ekf.P[expected], ref.P[expected])


def test_frozen_sample_ignored_by_later_steps_and_check_pd_off() -> None:
    prob = _problem(4, 8)
    ekf = BatchedEKF(prob["x0"], prob["P0"], check_pd=False)
    ekf.predict(prob["F"], prob["Q"])
    r = prob["r"][0].clone()
    r[0] = float("inf")
    ekf.update(r, prob["H"][0], prob["R"][0])
    assert not bool(ekf.healthy[0]) and bool(ekf.healthy[1:].all())
    x0, P0 = ekf.x[0].clone(), ekf.P[0].clone()
    for k in range(1, 8):
        ekf.predict(prob["F"], prob["Q"])
        d = ekf.update(prob["r"][k], prob["H"][k], prob["R"][k])
        assert not bool(d.applied[0])
    assert torch.equal(ekf.x[0], x0) and torch.equal(ekf.P[0], P0)


def test_predict_checks_an_assigned_covariance_despite_the_certificate(monkeypatch) -> None:
    """A shared PD Q lets predict skip the Cholesky test (rounding-error certificate), but
    only while every stored P is known positive definite; an assigned P is re-tested."""
    import neuralmap.filters.ekf as ekf_module

    calls = {"pd_tests": 0}
    real = ekf_module._pd_from_entries

    def counting(*args, **kwargs):
        calls["pd_tests"] += 1
        return real(*args, **kwargs)

    monkeypatch.setattr(ekf_module, "_pd_from_entries", counting)
    prob = _problem(5, 1)
    ekf = BatchedEKF(prob["x0"], prob["P0"])
    Q = 0.1 * torch.eye(N_STATE, dtype=F64)
    ekf.predict(prob["F"], Q)  # certified (float64, Q = 0.1 I): no Cholesky test ran
    assert calls["pd_tests"] == 0
    assert bool(ekf.healthy.all())
    P = ekf.P.clone()
    P[6] = torch.diag(torch.tensor([1.0, -50.0, 1.0, 1.0, 1.0], dtype=F64))
    ekf.P = P
    ekf.predict(prob["F"], Q)  # an assigned P: the full test runs
    assert calls["pd_tests"] == 1
    expected = torch.ones(BATCH, dtype=torch.bool)
    expected[6] = False
    assert torch.equal(ekf.healthy, expected)
    assert torch.equal(ekf.P[6], P[6])
    ekf.predict(prob["F"], Q)  # certified again: the frozen sample stays as it was
    assert calls["pd_tests"] == 1
    assert torch.equal(ekf.P[6], P[6]) and torch.equal(ekf.healthy, expected)
