"""BatchedEKF against FilterPy's float64 single-filter EKF, and its dtype/device behaviour.

Reference: ``filterpy.kalman.ExtendedKalmanFilter`` (Joseph-form update
``P = (I-KH)P(I-KH)' + KRK'``, explicit ``inv(S)``), one filter per sample, fed the very
same residual through its ``residual`` hook. Tolerance: 1e-9 relative (to the largest
|entry|) on x and P after hundreds of random steps.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from filterpy.kalman import ExtendedKalmanFilter

from neuralmap.filters import BatchedEKF, UpdateDiagnostics
from neuralmap.filters.ekf import positive_definite_batchlast

F64 = torch.float64


def _random_F(
    gen: torch.Generator, n: int, *, dense: bool, batch: int | None = None
) -> torch.Tensor:
    shape = (n, n) if batch is None else (batch, n, n)
    if dense:
        F = torch.eye(n, dtype=F64) + 0.3 * torch.randn(shape, generator=gen, dtype=F64)
    else:  # TAN-like sparse Φ with a random period
        F = torch.eye(n, dtype=F64).expand(shape).clone()
        F[..., 0, n - 2] = 0.5 + torch.rand(shape[:-2], generator=gen, dtype=F64)
        F[..., 1, n - 1] = 0.5 + torch.rand(shape[:-2], generator=gen, dtype=F64)
    # keep the spectral radius <= 1 so that P stays bounded over hundreds of steps
    rho = torch.linalg.eigvals(F).abs().amax(-1)
    return F / rho.clamp_min(1.0)[..., None, None]


def _random_spd(
    gen: torch.Generator, shape: tuple[int, ...], scale: float, floor: float
) -> torch.Tensor:
    n = shape[-1]
    A = torch.randn(shape, generator=gen, dtype=F64)
    return scale * A @ A.transpose(-2, -1) / n + floor * torch.eye(n, dtype=F64)


def _filterpy_bank(x0: torch.Tensor, P0: torch.Tensor, m: int) -> list[ExtendedKalmanFilter]:
    bank = []
    for i in range(x0.shape[0]):
        kf = ExtendedKalmanFilter(dim_x=x0.shape[1], dim_z=m)
        kf.x = x0[i].numpy().copy()[:, None]
        kf.P = (P0[i] if P0.ndim == 3 else P0).numpy().copy()
        bank.append(kf)
    return bank


def _per(t: torch.Tensor, i: int, ndim: int) -> np.ndarray:
    """Sample i of a possibly shared tensor (shared = ndim dims)."""
    return (t if t.ndim == ndim else t[i]).numpy()


def _run_against_filterpy(
    *, n: int, m: int, batch: int, steps: int, seed: int, dense_F: bool,
    per_sample_F: bool, per_sample_H: bool, per_sample_R: bool,
) -> tuple[BatchedEKF, list[ExtendedKalmanFilter], UpdateDiagnostics]:
    gen = torch.Generator().manual_seed(seed)
    x0 = 10.0 * torch.randn(batch, n, generator=gen, dtype=F64)
    P0 = _random_spd(gen, (batch, n, n), 50.0, 1.0)
    ekf = BatchedEKF(x0, P0)
    bank = _filterpy_bank(x0, P0, m)
    diag = None
    for _ in range(steps):
        F = _random_F(gen, n, dense=dense_F, batch=batch if per_sample_F else None)
        Q = _random_spd(gen, (batch, n, n) if per_sample_F else (n, n), 0.5, 0.01)
        if per_sample_H:
            H = torch.randn((batch, m, n) if m > 1 else (batch, n), generator=gen, dtype=F64)
        else:
            H = torch.randn((m, n), generator=gen, dtype=F64)
        if per_sample_R:
            R = (_random_spd(gen, (batch, m, m), 2.0, 0.2) if m > 1
                 else 0.2 + torch.rand(batch, generator=gen, dtype=F64))
        else:
            R = _random_spd(gen, (m, m), 2.0, 0.2)
        r = torch.randn((batch, m) if m > 1 else (batch,), generator=gen, dtype=F64)
        ekf.predict(F, Q)
        diag = ekf.update(r, H, R)
        for i, kf in enumerate(bank):
            kf.F = _per(F, i, 2)
            kf.Q = _per(Q, i, 2)
            kf.predict()
            Hi = (H[i] if per_sample_H else H).reshape(m, n).numpy()
            Ri = (R[i] if per_sample_R else R).reshape(m, m).numpy()
            kf.update(
                r[i].reshape(m, 1).numpy(), HJacobian=lambda _x, Hi=Hi: Hi,
                Hx=lambda _x, m=m: np.zeros((m, 1)), R=Ri,
            )
    assert diag is not None
    return ekf, bank, diag


def _assert_rel(actual: torch.Tensor, expected: np.ndarray, rel: float) -> None:
    expected_t = torch.as_tensor(expected, dtype=F64)
    scale = expected_t.abs().max().clamp_min(1e-300)
    err = (actual.to(F64) - expected_t).abs().max() / scale
    assert err <= rel, f"max relative error {float(err):.3g} > {rel}"


CASES = {
    "scalar-sparseF-perH": dict(m=1, dense_F=False, per_sample_F=False, per_sample_H=True,
                                per_sample_R=True),
    "scalar-denseF-sharedH": dict(m=1, dense_F=True, per_sample_F=False, per_sample_H=False,
                                  per_sample_R=False),
    "scalar-perF": dict(m=1, dense_F=True, per_sample_F=True, per_sample_H=True,
                        per_sample_R=True),
    "vector3-perH-perR": dict(m=3, dense_F=True, per_sample_F=False, per_sample_H=True,
                              per_sample_R=True),
    "vector2-shared": dict(m=2, dense_F=False, per_sample_F=True, per_sample_H=False,
                           per_sample_R=False),
    # n = 10 > SMALL_STATE_MAX: batched-kernel paths (dense predict, cholesky_ex checks)
    "n10-scalar": dict(n=10, m=1, dense_F=True, per_sample_F=False, per_sample_H=True,
                       per_sample_R=True),
    "n10-vector": dict(n=10, m=3, dense_F=False, per_sample_F=False, per_sample_H=True,
                       per_sample_R=False),
}


@pytest.mark.parametrize("case", list(CASES))
def test_matches_filterpy(case: str) -> None:
    opts = dict(CASES[case])
    n = opts.pop("n", 5)
    ekf, bank, diag = _run_against_filterpy(n=n, batch=6, steps=300, seed=1, **opts)
    m = opts["m"]
    x_ref = np.stack([kf.x[:, 0] for kf in bank])
    P_ref = np.stack([kf.P for kf in bank])
    assert bool(ekf.healthy.all())
    _assert_rel(ekf.x, x_ref, 1e-9)
    _assert_rel(ekf.P, P_ref, 1e-9)
    # diagnostics of the last update
    _assert_rel(diag.S, np.stack([kf.S for kf in bank]), 1e-9)
    _assert_rel(diag.gain, np.stack([kf.K for kf in bank]), 1e-9)
    _assert_rel(diag.innovation, np.stack([kf.y[:, 0] for kf in bank]), 1e-12)
    nis_ref = np.array([(kf.y.T @ kf.SI @ kf.y).item() for kf in bank])
    _assert_rel(diag.nis, nis_ref, 1e-9)
    assert diag.innovation.shape == (6, m) and diag.S.shape == (6, m, m)
    assert diag.gain.shape == (6, n, m) and diag.nis.shape == (6,)
    assert bool(diag.applied.all()) and bool(diag.healthy.all())


def test_covariance_exactly_symmetric_and_snapshots_stay_valid() -> None:
    gen = torch.Generator().manual_seed(3)
    ekf = BatchedEKF(torch.zeros(50, 5, dtype=F64), _random_spd(gen, (5, 5), 100.0, 1.0))
    before = ekf.P
    before_copy = before.clone()
    for _ in range(20):
        ekf.predict(_random_F(gen, 5, dense=True), _random_spd(gen, (5, 5), 1.0, 0.1))
        ekf.update(torch.randn(50, generator=gen, dtype=F64),
                   torch.randn(50, 5, generator=gen, dtype=F64), 3.0)
        assert torch.equal(ekf.P, ekf.P.transpose(1, 2))
    assert torch.equal(before, before_copy)  # the old view was never written in place


def test_sparse_and_dense_transition_plans_agree() -> None:
    gen = torch.Generator().manual_seed(4)
    P0 = _random_spd(gen, (30, 5, 5), 10.0, 1.0)
    F = _random_F(gen, 5, dense=False)
    Q = _random_spd(gen, (5, 5), 1.0, 0.1)
    a = BatchedEKF(torch.zeros(30, 5, dtype=F64), P0)
    a.predict(F, Q)  # sparse plan
    b = BatchedEKF(torch.zeros(30, 5, dtype=F64), P0)
    b.predict(F.expand(30, 5, 5), Q.expand(30, 5, 5))  # per-sample path
    ref = F @ P0 @ F.T + Q
    torch.testing.assert_close(a.P, ref, rtol=1e-13, atol=1e-12)
    torch.testing.assert_close(b.P, ref, rtol=1e-13, atol=1e-12)


def test_float32_tracks_float64() -> None:
    gen = torch.Generator().manual_seed(5)
    batch, n = 200, 5
    x0 = torch.randn(batch, n, generator=gen, dtype=F64)
    P0 = torch.diag(torch.tensor([1e4, 1e4, 1e4, 40.0, 40.0], dtype=F64))
    F = torch.eye(n, dtype=F64)
    F[0, 3] = F[1, 4] = 1.0
    Q = torch.diag(torch.tensor([100.0, 100.0, 100.0, 10.0, 1.0], dtype=F64))
    e64 = BatchedEKF(x0, P0)
    e32 = BatchedEKF(x0.float(), P0.float())
    assert e32.dtype == torch.float32 and e32.P.dtype == torch.float32
    for _ in range(100):
        H = torch.zeros(batch, n, dtype=F64)
        H[:, :2] = 0.3 * torch.randn(batch, 2, generator=gen, dtype=F64)
        H[:, 2] = 1.0
        R = 100.0 + 10.0 * torch.rand(batch, generator=gen, dtype=F64)
        r = 10.0 * torch.randn(batch, generator=gen, dtype=F64)
        for e in (e64, e32):
            e.predict(F, Q)
            d = e.update(r, H, R)
    assert bool(e32.healthy.all()) and d.nis.dtype == torch.float32
    for a, b in ((e32.x, e64.x), (e32.P, e64.P)):
        scale = b.abs().amax(dim=tuple(range(1, b.ndim)), keepdim=True)
        assert float(((a.double() - b).abs() / scale).max()) < 1e-4


def test_mask_skips_samples_exactly() -> None:
    gen = torch.Generator().manual_seed(6)
    ekf = BatchedEKF(torch.randn(8, 5, generator=gen, dtype=F64),
                     _random_spd(gen, (5, 5), 10.0, 1.0))
    x_before, P_before = ekf.x.clone(), ekf.P.clone()
    mask = torch.tensor([True, False, True, True, False, True, True, True])
    r = torch.randn(8, generator=gen, dtype=F64)
    r[1] = float("nan")  # garbage where masked: no effect, no error, no flag
    H = torch.randn(8, 5, generator=gen, dtype=F64)
    H[4] = float("inf")
    R = torch.full((8,), 2.0, dtype=F64)
    R[4] = -1.0  # an invalid variance of a masked sample is ignored
    diag = ekf.update(r, H, R, mask=mask)
    assert bool(ekf.healthy.all())
    assert torch.equal(diag.applied, mask)
    assert torch.equal(ekf.x[~mask], x_before[~mask])
    assert torch.equal(ekf.P[~mask], P_before[~mask])
    assert not torch.equal(ekf.x[mask], x_before[mask])
    # the unmasked samples match an unmasked run on the same inputs
    ref = BatchedEKF(x_before[mask], P_before[0])
    ref.update(r[mask], H[mask], R[mask])
    assert torch.equal(ekf.x[mask], ref.x) and torch.equal(ekf.P[mask], ref.P)


def test_positive_definite_batchlast_matches_cholesky() -> None:
    gen = torch.Generator().manual_seed(7)
    for n in (1, 3, 5, 10):
        A = torch.randn(400, n, n, generator=gen, dtype=F64)
        M = A @ A.transpose(1, 2) - 0.5 * n * torch.rand(400, 1, 1, generator=gen, dtype=F64) * (
            torch.eye(n, dtype=F64))
        M[3, 0, 0] = float("nan")
        M[5, n - 1, n - 1] = float("inf")
        expected = (torch.linalg.cholesky_ex(M).info == 0) & torch.isfinite(M).all(-1).all(-1)
        got = positive_definite_batchlast(M.permute(1, 2, 0).contiguous())
        assert 0 < int(expected.sum()) < 400
        assert torch.equal(got, expected)


def test_differentiable_through_steps() -> None:
    """Gradients of the final state w.r.t. residuals and R agree with finite differences."""
    gen = torch.Generator().manual_seed(8)
    n, batch = 3, 2
    F = _random_F(gen, n, dense=True)
    Q = _random_spd(gen, (n, n), 0.5, 0.1)
    H = torch.randn(3, batch, n, generator=gen, dtype=F64)
    P0 = _random_spd(gen, (n, n), 5.0, 1.0)

    def run(r: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        ekf = BatchedEKF(torch.zeros(batch, n, dtype=F64), P0)
        for k in range(3):
            ekf.predict(F, Q)
            ekf.update(r[k], H[k], R[k])
        return torch.cat([ekf.x.reshape(-1), ekf.P.reshape(-1)])

    r = torch.randn(3, batch, generator=gen, dtype=F64, requires_grad=True)
    R = (1.0 + torch.rand(3, batch, generator=gen, dtype=F64)).requires_grad_(True)
    assert torch.autograd.gradcheck(run, (r, R))


def test_default_dtype_and_device_follow_x0() -> None:
    ekf = BatchedEKF(torch.zeros(4, 2, dtype=torch.int64), torch.eye(2))
    assert ekf.dtype == torch.float64 and ekf.x.dtype == torch.float64
    assert ekf.device == torch.device("cpu")
    assert ekf.x.shape == (4, 2) and ekf.P.shape == (4, 2, 2) and ekf.healthy.shape == (4,)
    # inputs of another dtype are cast
    ekf.predict(torch.eye(2, dtype=torch.float32), 0.1 * torch.eye(2, dtype=torch.float32))
    d = ekf.update(torch.ones(4, dtype=torch.float32), torch.tensor([1.0, 0.0]), 1.0)
    assert d.nis.dtype == torch.float64


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:  # pragma: no cover - only on GPU machines
    gen = torch.Generator().manual_seed(9)
    x0 = torch.randn(64, 5, generator=gen, dtype=F64)
    P0 = _random_spd(gen, (5, 5), 10.0, 1.0)
    F = _random_F(gen, 5, dense=False)
    Q = _random_spd(gen, (5, 5), 1.0, 0.1)
    H = torch.randn(64, 5, generator=gen, dtype=F64)
    r = torch.randn(64, generator=gen, dtype=F64)
    cpu = BatchedEKF(x0, P0)
    gpu = BatchedEKF(x0.cuda(), P0.cuda())
    for e in (cpu, gpu):
        e.predict(F, Q)
        e.update(r, H, 2.0)
    assert gpu.P.device.type == "cuda"
    torch.testing.assert_close(gpu.P.cpu(), cpu.P, rtol=1e-12, atol=1e-12)


def test_second_update_after_one_predict_does_not_reuse_q() -> None:
    """After one update P is a posterior, not Φ P Φᵀ + Q: a second update offers no Q.

    Constructed case: P⁻ = 101 I (Q = 100 I), a first update with r = 0 (λ = 0, α = 1), then
    a second with r = 30 (α ≈ 377). Reusing Q would give α P⁺ − (α − 1) Q with a negative
    variance; without Q the policy inflates the whole P (α P⁺). Reference: NumPy float64
    Joseph form on α P⁺.
    """
    from neuralmap.filters.policies import InnovationInflation

    seen: list[object] = []

    class Recording(InnovationInflation):
        def adapt(self, context):  # type: ignore[no-untyped-def]
            seen.append(context.process_noise)
            return super().adapt(context)

    policy = Recording(c0=1.2)
    ekf = BatchedEKF(torch.zeros(1, 2, dtype=F64), torch.eye(2, dtype=F64))
    ekf.predict(torch.eye(2, dtype=F64), 100.0 * torch.eye(2, dtype=F64))
    H = torch.tensor([[1.0, 0.0]], dtype=F64)
    ekf.update(torch.zeros(1, 1, dtype=F64), H, 1.0, policy=policy)
    p1 = ekf.P[0].numpy().copy()
    x1 = ekf.x[0].numpy().copy()
    diag = ekf.update(torch.full((1, 1), 30.0, dtype=F64), H, 1.0, policy=policy)
    assert seen[0] is not None and seen[1] is None
    lam = 900.0 / (p1[0, 0] + 1.0)
    alpha = lam / 1.2
    torch.testing.assert_close(diag.policy_info["alpha"], torch.tensor([alpha], dtype=F64))
    p_use = alpha * p1
    h = np.array([[1.0, 0.0]])
    s = h @ p_use @ h.T + 1.0
    k = p_use @ h.T / s
    i_kh = np.eye(2) - k @ h
    p_ref = i_kh @ p_use @ i_kh.T + k @ k.T
    x_ref = x1 + (k * 30.0)[:, 0]
    assert bool(ekf.healthy.all()) and bool(diag.applied.all())
    np.testing.assert_allclose(ekf.P[0].numpy(), p_ref, rtol=1e-12, atol=0)
    np.testing.assert_allclose(ekf.x[0].numpy(), x_ref, rtol=1e-12, atol=1e-12)
    # a new predict offers its Q again; assigning P withdraws it
    ekf.predict(torch.eye(2, dtype=F64), 100.0 * torch.eye(2, dtype=F64))
    ekf.P = ekf.P.clone()
    ekf.update(torch.zeros(1, 1, dtype=F64), H, 1.0, policy=policy)
    assert seen[2] is None


def test_trusted_noise_predict_gives_the_same_numbers() -> None:
    # a per-sample Q that is finite and exactly symmetric: skipping its validation changes
    # no number; the health check still flags an indefinite Q
    import torch

    from neuralmap.filters import BatchedEKF

    gen = torch.Generator().manual_seed(0)
    n, batch = 5, 4
    a = torch.randn(batch, n, n, generator=gen, dtype=torch.float64)
    F = torch.eye(n, dtype=torch.float64) + 0.1 * a
    b = torch.randn(batch, n, n, generator=gen, dtype=torch.float64)
    Q = b @ b.transpose(1, 2) * 1e-2
    P0 = torch.eye(n, dtype=torch.float64)
    checked = BatchedEKF(torch.zeros(batch, n, dtype=torch.float64), P0)
    trusted = BatchedEKF(torch.zeros(batch, n, dtype=torch.float64), P0)
    checked.predict(F, Q)
    trusted.predict(F, Q, trusted_noise=True)
    assert torch.equal(checked.P, trusted.P) and torch.equal(checked.x, trusted.x)
    bad = Q.clone()
    bad[1] = -10.0 * torch.eye(n, dtype=torch.float64)
    trusted.predict(F, bad, trusted_noise=True)
    assert trusted.healthy.tolist() == [True, False, True, True]
