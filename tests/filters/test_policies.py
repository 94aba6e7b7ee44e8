"""Update policies inside BatchedEKF against independent references.

References: the plain update (the filter without a policy, or with the adapted inputs
written out by hand), and plain NumPy implementations of Sage-Husa (SEEDS 002) and of
Huang et al.'s variational-Bayes filter (IEEE TAC 2018) on a linear system, one sample at
a time in float64.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from neuralmap.filters import (
    IGG3,
    BatchedEKF,
    ChiSquareGate,
    Compose,
    Huber,
    InnovationInflation,
    QualityR,
    RobustAdaptive,
    SageHusa,
    VariationalAdaptive,
    YangAdaptive,
)
from neuralmap.filters.policies import igg3_weights, yang_factor

D = torch.float64


def _problem(n: int, m: int, batch: int, seed: int, scale: float = 0.3) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    A = torch.randn(batch, n, n, generator=g, dtype=D)
    P = 0.2 * A @ A.transpose(1, 2) + torch.eye(n, dtype=D)
    R = torch.diag_embed(torch.rand(batch, m, generator=g, dtype=D) + 0.5)
    H = torch.randn(batch, m, n, generator=g, dtype=D)
    S = H @ P @ H.transpose(1, 2) + R
    z = scale * torch.randn(batch, m, generator=g, dtype=D) * torch.diagonal(S, 0, 1, 2).sqrt()
    return {"x": torch.randn(batch, n, generator=g, dtype=D), "P": P, "H": H, "R": R, "z": z}


def _plain(prob: dict[str, torch.Tensor], R: torch.Tensor | None = None,
           P: torch.Tensor | None = None, keep: torch.Tensor | None = None) -> BatchedEKF:
    ekf = BatchedEKF(prob["x"], prob["P"] if P is None else P)
    H, z = prob["H"], prob["z"]
    R = prob["R"] if R is None else R
    if keep is not None:
        H = torch.where(keep.unsqueeze(-1), H, 0.0)
        z = torch.where(keep, z, 0.0)
        eye = torch.eye(R.shape[-1], dtype=D)
        R = torch.where(keep.unsqueeze(-1) & keep.unsqueeze(-2), R, eye)
    ekf.update(z, H, R)
    return ekf


# ---------------------------------------------------------------- clean data = plain EKF
@pytest.mark.parametrize("m", [1, 3])
def test_raf_on_clean_data_equals_plain_ekf(m: int) -> None:
    prob = _problem(5, m, batch=40, seed=m)
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=RobustAdaptive(1.5, 4.5, 1.0, 3.0))
    assert bool((diag.policy_info["igg3.weight"] == 1).all())
    assert bool((diag.policy_info["yang.alpha"] == 1).all())
    ref = _plain(prob)
    torch.testing.assert_close(ekf.x, ref.x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ekf.P, ref.P, rtol=1e-12, atol=1e-12)
    assert bool(diag.applied.all())


# ---------------------------------------------------------------- one outlier, others untouched
@pytest.mark.parametrize("policy_name", ["igg3", "huber", "raf", "chi2", "yang"])
def test_outlier_in_one_sample_leaves_the_others_untouched(policy_name: str) -> None:
    prob = _problem(5, 1, batch=12, seed=4)
    bad = 7
    S_bad = float(prob["H"][bad] @ prob["P"][bad] @ prob["H"][bad].t() + prob["R"][bad])
    prob["z"][bad, 0] = 40.0 * math.sqrt(S_bad)
    policy = {
        "igg3": IGG3(1.5, 4.5), "huber": Huber(1.345), "raf": RobustAdaptive(),
        "chi2": ChiSquareGate(0.99), "yang": YangAdaptive(1.0, 3.0),
    }[policy_name]
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=policy)
    ref = _plain(prob)
    others = torch.arange(12) != bad
    torch.testing.assert_close(ekf.x[others], ref.x[others], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ekf.P[others], ref.P[others], rtol=1e-12, atol=1e-12)
    if policy_name in ("igg3", "raf", "chi2"):  # rejected: not updated at all
        assert not bool(diag.applied[bad])
        start = BatchedEKF(prob["x"], prob["P"])  # P0 as stored (symmetrised)
        assert torch.equal(ekf.x[bad], start.x[bad]) and torch.equal(ekf.P[bad], start.P[bad])
    elif policy_name == "huber":  # down-weighted: R / w with w = k / ṽ
        w = 1.345 / 40.0
        torch.testing.assert_close(diag.policy_info["weight"][bad], torch.tensor([w], dtype=D))
        one = {k: v[bad:bad + 1] for k, v in prob.items()}
        ref_bad = _plain(one, R=one["R"] / w)
        torch.testing.assert_close(ekf.x[bad], ref_bad.x[0], rtol=1e-12, atol=1e-12)
        torch.testing.assert_close(ekf.P[bad], ref_bad.P[0], rtol=1e-12, atol=1e-12)
    else:  # yang: P⁻ / α with α at the floor
        alpha = float(diag.policy_info["alpha"][bad])
        assert alpha == pytest.approx(1e-3)
        one = {k: v[bad:bad + 1] for k, v in prob.items()}
        ref_bad = _plain(one, P=one["P"] / alpha)
        torch.testing.assert_close(ekf.x[bad], ref_bad.x[0], rtol=1e-10, atol=1e-10)


def test_igg3_down_weights_and_rejects_components_per_the_formula() -> None:
    prob = _problem(5, 3, batch=4, seed=9)
    S = prob["H"] @ prob["P"] @ prob["H"].transpose(1, 2) + prob["R"]
    sd = torch.diagonal(S, 0, 1, 2).sqrt()
    prob["z"][1, 0] = 3.0 * sd[1, 0]   # in the taper: weight (1.5/3)(1.5/3)²
    prob["z"][2, 2] = -9.0 * sd[2, 2]  # beyond k1: rejected
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=IGG3(1.5, 4.5))
    v = prob["z"].abs() / sd
    w = igg3_weights(v, 1.5, 4.5)
    torch.testing.assert_close(diag.policy_info["weight"], w, rtol=1e-14, atol=0)
    assert float(w[1, 0]) == pytest.approx(0.125, rel=1e-12)
    keep = w > 0
    R_bar = torch.diag_embed(torch.diagonal(prob["R"], 0, 1, 2) / torch.where(keep, w, 1.0))
    ref = _plain(prob, R=R_bar, keep=keep)
    torch.testing.assert_close(ekf.x, ref.x, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(ekf.P, ref.P, rtol=1e-12, atol=1e-12)


def test_raf_uses_equivalent_R_in_delta() -> None:
    prob = _problem(5, 2, batch=6, seed=21, scale=2.0)
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=RobustAdaptive(1.0, 4.0, 1.0, 3.0))
    HPH = prob["H"] @ prob["P"] @ prob["H"].transpose(1, 2)
    S = HPH + prob["R"]
    v = prob["z"].abs() / torch.diagonal(S, 0, 1, 2).sqrt()
    w = igg3_weights(v, 1.0, 4.0)
    keep = w > 0
    R_bar = torch.diagonal(prob["R"], 0, 1, 2) / torch.where(keep, w, 1.0)
    num = torch.where(keep, prob["z"] ** 2, 0.0).sum(-1)
    den = torch.where(keep, torch.diagonal(HPH, 0, 1, 2) + R_bar, 0.0).sum(-1)
    delta = torch.sqrt(torch.where(den > 0, num / den, 0.0))
    torch.testing.assert_close(diag.policy_info["yang.delta"], delta, rtol=1e-12, atol=1e-12)
    alpha = yang_factor(delta, 1.0, 3.0)
    torch.testing.assert_close(diag.policy_info["yang.alpha"], alpha, rtol=1e-12, atol=1e-12)
    ref = _plain(prob, R=torch.diag_embed(R_bar), P=prob["P"] / alpha.reshape(-1, 1, 1),
                 keep=keep)
    sel = keep.any(-1)
    torch.testing.assert_close(ekf.x[sel], ref.x[sel], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ekf.P[sel], ref.P[sel], rtol=1e-10, atol=1e-10)


def test_chi_square_gate_vector_nis() -> None:
    prob = _problem(5, 2, batch=200, seed=5, scale=2.0)
    ekf = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=ChiSquareGate(0.9))
    S = prob["H"] @ prob["P"] @ prob["H"].transpose(1, 2) + prob["R"]
    nis = torch.einsum("bi,bij,bj->b", prob["z"], torch.linalg.inv(S), prob["z"])
    torch.testing.assert_close(diag.policy_info["nis"], nis, rtol=1e-10, atol=1e-12)
    rejected = nis > chi2.ppf(0.9, 2)
    assert 0 < int(rejected.sum()) < 200
    assert torch.equal(diag.applied, ~rejected)


# ---------------------------------------------------------------- paper 003 composition
def test_quality_then_inflation_scales_R_before_the_alpha_test() -> None:
    prob = _problem(4, 1, batch=5, seed=13, scale=3.0)
    F = torch.eye(4, dtype=D) + 0.1 * torch.diag(torch.ones(3, dtype=D), 1)
    Q = 0.05 * torch.eye(4, dtype=D)
    q = QualityR.altimeter()
    policy = Compose(q, InnovationInflation(1.2))
    ekf = BatchedEKF(prob["x"], prob["P"])
    ekf.predict(F, Q)
    P_minus = ekf.P.clone()
    rough = torch.tensor([0.0, 8.5, 15.0, 40.0, 1.0], dtype=D)
    lock = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0], dtype=D)
    q.set_quality(torch.stack([rough, torch.full((5,), 100.0, dtype=D), lock], -1))
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=policy)
    rho = 1.0 + 0.5 * ((rough - 2.0) / 13.0).clamp(0, 4)
    rho[4] = 1.0
    torch.testing.assert_close(diag.policy_info["quality.rho"], rho, rtol=1e-14, atol=0)
    R_q = prob["R"][:, 0, 0] * rho
    hph = torch.einsum("bi,bij,bj->b", prob["H"][:, 0], P_minus, prob["H"][:, 0])
    lam = prob["z"][:, 0] ** 2 / (hph + R_q)
    torch.testing.assert_close(diag.policy_info["inflation.lambda"][:4], lam[:4], rtol=1e-12,
                               atol=0)
    alpha = torch.where(lam > 1.2, lam / 1.2, 1.0)
    assert bool((alpha[:4] > 1).any())
    # P⁻ = α Φ P Φᵀ + Q
    FPF = F @ prob["P"] @ F.t()
    P_infl = alpha.reshape(-1, 1, 1) * FPF + Q
    ref = BatchedEKF(ekf.x * 0 + (prob["x"] @ F.t()), P_infl)
    ref.update(prob["z"], prob["H"], R_q)
    sel = torch.arange(4)
    torch.testing.assert_close(ekf.x[sel], ref.x[sel], rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ekf.P[sel], ref.P[sel], rtol=1e-10, atol=1e-10)
    assert not bool(diag.applied[4])  # loss of lock: rejected
    with pytest.raises(Exception, match="set_quality"):
        ekf.update(prob["z"], prob["H"], prob["R"], policy=policy)
    q.set_quality(torch.ones(4, 3))
    with pytest.raises(Exception, match="samples"):
        ekf.update(prob["z"], prob["H"], prob["R"], policy=policy)


# ---------------------------------------------------------------- NumPy references
def _linear_system() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    dt = 1.0
    F = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1]], dtype=float)
    Q = np.diag([0.01, 0.01, 0.04, 0.04])
    H = np.array([[1.0, 0, 0, 0], [0, 1.0, 0.2, 0]])
    R = np.diag([0.5, 0.8])
    return F, Q, H, R


def _measurements(batch: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    F, Q, H, _ = _linear_system()
    R_true = np.diag([2.0, 0.3])
    x = rng.normal(size=(batch, 4))
    zs = np.zeros((steps, batch, 2))
    for k in range(steps):
        x = x @ F.T + rng.normal(size=(batch, 4)) * np.sqrt(np.diag(Q))
        zs[k] = x @ H.T + rng.normal(size=(batch, 2)) * np.sqrt(np.diag(R_true))
        if k == 4:
            zs[k, 0, 0] += 30.0  # an outlier
    mask = np.ones((steps, batch), dtype=bool)
    mask[3, 1] = False
    mask[min(6, steps - 1), min(2, batch - 1)] = False
    return zs, mask


def _sage_husa_reference(zs, mask, b, r_min, r_max, adapt_q, diagonal=True):  # type: ignore[no-untyped-def]
    F, Q, H, R = _linear_system()
    steps, batch, m = zs.shape
    xs, Ps = [], []
    for i in range(batch):
        x, P = np.zeros(4), 4.0 * np.eye(4)
        R_hat, k, Q_hat = None, 0, None
        for s in range(steps):
            Q_use = Q if Q_hat is None else Q_hat
            x, P_minus = F @ x, F @ P @ F.T + Q_use
            P = P_minus
            if not mask[s, i]:
                continue
            eps = zs[s, i] - H @ x
            d = (1 - b) / (1 - b ** (k + 1))
            prev = np.diag(np.clip(np.diag(R), r_min, r_max)) if R_hat is None else R_hat
            est = (1 - d) * prev + d * (np.outer(eps, eps) - H @ P_minus @ H.T)
            if diagonal:
                R_hat = np.diag(np.clip(np.diag(est), r_min, r_max))
            else:
                lam, V = np.linalg.eigh(0.5 * (est + est.T))
                R_hat = (V * np.clip(lam, r_min, r_max)) @ V.T
            S = H @ P_minus @ H.T + R_hat
            K = P_minus @ H.T @ np.linalg.inv(S)
            x = x + K @ eps
            I_KH = np.eye(4) - K @ H
            P = I_KH @ P_minus @ I_KH.T + K @ R_hat @ K.T
            if adapt_q:
                ke = K @ eps
                est_q = (1 - d) * Q_use + d * (np.outer(ke, ke) + P - (P_minus - Q_use))
                if diagonal:
                    Q_hat = np.diag(np.maximum(np.diag(est_q), 0.0))
                else:
                    lam, V = np.linalg.eigh(0.5 * (est_q + est_q.T))
                    Q_hat = (V * np.maximum(lam, 0.0)) @ V.T
            k += 1
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


def _run_torch(policy, zs, mask, dtype=D):  # type: ignore[no-untyped-def]
    F, Q, H, R = (torch.tensor(a, dtype=dtype) for a in _linear_system())
    steps, batch, _ = zs.shape
    ekf = BatchedEKF(torch.zeros(batch, 4, dtype=dtype), 4.0 * torch.eye(4, dtype=dtype))
    infos = []
    for s in range(steps):
        ekf.predict(F, Q, policy=policy)
        z = torch.tensor(zs[s], dtype=dtype)
        diag = ekf.update(z - ekf.x @ H.t(), H, R, mask=torch.tensor(mask[s]), policy=policy)
        infos.append(diag)
    return ekf, infos


@pytest.mark.parametrize(("adapt_q", "diagonal"), [(False, True), (True, True), (True, False)])
def test_sage_husa_matches_numpy_reference(adapt_q: bool, diagonal: bool) -> None:
    zs, mask = _measurements(batch=3, steps=10, seed=1)
    policy = SageHusa(b=0.95, R_min=0.05, R_max=50.0, adapt_Q=adapt_q, diagonal=diagonal)
    ekf, infos = _run_torch(policy, zs, mask)
    x_ref, P_ref = _sage_husa_reference(zs, mask, 0.95, 0.05, 50.0, adapt_q, diagonal)
    np.testing.assert_allclose(ekf.x.numpy(), x_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(ekf.P.numpy(), P_ref, rtol=1e-10, atol=1e-10)
    assert policy.R_hat is not None and bool(ekf.healthy.all())
    # the clamp engaged at least once (the first estimate ε εᵀ − H P⁻ Hᵀ is negative)
    low = infos[0].policy_info["R"].min()
    assert float(low) == pytest.approx(0.05) if diagonal else float(low) < 0.5


def _vb_reference(zs, mask, iterations, tau, rho, prior_dof):  # type: ignore[no-untyped-def]
    F, Q, H, R = _linear_system()
    steps, batch, m = zs.shape
    n = 4
    xs, Ps = [], []
    for i in range(batch):
        x, P = np.zeros(n), 4.0 * np.eye(n)
        u, U = m + 1 + prior_dof, prior_dof * R
        for s in range(steps):
            x_pred, P_pred = F @ x, F @ P @ F.T + Q
            x, P = x_pred, P_pred
            if not mask[s, i]:
                continue
            z = zs[s, i]
            t_hat, T_hat = n + tau + 1, tau * P_pred
            u_hat, U_hat = rho * (u - m - 1) + m + 1, rho * U
            xi, Pi = x_pred, P_pred
            for _ in range(iterations):
                A = Pi + np.outer(xi - x_pred, xi - x_pred)
                t, T = t_hat + 1, A + T_hat
                B = np.outer(z - H @ xi, z - H @ xi) + H @ Pi @ H.T
                u_new, U_new = u_hat + 1, B + U_hat
                P_t = T / (t - n - 1)
                R_t = U_new / (u_new - m - 1)
                K = P_t @ H.T @ np.linalg.inv(H @ P_t @ H.T + R_t)
                xi = x_pred + K @ (z - H @ x_pred)
                Pi = P_t - K @ H @ P_t
            x, P, u, U = xi, Pi, u_new, U_new
        xs.append(x)
        Ps.append(P)
    return np.array(xs), np.array(Ps)


@pytest.mark.parametrize("iterations", [1, 3])
def test_variational_matches_numpy_reference(iterations: int) -> None:
    zs, mask = _measurements(batch=3, steps=10, seed=2)
    policy = VariationalAdaptive(iterations=iterations, tau=3.0, rho=0.95, prior_dof=2.0)
    ekf, infos = _run_torch(policy, zs, mask)
    x_ref, P_ref = _vb_reference(zs, mask, iterations, 3.0, 0.95, 2.0)
    np.testing.assert_allclose(ekf.x.numpy(), x_ref, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(ekf.P.numpy(), P_ref, rtol=1e-10, atol=1e-10)


def test_variational_inside_compose_matches_alone() -> None:
    zs, mask = _measurements(batch=2, steps=6, seed=3)
    a, _ = _run_torch(VariationalAdaptive(iterations=3), zs, mask)
    b, infos = _run_torch(Compose(Huber(100.0), VariationalAdaptive(iterations=3)), zs, mask)
    torch.testing.assert_close(a.x, b.x, rtol=1e-12, atol=1e-12)
    assert "vb.R" in infos[-1].policy_info and "huber.weight" in infos[-1].policy_info


# ---------------------------------------------------------------- P stays SPD
_all_policies = [
    lambda: IGG3(1.5, 4.5), lambda: Huber(), lambda: ChiSquareGate(0.99),
    lambda: YangAdaptive(1.0, 3.0), lambda: YangAdaptive(1.0, segments=2),
    lambda: RobustAdaptive(), lambda: InnovationInflation(1.2),
    lambda: SageHusa(0.95, 0.01, 100.0), lambda: SageHusa(0.95, 0.01, 100.0, adapt_Q=True),
    lambda: SageHusa(0.95, 0.01, 100.0, diagonal=False),
    lambda: VariationalAdaptive(iterations=3), lambda: Compose(IGG3(), InnovationInflation()),
]


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_policies_keep_P_symmetric_positive_definite(dtype: torch.dtype) -> None:
    rng = np.random.default_rng(7)
    zs, mask = _measurements(batch=16, steps=12, seed=7)
    zs = zs + (rng.random(zs.shape) < 0.15) * rng.normal(scale=50.0, size=zs.shape)
    for make in _all_policies:
        policy = make()
        ekf, _ = _run_torch(policy, zs, mask, dtype=dtype)
        P = ekf.P
        assert P.dtype == dtype
        assert torch.equal(P, P.transpose(1, 2)), policy.name
        assert bool((torch.linalg.cholesky_ex(P.double()).info == 0).all()), policy.name
        assert bool(ekf.healthy.all()), policy.name
        assert bool(torch.isfinite(ekf.x).all()), policy.name


# ---------------------------------------------------------------- scalar fast path
@pytest.mark.parametrize("shared_h", [False, True])
def test_scalar_policy_fast_path_equals_dense_path(shared_h: bool) -> None:
    """m = 1: the entry-by-entry policy path against the (N, m, m) one, every policy."""
    zs, mask = _measurements(batch=12, steps=8, seed=11)
    rng = np.random.default_rng(11)
    zs = zs + (rng.random(zs.shape) < 0.2) * rng.normal(scale=30.0, size=zs.shape)
    F, Q, H2, _ = (torch.tensor(a, dtype=D) for a in _linear_system())
    H = H2[:1]
    for make in _all_policies:
        fast_policy, dense_policy = make(), make()
        fast = BatchedEKF(torch.zeros(12, 4, dtype=D), 4.0 * torch.eye(4, dtype=D))
        dense = BatchedEKF(torch.zeros(12, 4, dtype=D), 4.0 * torch.eye(4, dtype=D))
        for s in range(zs.shape[0]):
            fast.predict(F, Q, policy=fast_policy)
            dense.predict(F, Q, policy=dense_policy)
            m_s = torch.tensor(mask[s])
            z = torch.tensor(zs[s, :, :1], dtype=D)
            h_b = H.expand(12, 1, 4) * (1.0 + 0.1 * s)
            h_in = h_b[0] if shared_h else h_b  # shared (1, n) or per-sample (N, 1, n)
            r_fast = z - torch.einsum("bmn,bn->bm", h_b, fast.x)
            d_fast = fast.update(r_fast, h_in, 0.7, mask=m_s, policy=fast_policy)
            # the dense path on the same (sanitised) inputs
            r_d, h_d = dense._parse_measurement(z - torch.einsum("bmn,bn->bm", h_b, dense.x),
                                                h_in)[:2]
            R_d = dense._parse_noise(0.7, 1, m_s)
            r_d, h_d, R_d = dense._sanitise(r_d, h_d, R_d, m_s)
            d_dense = dense._update_policy_dense(r_d, h_d, R_d, m_s, dense_policy)
            assert torch.equal(d_fast.applied, d_dense.applied), fast_policy.name
            for key, value in d_dense.policy_info.items():
                torch.testing.assert_close(d_fast.policy_info[key], value, rtol=1e-10,
                                           atol=1e-10, msg=f"{fast_policy.name} {key}")
        torch.testing.assert_close(fast.x, dense.x, rtol=1e-10, atol=1e-10)
        torch.testing.assert_close(fast.P, dense.P, rtol=1e-10, atol=1e-10)
        assert torch.equal(fast.P, fast.P.transpose(1, 2))


def test_scalar_path_rejection_with_adapted_P_leaves_sample_unchanged() -> None:
    """A rejected sample keeps x and P even when the same adaptation rescales P⁻."""
    from neuralmap.filters import Adaptation, FilterPolicy

    class _RejectAndScale(FilterPolicy):
        def adapt(self, context):  # type: ignore[no-untyped-def]
            keep = torch.tensor([[True], [False], [True]])
            return Adaptation(p_scale=torch.full((3,), 2.0, dtype=D), keep=keep)

    prob = _problem(5, 1, batch=3, seed=2)
    ekf = BatchedEKF(prob["x"], prob["P"])
    start = BatchedEKF(prob["x"], prob["P"])
    diag = ekf.update(prob["z"], prob["H"], prob["R"], policy=_RejectAndScale())
    assert diag.applied.tolist() == [True, False, True]
    assert torch.equal(ekf.x[1], start.x[1]) and torch.equal(ekf.P[1], start.P[1])
    ref = _plain(prob, P=2.0 * prob["P"])
    torch.testing.assert_close(ekf.P[0], ref.P[0], rtol=1e-12, atol=1e-12)


def test_compose_chains_covariance_adaptations_and_prefixes_info() -> None:
    """Inflation then Yang: Yang sees the inflated P⁻; the update uses both, in order."""
    prob = _problem(4, 2, batch=6, seed=17, scale=2.5)
    F = torch.eye(4, dtype=D)
    Q = 0.3 * torch.eye(4, dtype=D)
    ekf = BatchedEKF(prob["x"], prob["P"])
    ekf.predict(F, Q)
    P_minus = ekf.P.clone()
    diag = ekf.update(prob["z"], prob["H"], prob["R"],
                      policy=Compose(InnovationInflation(1.0), YangAdaptive(1.0, 3.0)))
    info = diag.policy_info
    assert set(info) == {"inflation.alpha", "inflation.lambda", "yang.alpha", "yang.delta"}
    a = info["inflation.alpha"].reshape(-1, 1, 1)
    P_infl = a * P_minus - (a - 1) * Q
    HPH = prob["H"] @ P_infl @ prob["H"].transpose(1, 2)
    delta = torch.sqrt((prob["z"] ** 2).sum(-1)
                       / torch.diagonal(HPH + prob["R"], 0, 1, 2).sum(-1))
    torch.testing.assert_close(info["yang.delta"], delta, rtol=1e-12, atol=1e-12)
    alpha = info["yang.alpha"].reshape(-1, 1, 1)
    ref = BatchedEKF(prob["x"], P_infl / alpha)
    ref.update(prob["z"], prob["H"], prob["R"])
    torch.testing.assert_close(ekf.x, ref.x, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(ekf.P, ref.P, rtol=1e-10, atol=1e-10)
    assert bool((info["inflation.alpha"] > 1).any()) and bool((info["yang.alpha"] < 1).any())


def test_compose_rejects_an_iterating_member_that_is_not_last() -> None:
    from neuralmap.exceptions import NeuralMapError

    with pytest.raises(NeuralMapError, match="last"):
        Compose(VariationalAdaptive(iterations=3), Huber())
    with pytest.raises(NeuralMapError, match="FilterPolicy"):
        Compose(Huber(), "igg3")  # type: ignore[arg-type]
