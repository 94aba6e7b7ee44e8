"""Rotation helpers against scipy's Rotation."""

from __future__ import annotations

import torch
from scipy.spatial.transform import Rotation

from neuralmap.ins.rotation import (
    dcm_from_euler,
    dcm_from_quat,
    euler_from_dcm,
    quat_from_dcm,
    quat_from_rotvec,
    quat_multiply,
    rotvec_from_dcm,
)


def test_against_scipy() -> None:
    gen = torch.Generator().manual_seed(0)
    euler = (torch.rand(50, 3, generator=gen, dtype=torch.float64) - 0.5) * torch.tensor(
        [6.0, 3.0, 6.0], dtype=torch.float64)
    ref = Rotation.from_euler("ZYX", euler.flip(-1).numpy())  # yaw, pitch, roll
    c = dcm_from_euler(euler)
    assert torch.allclose(c, torch.from_numpy(ref.as_matrix()), atol=1e-13)
    assert torch.allclose(euler_from_dcm(c), euler, atol=1e-12)
    q = quat_from_dcm(c)
    assert torch.allclose(dcm_from_quat(q), c, atol=1e-13)
    rv = torch.from_numpy(ref.as_rotvec())
    assert torch.allclose(rotvec_from_dcm(c), rv, atol=1e-10)
    assert torch.allclose(dcm_from_quat(quat_from_rotvec(rv)), c, atol=1e-13)
    # composition: C(p ⊗ q) = C(p) C(q)
    p = quat_from_dcm(c.flip(0))
    assert torch.allclose(dcm_from_quat(quat_multiply(p, q)),
                          dcm_from_quat(p) @ dcm_from_quat(q), atol=1e-13)


def test_small_rotation_vectors() -> None:
    rv = torch.tensor([[1e-9, -2e-9, 3e-10], [0.0, 0.0, 0.0]], dtype=torch.float64)
    c = dcm_from_quat(quat_from_rotvec(rv))
    assert torch.allclose(rotvec_from_dcm(c), rv, atol=1e-18)
