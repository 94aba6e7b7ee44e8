"""First-order time-varying AR wind model with random-walk noises (SEEDS 002, eqs. 1–15).

Reconstructed model (one axis), state ``x = [v, a, η]`` (wind, AR coefficient, coloured
process noise appended to the state):

    v_{k+1} = a_k v_k + η_{k+1}          (direct_noise=True, default)
            = a_k v_k + η_k              (direct_noise=False, the form printed in SEEDS)
    a_{k+1} = a_k + ξ_k,                 ξ ~ N(0, coeff_var)
    η_{k+1} = η_k + w_{k+1},             w ~ N(0, process_var)
    Z_k     = v_k + γ_k,   γ_{k+1} = γ_k + ν_{k+1},   ν ~ N(0, meas_var)

i.e. ``x_{k+1} = f(x_k) + Γ ω_{k+1}`` with ``f(x) = [a v + η, a, η]``, ``ω = [w, ξ]``,
``Γ = [[g, 0], [0, 1], [1, 0]]`` (``g = 1`` with direct noise, else 0), ``H = [1, 0, 0]``.
The model is nonlinear in ``(a, v)``; it is linearised at the estimate (EKF):
``F = ∂f/∂x = [[a, v, 1], [0, 1, 0], [0, 0, 1]]``.

Measurement differencing (eqs. 4–10): ``L_k = Z_{k+1} − Z_k = h(x_k) + e_k`` with

    h(x)  = H f(x) − H x = (a − 1) v + η,     A_k = ∂h/∂x = H F_k − H = [a − 1, v, 1],
    e_k   = H Γ ω_{k+1} + ν_{k+1}             (zero mean, white),

and, derived here (eqs. 11–12 were lost; ω and ν independent, ``Σ_ω = diag(process_var,
coeff_var)``):

    R_e = cov e_k        = H Γ Σ_ω Γᵀ Hᵀ + Σ_ν = g² process_var + meas_var,
    C   = E[Γ ω_{k+1} e_kᵀ] = Γ Σ_ω Γᵀ Hᵀ       = [g² process_var, 0, g process_var]ᵀ,
    E[e_k e_jᵀ] = 0 (j ≠ k),  E[Γ ω_{j+1} e_kᵀ] = 0 (j ≠ k).

So the differenced measurement noise is correlated with the process noise of the same
transition ``x_k → x_{k+1}``; the filter handles it explicitly with the decorrelated
predict of `.correlated` (``J = C R_e⁻¹``); dropping it roughly triples the error
on data from the model (tested). With ``direct_noise=False`` (the timing printed in
SEEDS) the cross-covariance vanishes (``HΓ = 0``) and ``R_e = meas_var``; that is the
same wind process with ``η`` relabelled one sample later (``η'_k = η_{k+1}``), so both
timings give the same wind estimates once started consistently (tested); the default
keeps the paper's form ``e_k = H Γ w_{k+1} + v_{k+1}`` with its correlation. Note that ``L_k`` uses
``Z_{k+1}``: processing it yields the estimate of ``x_{k+1}`` given ``Z_0..Z_{k+1}``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import torch

from neuralmap.wind.checks import require_positive

__all__ = ["TVARWindModel"]


@dataclass
class TVARWindModel:
    """Parameters of the time-varying AR wind model and its differenced measurement.

    Attributes:
        process_var: ``Σ_w``, random-walk increment variance of ``η`` (paper start 0.01).
        coeff_var: ``Σ_ξ``, random-walk increment variance of the AR coefficient ``a``
            (not given by the paper). ``a`` and ``η`` are nearly interchangeable in
            ``h = (a − 1) v + η`` when ``v`` changes slowly, so a loose ``Σ_ξ`` lets ``a``
            wander and bias the wind: with the paper's ``Σ_w0``, ``Σ_v0`` a value of 1e-4
            drifts ``a`` to about 0.86 in 400 samples (wind bias about −8 m/s); 1e-6
            (default) keeps it near 1.
        meas_var: ``Σ_ν``, random-walk increment variance of the measurement noise
            (paper start ``Σ_v0 = 2``).
        direct_noise: ``v_{k+1} = a v + η_{k+1}`` (True) or ``a v + η_k`` (False).
        a0: Initial AR coefficient.
        var_v0: Initial variance of ``v`` (about the first measurement).
        var_a0: Initial variance of ``a``.
        var_eta0: Initial variance of ``η``.
    """

    process_var: float = 0.01
    coeff_var: float = 1.0e-6
    meas_var: float = 2.0
    direct_noise: bool = True
    a0: float = 1.0
    var_v0: float = 2.0
    var_a0: float = 1.0e-6
    var_eta0: float = 0.1

    num_states: ClassVar[int] = 3

    def validate(self) -> TVARWindModel:
        """Checks the variances; returns ``self``.

        Raises:
            NeuralMapError: A non-positive variance.
        """
        where = "TVARWindModel"
        for name in ("process_var", "coeff_var", "meas_var", "var_v0", "var_a0", "var_eta0"):
            require_positive(getattr(self, name), name, where)
        return self

    @property
    def _g(self) -> float:
        return 1.0 if self.direct_noise else 0.0

    def initial(self, z0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial state ``[Z_0, a0, 0]`` and covariance for ``(N,)`` first measurements."""
        x0 = torch.stack([z0, torch.full_like(z0, self.a0), torch.zeros_like(z0)], dim=-1)
        P0 = torch.diag(torch.tensor([self.var_v0, self.var_a0, self.var_eta0],
                                     dtype=z0.dtype, device=z0.device))
        return x0, P0.expand(z0.shape[0], 3, 3).clone()

    def transition(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``f(x)`` ``(N, 3)`` and its Jacobian ``F`` ``(N, 3, 3)``."""
        v, a, eta = x.unbind(-1)
        fx = torch.stack([a * v + eta, a, eta], dim=-1)
        F = torch.zeros(x.shape[0], 3, 3, dtype=x.dtype, device=x.device)
        F[:, 0, 0] = a
        F[:, 0, 1] = v
        F[:, 0, 2] = 1.0
        F[:, 1, 1] = 1.0
        F[:, 2, 2] = 1.0
        return fx, F

    def measurement(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Differenced measurement ``h(x) = (a − 1) v + η`` ``(N, 1)``, ``A`` ``(N, 1, 3)``."""
        v, a, eta = x.unbind(-1)
        hx = ((a - 1.0) * v + eta).unsqueeze(-1)
        A = torch.stack([a - 1.0, v, torch.ones_like(v)], dim=-1).unsqueeze(1)
        return hx, A

    def noise_input(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``Γ`` ``(3, 2)`` mapping ``ω = [w, ξ]`` into the state."""
        return torch.tensor([[self._g, 0.0], [0.0, 1.0], [1.0, 0.0]], dtype=dtype)

    def noise_covariances(
        self,
        process_var: torch.Tensor | float | None = None,
        meas_var: torch.Tensor | float | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``Q = ΓΣ_ωΓᵀ`` ``(…, 3, 3)``, ``R_e`` ``(…, 1, 1)``, ``C`` ``(…, 3, 1)``.

        Args:
            process_var: ``Σ_w`` override, a float or ``(N,)`` per sample (adaptive
                filters); default the model's.
            meas_var: ``Σ_ν`` override, as ``process_var``.
            dtype: Dtype of the result.

        Returns:
            ``(Q, R_e, C)`` from the derivation in the module docstring; batched when an
            override is batched.
        """
        sw = torch.as_tensor(self.process_var if process_var is None else process_var,
                             dtype=dtype)
        sv = torch.as_tensor(self.meas_var if meas_var is None else meas_var, dtype=dtype)
        sw, sv = torch.broadcast_tensors(sw, sv)
        g = self._g
        shape = sw.shape
        Q = torch.zeros(*shape, 3, 3, dtype=dtype)
        Q[..., 0, 0] = g * g * sw
        Q[..., 0, 2] = g * sw
        Q[..., 2, 0] = g * sw
        Q[..., 2, 2] = sw
        Q[..., 1, 1] = self.coeff_var
        R = (g * g * sw + sv).reshape(*shape, 1, 1)
        C = torch.zeros(*shape, 3, 1, dtype=dtype)
        C[..., 0, 0] = g * g * sw
        C[..., 2, 0] = g * sw
        return Q, R, C
