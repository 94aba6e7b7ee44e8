"""Navigation state of N strapdown solutions: position, velocity, attitude.

The state is stored packed as one ``(N, 10)`` tensor ``[lat, lon, h, v_N, v_E, v_D, q0,
q1, q2, q3]`` (radians, metres, m/s; scalar-first quaternion of ``C_b^n``) so that the
mechanisation advances all N runs with a few elementwise kernels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.rotation import dcm_from_quat, euler_from_dcm, quat_from_euler

__all__ = ["NavState"]


@dataclass(frozen=True)
class NavState:
    """N navigation solutions in the NED frame (batch first).

    Attributes:
        packed: ``(N, 10)`` ``[lat, lon, h, v_N, v_E, v_D, q0, q1, q2, q3]``.
    """

    packed: torch.Tensor

    def __post_init__(self) -> None:
        p = self.packed
        if not isinstance(p, torch.Tensor) or p.ndim != 2 or p.shape[1] != 10:
            shape = tuple(p.shape) if isinstance(p, torch.Tensor) else type(p).__name__
            raise NeuralMapError(
                f"NavState: 'packed' has shape {shape}, expected (N, 10) = "
                "[lat, lon, h, v_N, v_E, v_D, q0..q3]. Build it with NavState.from_parts."
            )

    @classmethod
    def from_parts(
        cls,
        *,
        lat: torch.Tensor,
        lon: torch.Tensor,
        h: torch.Tensor,
        vel: torch.Tensor,
        quat: torch.Tensor | None = None,
        euler: torch.Tensor | None = None,
    ) -> NavState:
        """Packs ``(N,)`` lat/lon (rad), h (m), ``(N, 3)`` NED velocity and attitude.

        Exactly one of ``quat`` ``(N, 4)`` (``C_b^n``) or ``euler`` ``(N, 3)`` (roll,
        pitch, yaw in rad) must be given.
        """
        if (quat is None) == (euler is None):
            raise NeuralMapError("NavState.from_parts: give exactly one of 'quat' or 'euler'.")
        if quat is None:
            quat = quat_from_euler(euler)
        n = vel.shape[0]
        for name, value, shape in (("lat", lat, (n,)), ("lon", lon, (n,)), ("h", h, (n,)),
                                   ("vel", vel, (n, 3)), ("quat", quat, (n, 4))):
            if tuple(value.shape) != shape:
                raise NeuralMapError(
                    f"NavState.from_parts: '{name}' has shape {tuple(value.shape)}, expected "
                    f"{shape} (N = {n} from 'vel')."
                )
        return cls(torch.cat([lat[:, None], lon[:, None], h[:, None], vel, quat], dim=1))

    @property
    def n_runs(self) -> int:
        """Number of solutions N."""
        return self.packed.shape[0]

    @property
    def lat(self) -> torch.Tensor:
        """``(N,)`` latitude (rad)."""
        return self.packed[:, 0]

    @property
    def lon(self) -> torch.Tensor:
        """``(N,)`` longitude (rad)."""
        return self.packed[:, 1]

    @property
    def h(self) -> torch.Tensor:
        """``(N,)`` ellipsoidal height (m)."""
        return self.packed[:, 2]

    @property
    def vel(self) -> torch.Tensor:
        """``(N, 3)`` NED velocity (m/s)."""
        return self.packed[:, 3:6]

    @property
    def quat(self) -> torch.Tensor:
        """``(N, 4)`` quaternion of ``C_b^n``."""
        return self.packed[:, 6:10]

    @property
    def dcm(self) -> torch.Tensor:
        """``(N, 3, 3)`` ``C_b^n``."""
        return dcm_from_quat(self.quat)

    @property
    def euler(self) -> torch.Tensor:
        """``(N, 3)`` roll, pitch, yaw (rad)."""
        return euler_from_dcm(self.dcm)
