"""Closed-form 2 × 2 algebra of the lattice filter against torch.linalg (float64): random,
ill-conditioned (condition 1e10), diagonal and isotropic matrices."""

from __future__ import annotations

import math

import torch

from neuralmap.filters.lattice.algebra2 import eigh2, eigvalsh2, inv2, solve2, spd2_ok, sqrtm2

D = torch.float64


def _spd(n: int = 400) -> torch.Tensor:
    gen = torch.Generator().manual_seed(11)
    theta = torch.rand(n, generator=gen, dtype=D) * 2 * math.pi
    log_cond = torch.rand(n, generator=gen, dtype=D) * 10.0  # condition up to 1e10
    scale = 10.0 ** (torch.rand(n, generator=gen, dtype=D) * 8 - 4)
    lam = torch.stack([scale, scale * 10.0**log_cond], 1)
    rot = torch.stack([torch.stack([theta.cos(), -theta.sin()], 1),
                       torch.stack([theta.sin(), theta.cos()], 1)], 1)
    c = (rot * lam[:, None, :]) @ rot.transpose(1, 2)
    c = 0.5 * (c + c.transpose(1, 2))
    special = torch.tensor([[[4.0, 0.0], [0.0, 1.0]], [[1.0, 0.0], [0.0, 4.0]],
                            [[2.0, 0.0], [0.0, 2.0]], [[3.0, -1.0], [-1.0, 3.0]]], dtype=D)
    return torch.cat([c, special])


def test_eigh2_matches_torch_linalg() -> None:
    c = _spd()
    lam, vec = eigh2(c)
    lam_ref = torch.linalg.eigvalsh(c)
    top = lam_ref[:, 1:]
    # eigenvalues to round-off of the largest (what any backward-stable method achieves)
    assert float(((lam - lam_ref).abs() / top).max()) < 1e-14
    torch.testing.assert_close(eigvalsh2(c), lam, rtol=0, atol=0)
    # orthonormal eigenvectors that rebuild the matrix (signs are a convention)
    eye = torch.eye(2, dtype=D).expand_as(c)
    torch.testing.assert_close(vec.transpose(1, 2) @ vec, eye, rtol=0, atol=1e-15)
    rebuilt = (vec * lam[:, None, :]) @ vec.transpose(1, 2)
    assert float(((rebuilt - c).abs().flatten(1).amax(1) / top[:, 0]).max()) < 1e-14
    # the direction of the larger eigenvalue agrees with LAPACK's up to sign
    _, vec_ref = torch.linalg.eigh(c)
    sep = (lam_ref[:, 1] - lam_ref[:, 0]) / top[:, 0] > 1e-6
    cosang = (vec[:, :, 1] * vec_ref[:, :, 1]).sum(1).abs()
    assert float((1.0 - cosang[sep]).max()) < 1e-12


def test_sqrtm2_inv2_solve2_match_torch_linalg() -> None:
    c = _spd()
    lam_ref, vec_ref = torch.linalg.eigh(c)
    ref = (vec_ref * lam_ref.sqrt()[:, None, :]) @ vec_ref.transpose(1, 2)
    root = sqrtm2(c)
    # an eigenvalue known to eps·λ_max gives its root to eps·sqrt(λ_max)·sqrt(cond) / 2
    err = (root - ref).abs().flatten(1).amax(1) / lam_ref[:, 1].sqrt()
    cond = lam_ref[:, 1] / lam_ref[:, 0]
    assert bool((err <= 1e-15 * (1.0 + cond.sqrt())).all())
    iroot = sqrtm2(c, inverse=True)
    eye = torch.eye(2, dtype=D).expand_as(c)
    well = (lam_ref[:, 1] / lam_ref[:, 0]) < 1e6
    torch.testing.assert_close((root @ iroot)[well], eye[well], rtol=0, atol=1e-9)
    gen = torch.Generator().manual_seed(5)
    a = torch.randn(500, 2, 2, generator=gen, dtype=D)
    b = torch.randn(500, 2, 3, generator=gen, dtype=D)
    cond = torch.linalg.cond(a)
    ok = cond < 1e6
    torch.testing.assert_close(inv2(a)[ok], torch.linalg.inv(a)[ok], rtol=1e-9, atol=1e-9)
    rel = ((solve2(a, b) - torch.linalg.solve(a, b)).abs().flatten(1).amax(1)
           / torch.linalg.solve(a, b).abs().flatten(1).amax(1))
    assert bool((rel <= 1e-15 * cond * 10).all())


def test_spd2_ok_is_the_cholesky_test() -> None:
    c = _spd()
    bad = c.clone()
    bad[:50, 1, 1] = -1.0  # indefinite
    bad[50:60, 0, 1] += 1.0  # not symmetric
    bad[60:70, 0, 0] = math.nan
    bad[70:80] = 0.0
    for m in (c, bad):
        chol = torch.linalg.cholesky_ex(torch.nan_to_num(m)).info == 0
        sym = (m - m.transpose(1, 2)).abs().flatten(1).amax(1) <= 1e-9 * m.abs().flatten(
            1).amax(1) + 1e-300
        want = torch.isfinite(m).flatten(1).all(1) & sym & chol
        assert torch.equal(spd2_ok(m), want)
    c32 = c.float()  # float32 input: the test runs in float64 as the Cholesky test did
    assert torch.equal(spd2_ok(c32), torch.linalg.cholesky_ex(c32.double()).info == 0)
