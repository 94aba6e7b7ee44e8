"""WGS-84 Earth model against closed forms and published values."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.ins.earth import (
    WGS84_A,
    WGS84_E2,
    earth_rate_ned,
    normal_gravity,
    radii,
    schuler_period,
    transport_rate_ned,
)


def test_radii_at_equator_and_pole() -> None:
    lat = torch.tensor([0.0, math.pi / 2], dtype=torch.float64)
    rm, rn = radii(lat)
    b = WGS84_A * math.sqrt(1 - WGS84_E2)
    assert rm[0].item() == pytest.approx(WGS84_A * (1 - WGS84_E2), rel=1e-14)
    assert rn[0].item() == pytest.approx(WGS84_A, rel=1e-14)
    # at the pole both radii equal a²/b
    assert rm[1].item() == pytest.approx(WGS84_A**2 / b, rel=1e-12)
    assert rn[1].item() == pytest.approx(WGS84_A**2 / b, rel=1e-12)


def test_normal_gravity_published_values() -> None:
    # WGS-84 normal gravity on the ellipsoid: 9.7803253359 (equator), 9.8321849378 (pole);
    # the series used here agrees to about 2e-6 m/s², and the free-air gradient is
    # about -3.086e-6 s^-2.
    lat = torch.tensor([0.0, math.pi / 2], dtype=torch.float64)
    g = normal_gravity(lat, torch.zeros(2, dtype=torch.float64))
    assert g[0].item() == pytest.approx(9.7803253359, abs=2e-6)
    assert g[1].item() == pytest.approx(9.8321849378, abs=2e-4)
    g1 = normal_gravity(lat[:1], torch.tensor([1000.0], dtype=torch.float64))
    assert (g1 - g[:1]).item() / 1000.0 == pytest.approx(-3.0877e-6, rel=1e-3)


def test_rates_closed_form() -> None:
    lat = torch.tensor([0.6], dtype=torch.float64)
    w = earth_rate_ned(lat)[0]
    assert torch.linalg.vector_norm(w).item() == pytest.approx(7.2921151467e-5, rel=1e-14)
    assert w[0].item() / -w[2].item() == pytest.approx(1 / math.tan(0.6), rel=1e-12)
    vel = torch.tensor([[10.0, 5.0, 0.0]], dtype=torch.float64)
    h = torch.tensor([100.0], dtype=torch.float64)
    rm, rn = radii(lat)
    rho = transport_rate_ned(lat, h, vel)[0]
    assert rho[0].item() == pytest.approx(5.0 / (rn.item() + 100.0), rel=1e-14)
    assert rho[1].item() == pytest.approx(-10.0 / (rm.item() + 100.0), rel=1e-14)
    assert rho[2].item() == pytest.approx(-5.0 * math.tan(0.6) / (rn.item() + 100.0), rel=1e-14)


def test_schuler_period_is_84_minutes() -> None:
    assert schuler_period(math.radians(30.0)) / 60.0 == pytest.approx(84.4, rel=2e-3)
