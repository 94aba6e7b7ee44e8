"""BatchedEKF: N independent extended Kalman filters advanced by one set of tensor ops.

The filter runs the textbook discrete EKF for every sample of a batch at once:

* predict: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q`` (symmetric);
* update with the caller's innovation ``r = z − h(x⁻)`` and Jacobian ``H``:
  ``S = H P⁻ Hᵀ + R``, ``K = P⁻ Hᵀ S⁻¹`` (Cholesky solve, never an explicit inverse;
  a plain division for a scalar measurement), ``x⁺ = x⁻ + K r``, Joseph form
  ``P⁺ = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ`` (symmetric), ``NIS = rᵀ S⁻¹ r``.

This is the filter of SEEDS 004 (TAN error-state EKF, its eqs. for Φ, H, P, K) and
SEEDS 000 (augmented states); nothing in it is specific to terrain navigation.

Layout and speed: the state is stored *batch-last* — ``x`` as ``(n, N)`` and ``P`` as
``(n, n, N)`` — so that each matrix entry ``P[i, j]`` is a contiguous length-N vector.
For small state sizes (n ≤ 8) the predict with a sparse shared ``F`` and the scalar
update are written entry by entry on those vectors (a loop over the *state* indices,
never over samples): a few dozen elementwise kernels on cache-resident vectors instead of
batched small-matrix kernels, which on CPU are dominated by per-matrix overhead and by
memory traffic of ``(N, n, n)`` temporaries. Only the upper triangle is computed and then
mirrored, so ``P`` is exactly symmetric by construction. The public attributes
`BatchedEKF.x` ``(N, n)`` and `BatchedEKF.P` ``(N, n, n)`` are views of that
storage (batch first, as everywhere in the project). The stored tensors are never
modified in place, so a view taken before a step stays a valid snapshot; all operations
are out-of-place and differentiable (autograd flows through a whole filter run).

Health: a sample whose ``S`` or ``P`` stops being positive definite (Cholesky pivots) or
whose ``x``/``P`` become non-finite is flagged unhealthy and frozen: its ``x`` and ``P``
keep their last healthy values and later predicts/updates leave it alone. Samples never
mix, so a broken sample cannot turn any other one into NaN (selection uses
``torch.where``; no boolean indexing in the hot path).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.kalman import (
    SMALL_STATE_MAX,
    TransitionPlan,
    full_from_upper,
    gaussian_log_likelihood,
    predict_upper,
    transition_plan,
    update_dense,
    update_scalar_upper,
)
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext
from neuralmap.filters.stats import symmetrize
from neuralmap.filters.validation import (
    as_float_tensor,
    check_covariance,
    check_finite,
    check_mask,
    check_matrix_shape,
    shape_error,
)
from neuralmap.threads import one_thread

__all__ = ["BatchedEKF", "positive_definite_batchlast"]

def _pd_from_entries(get: Callable[[int, int], torch.Tensor], n: int) -> torch.Tensor:
    """Cholesky pivots of symmetric matrices given entry by entry (``get(i, j)``, i ≥ j).

    Returns ``(N,)`` True where every pivot is finite and > 0; a NaN or infinite entry
    anywhere in the lower triangle makes some pivot NaN or ±inf, so this also tests
    finiteness.
    """
    low: dict[tuple[int, int], torch.Tensor] = {}
    pivots = []
    with torch.no_grad():
        for j in range(n):
            d = get(j, j)
            for k in range(j):
                d = torch.addcmul(d, low[j, k], low[j, k], value=-1.0)
            pivots.append(d)
            if j == n - 1:
                break
            inv = torch.rsqrt(d)
            for i in range(j + 1, n):
                s = get(i, j)
                for k in range(j):
                    s = torch.addcmul(s, low[i, k], low[j, k], value=-1.0)
                low[i, j] = s * inv
        piv = torch.stack(pivots)
        return ((piv > 0) & (piv < math.inf)).all(0)


def positive_definite_batchlast(pt: torch.Tensor) -> torch.Tensor:
    """Per-sample positive-definiteness test of a batch-last stack of symmetric matrices.

    Runs the Cholesky recursion ``l_jj² = a_jj − Σ_k l_jk²``,
    ``l_ij = (a_ij − Σ_k l_ik l_jk) / l_jj`` column by column on length-N vectors and
    reports whether every pivot ``l_jj²`` is finite and > 0 (Sylvester's criterion).
    Equivalent to ``torch.linalg.cholesky_ex(P).info == 0`` plus a finiteness test, and
    several times faster for small ``n`` on CPU (no per-matrix LAPACK call). For
    ``n > SMALL_STATE_MAX`` it calls ``cholesky_ex``.

    Args:
        pt: ``(n, n, N)`` symmetric matrices, batch last.

    Returns:
        ``(N,)`` bool, True where the matrix is finite and positive definite.
    """
    n = pt.shape[0]
    if n > SMALL_STATE_MAX:
        with torch.no_grad(), one_thread(n):  # no parallel-region waits on a busy machine
            flat = pt.reshape(n * n, -1)
            return (torch.linalg.cholesky_ex(pt.permute(2, 0, 1)).info == 0) & torch.isfinite(
                flat.sum(0)
            )
    return _pd_from_entries(lambda i, j: pt[i, j], n)


def _sum_rows(rows: Sequence[torch.Tensor]) -> torch.Tensor:
    acc = rows[0]
    for row in rows[1:]:
        acc = acc + row
    return acc


class BatchedEKF:
    """N independent EKFs with a shared state size ``n``, advanced in lock-step.

    ``predict`` and ``update`` act on all samples at once; shared matrices (``F``, ``Q``,
    ``R``, ``H``) may be given once or per sample. The filter runs in the dtype of ``x0``
    (float64 when ``x0`` is not floating; pass ``dtype`` to force one) and on ``x0``'s
    device; every other input is cast and moved to match.

    Args:
        x0: ``(N, n)`` initial state estimates.
        P0: ``(n, n)`` shared or ``(N, n, n)`` per-sample initial covariances; must be
            finite, symmetric and positive definite.
        dtype: Floating dtype of the filter (default: that of ``x0``, float64 if ``x0`` is
            not floating).
        check_pd: Test positive definiteness of ``P`` (Cholesky pivots) after every
            predict and update (default). False keeps only the finiteness, ``diag P > 0``
            and ``S > 0`` checks (slightly faster).

    Attributes:
        x: ``(N, n)`` state estimates (view of the batch-last storage).
        P: ``(N, n, n)`` covariances (view of the batch-last storage).
        healthy: ``(N,)`` bool; False = sample frozen (its x, P no longer change).

    Raises:
        NeuralMapError: Bad shapes, non-finite ``x0``, or a ``P0`` that is not symmetric
            positive definite (the message names the first offending sample).

    Example::

        ekf = BatchedEKF(torch.zeros(1000, 5, dtype=torch.float64), 1e4 * torch.eye(5))
        ekf.predict(F, Q)                                  # (5, 5) each
        diag = ekf.update(residual, H, R, mask=on_map)     # (N,), (N, 5), (N,), (N,)

    For the scalar fast path, passing ``H`` as the transposed view of a contiguous
    ``(n, N)`` tensor (``ht.t()``) saves a strided copy.
    """

    def __init__(
        self,
        x0: torch.Tensor,
        P0: torch.Tensor,
        *,
        dtype: torch.dtype | None = None,
        check_pd: bool = True,
    ) -> None:
        where = "BatchedEKF"
        if not isinstance(x0, torch.Tensor):
            x0 = torch.as_tensor(x0)
        if dtype is None:
            dtype = x0.dtype if x0.is_floating_point() else torch.float64
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise NeuralMapError(f"{where}: dtype must be a floating torch dtype, got {dtype!r}.")
        device = x0.device
        x0 = as_float_tensor(x0, name="x0", where=where, dtype=dtype, device=device)
        if x0.ndim != 2 or x0.shape[0] < 1 or x0.shape[1] < 1:
            raise shape_error(where, "x0", "(N, n) with N >= 1, n >= 1", x0.shape)
        check_finite(x0, name="x0", where=where)
        batch, n = x0.shape
        P0 = as_float_tensor(P0, name="P0", where=where, dtype=dtype, device=device)
        check_matrix_shape(P0, name="P0", where=where, n=n, batch=batch)
        P0 = check_covariance(P0, name="P0", where=where, definite=True)
        self._n = n
        self._batch = batch
        self._dtype = dtype
        self._device = device
        self._check_pd = bool(check_pd)
        self._small = n <= SMALL_STATE_MAX
        self._upper = [(i, j) for i in range(n) for j in range(i, n)]
        index = {ij: t for t, ij in enumerate(self._upper)}
        #: triangle position of every full entry (i, j), row-major
        self._full_from_tri = [index[min(i, j), max(i, j)] for i in range(n) for j in range(n)]
        self._eye = torch.eye(n, dtype=dtype, device=device)
        self._xt = x0.t().contiguous()
        if P0.ndim == 2:
            self._Pt = P0.unsqueeze(-1).expand(n, n, batch).contiguous()
        else:
            self._Pt = P0.permute(1, 2, 0).contiguous()
        self._healthy = torch.ones(batch, dtype=torch.bool, device=device)
        #: every stored P passed a positive-definiteness check (False after assignment)
        self._p_checked = True
        self._cache: dict[str, tuple[Any, int, Any]] = {}
        #: process noise of the last predict (for policies; cleared by the first update after
        #: it and by assigning P, since P is then no longer Φ P Φᵀ + Q), and updates so far
        self._last_Q: torch.Tensor | None = None
        self._n_updates = 0

    # ------------------------------------------------------------------ properties
    @property
    def x(self) -> torch.Tensor:
        """``(N, n)`` state estimates (a view; never modified in place)."""
        return self._xt.t()

    @x.setter
    def x(self, value: torch.Tensor) -> None:
        value = self._float(value, "x", "BatchedEKF.x")
        if tuple(value.shape) != (self._batch, self._n):
            raise shape_error("BatchedEKF.x", "x", f"(N, n) = ({self._batch}, {self._n})",
                              value.shape)
        self._xt = value.t().contiguous()

    @property
    def P(self) -> torch.Tensor:
        """``(N, n, n)`` covariances (a view; never modified in place).

        Assigning replaces them after a shape check only; definiteness is left to the
        health check of the next predict/update, which flags and freezes broken samples.
        """
        return self._Pt.permute(2, 0, 1)

    @P.setter
    def P(self, value: torch.Tensor) -> None:
        value = self._float(value, "P", "BatchedEKF.P")
        if tuple(value.shape) != (self._batch, self._n, self._n):
            raise shape_error("BatchedEKF.P", "P",
                              f"(N, n, n) = ({self._batch}, {self._n}, {self._n})", value.shape)
        self._Pt = value.permute(1, 2, 0).contiguous()
        self._p_checked = False
        self._last_Q = None

    @property
    def healthy(self) -> torch.Tensor:
        """``(N,)`` bool health flags (False = frozen)."""
        return self._healthy

    def reset(self, mask: torch.Tensor, x: torch.Tensor, P: torch.Tensor) -> None:
        """Filters ``mask (N,)`` restart from ``x (N, n)``, ``P (N, n, n)`` (rows outside the
        mask are kept) and are healthy again."""
        self.x = torch.where(mask[:, None], x.to(self.x.dtype), self.x)
        self.P = torch.where(mask[:, None, None], P.to(self.x.dtype), self.P)
        self._healthy = self._healthy | mask.to(self._healthy.device)

    @property
    def num_states(self) -> int:
        """State size ``n``."""
        return self._n

    @property
    def batch_size(self) -> int:
        """Number of filters ``N``."""
        return self._batch

    @property
    def dtype(self) -> torch.dtype:
        """Floating dtype of the filter."""
        return self._dtype

    @property
    def device(self) -> torch.device:
        """Device of the filter's tensors."""
        return self._device

    # ------------------------------------------------------------------ helpers
    def _float(self, value: object, name: str, where: str) -> torch.Tensor:
        return as_float_tensor(value, name=name, where=where, dtype=self._dtype,
                               device=self._device)

    def _cached(self, key: str, value: Any, convert: Callable[[Any], Any]) -> Any:
        """Validates/converts ``value`` once per distinct, unmodified input tensor.

        A repeated call with the very same tensor object (same ``_version``, i.e. not
        modified in place since) reuses the converted result; tensors that require grad
        are converted afresh every time (their graph changes every step).
        """
        hit = self._cache.get(key)
        if hit is not None and hit[0] is value and hit[1] == value._version:
            return hit[2]
        out = convert(value)
        if isinstance(value, torch.Tensor) and not value.requires_grad:
            self._cache[key] = (value, value._version, out)
        return out

    def _rows(self, pt: torch.Tensor) -> list[torch.Tensor]:
        """Upper-triangle entries of a batch-last ``(n, n, N)`` tensor as ``(N,)`` views."""
        return [pt[i, j] for i, j in self._upper]

    def _commit(
        self,
        xt: torch.Tensor,
        p_up: list[torch.Tensor],
        candidates: torch.Tensor | None,
        extra_ok: torch.Tensor | None = None,
        certified: bool = False,
        stacked: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Stores the new state where it is healthy; flags and freezes the rest.

        Args:
            xt: ``(n, N)`` candidate states.
            p_up: Upper-triangle entries of the candidate covariances, ``(N,)`` each, in
                row-major ``i <= j`` order (mirrored into the full matrix here).
            candidates: ``(N,)`` samples meant to change (None = all).
            extra_ok: ``(N,)`` further validity (e.g. ``S`` positive definite).
            certified: Positive definiteness (and finiteness) of every candidate ``P`` is
                already proven (see `_certified_pd`); skip the Cholesky test.
            stacked: The full ``(n, n, N)`` candidate covariances when the caller has
                already stacked ``p_up`` (saves one copy).

        Returns:
            ``(N,)`` bool: samples whose state was replaced.
        """
        n, batch = self._n, self._batch
        ok = torch.isfinite(xt.sum(0))
        if extra_ok is not None:
            ok = ok & extra_ok
        full = [p_up[t] for t in self._full_from_tri]
        pt_new: torch.Tensor | None = stacked
        if certified:
            pass
        elif self._check_pd and self._small:
            ok = ok & _pd_from_entries(lambda i, j: full[i * n + j], n)
        else:
            pt_new = torch.stack(full).reshape(n, n, batch)
            if self._check_pd:
                ok = ok & positive_definite_batchlast(pt_new)
            else:
                diag = torch.stack([p_up[self._full_from_tri[i * n + i]] for i in range(n)])
                ok = ok & torch.isfinite(_sum_rows(p_up)) & (diag > 0).all(0)
        cand = self._healthy if candidates is None else self._healthy & candidates
        take = cand & ok
        # _p_checked: every healthy sample's stored P passed a definiteness test. A commit
        # over all samples re-establishes it; a masked one keeps the previous state.
        if not (certified or self._check_pd):
            self._p_checked = False
        elif candidates is None:
            self._p_checked = True
        self._healthy = self._healthy & ~(cand & ~ok)
        if self._device.type == "cpu" and bool(take.all()):
            self._xt = xt
            self._Pt = pt_new if pt_new is not None else torch.stack(full).reshape(n, n, batch)
            return take
        self._xt = torch.where(take, xt, self._xt)
        if pt_new is not None:
            self._Pt = torch.where(take, pt_new, self._Pt)
        else:
            old = self._Pt
            kept = [
                torch.where(take, p, old[i, j])
                for p, (i, j) in zip(p_up, self._upper, strict=True)
            ]
            self._Pt = torch.stack([kept[t] for t in self._full_from_tri]).reshape(n, n, batch)
        return take

    # ------------------------------------------------------------------ predict
    def _transition(self, F: Any) -> TransitionPlan:
        """Validates ``F`` and, when shared, builds its covariance-propagation plan."""
        where = "BatchedEKF.predict"
        F = self._float(F, "F", where)
        check_matrix_shape(F, name="F", where=where, n=self._n, batch=self._batch)
        if F.ndim == 2:
            check_finite(F, name="F", where=where)
        return transition_plan(F)

    def _process_noise(self, Q: Any) -> tuple[torch.Tensor, float, float]:
        """Validated ``Q`` with ``(λ_min(Q), max |Q_ij|)`` for a shared ``Q`` (else 0, 0)."""
        where = "BatchedEKF.predict"
        Q = self._float(Q, "Q", where)
        check_matrix_shape(Q, name="Q", where=where, n=self._n, batch=self._batch)
        Q = check_covariance(Q, name="Q", where=where, definite=False)
        if Q.ndim == 3:
            return Q, 0.0, 0.0
        q = Q.detach().double()
        return Q, float(torch.linalg.eigvalsh(q)[0]), float(q.abs().max())

    def _certified_pd(self, plan: TransitionPlan, q_min: float, q_max: float) -> bool:
        """Whether every computed ``P⁻ = fl(F P Fᵀ) + Q`` is provably positive definite.

        Each computed entry ``P⁻_il = fl(Σ_t c_t P_t + Q_il)`` (at most ``k`` terms) has
        a rounding error ``|E_il| ≤ (k + 3)·eps·Σ_t |c_t| |P_t| + eps·|Q_il|``; with
        ``|P_jk| ≤ sqrt(P_jj P_kk) ≤ tr P`` for the stored positive definite P,
        ``‖E‖₂ ≤ n·max|E_il| ≤ n·eps·((k + 3)·C·tr P + max|Q|)``, ``C = max Σ_t |c_t|``
        (a 10 % margin is added). When that bound is below ``λ_min(Q)`` for every healthy
        sample, the computed ``P⁻`` has all eigenvalues ``≥ λ_min(Q) − ‖E‖₂ > 0`` and the
        Cholesky test can be skipped (roughly 0.3-0.5 ms at N = 100 000). A NaN/inf in
        ``P`` or an assigned (unchecked) ``P`` makes the full check run.
        """
        if q_min <= 0.0 or plan.F.ndim != 2 or not self._p_checked:
            return False
        n = self._n
        trace = self._Pt[0, 0]
        for i in range(1, n):
            trace = trace + self._Pt[i, i]
        trace = torch.where(self._healthy, trace.detach(), 0.0)
        eps = torch.finfo(self._dtype).eps
        bound = n * eps * (1.1 * (plan.n_terms + 3) * plan.coef_sum * trace.amax() + q_max)
        return bool(bound < q_min)

    def predict(
        self, F: torch.Tensor, Q: torch.Tensor, *, policy: FilterPolicy | None = None,
        trusted_noise: bool = False,
    ) -> None:
        """Time update of every healthy sample: ``x⁻ = F x``, ``P⁻ = F P Fᵀ + Q``.

        ``P⁻`` is computed on its upper triangle and mirrored (exactly symmetric; for a
        dense shared ``F`` the Kronecker rows are symmetrised, for per-sample ``F`` the
        product is symmetrised as ``(A + Aᵀ)/2``) by
        `neuralmap.filters.kalman.predict_upper`. Unhealthy samples are not touched; a
        sample whose ``P⁻`` is not finite and positive definite is flagged and keeps its
        previous ``x``, ``P``.

        Args:
            F: ``(n, n)`` shared or ``(N, n, n)`` per-sample transition matrix.
            Q: ``(n, n)`` shared or ``(N, n, n)`` per-sample process-noise covariance
                (symmetric positive semi-definite).
            policy: Optional `FilterPolicy` whose
                ``process_noise`` hook may return an adapted per-sample ``Q`` (Sage-Husa).
            trusted_noise: A per-sample ``Q`` comes from a model that makes it finite and
                exactly symmetric (e.g. the INS error model's ``Q_d``): only its shape is
                checked, not finiteness, symmetry and semi-definiteness (a per-sample
                Cholesky test per call). The numbers are the same (the validation's
                symmetrisation leaves an exactly symmetric ``Q`` unchanged); a ``Q`` that is
                not positive semi-definite still fails the health check of the commit.

        Raises:
            NeuralMapError: Wrong shapes, non-finite shared ``F``, or ``Q`` not symmetric
                positive semi-definite / with negative variances.
        """
        plan: TransitionPlan = self._cached("F", F, self._transition)
        if trusted_noise and getattr(Q, "ndim", 0) == 3:
            Q = self._float(Q, "Q", "BatchedEKF.predict")
            check_matrix_shape(Q, name="Q", where="BatchedEKF.predict", n=self._n,
                               batch=self._batch)
            q_min = q_max = 0.0
        else:
            Q, q_min, q_max = self._cached("Q", Q, self._process_noise)
        if policy is not None:
            n, batch = self._n, self._batch
            F_b = plan.F if plan.F.ndim == 3 else plan.F.expand(batch, n, n)
            Q_b = Q if Q.ndim == 3 else Q.expand(batch, n, n)
            adapted = policy.process_noise(F=F_b, Q=Q_b, P=self.P)
            if adapted is not None:
                # A policy's Q is only shape-checked and symmetrised here: a Q that is not
                # positive semi-definite (or not finite) makes P⁻ fail the health check of
                # the commit below, which flags that sample, so a per-sample Cholesky test of
                # Q at every predict would only cost time.
                adapted = self._float(adapted, "Q", "BatchedEKF.predict (policy)")
                if tuple(adapted.shape) != (batch, n, n):
                    raise shape_error("BatchedEKF.predict (policy)", "Q",
                                      f"(N, n, n) = ({batch}, {n}, {n})", adapted.shape)
                Q = symmetrize(adapted)
                q_min = q_max = 0.0
        self._last_Q = Q
        certified = self._check_pd and self._certified_pd(plan, q_min, q_max)
        xt, p_up = predict_upper(self._xt, self._Pt, plan, Q)
        self._commit(xt, p_up, None, certified=certified)

    # ------------------------------------------------------------------ update
    def _parse_measurement(
        self, residual: Any, H: Any
    ) -> tuple[torch.Tensor, torch.Tensor, int]:
        """Returns residual ``(N, m)``, ``H`` (``(N, m, n)`` or shared ``(m, n)``), m."""
        where = "BatchedEKF.update"
        n, batch = self._n, self._batch
        r = self._float(residual, "residual", where)
        if r.ndim == 1 and r.shape[0] == batch:
            r = r.unsqueeze(-1)
        if r.ndim != 2 or r.shape[0] != batch or r.shape[1] < 1:
            raise shape_error(where, "residual", f"(N,) or (N, m) with N = {batch}", r.shape)
        m = r.shape[1]
        H = self._float(H, "H", where)
        if H.ndim == 3 and tuple(H.shape) == (batch, m, n):
            pass
        elif H.ndim == 2 and m == 1 and tuple(H.shape) == (batch, n):
            H = H.unsqueeze(1)
        elif H.ndim == 2 and tuple(H.shape) == (m, n):
            check_finite(H, name="H", where=where)
        elif H.ndim == 1 and m == 1 and H.shape[0] == n:
            check_finite(H, name="H", where=where)
            H = H.unsqueeze(0)
        else:
            raise shape_error(
                where, "H",
                f"(N, m, n) = ({batch}, {m}, {n}) or shared (m, n) = ({m}, {n})"
                + (f", or for m = 1 (N, n) = ({batch}, {n}) or (n,) = ({n},)" if m == 1 else ""),
                H.shape,
            )
        return r, H, m

    def _parse_noise(self, R: Any, m: int, mask: torch.Tensor | None) -> torch.Tensor:
        """Returns R as ``()``/``(N,)`` for m = 1, else ``(m, m)``/``(N, m, m)``."""
        where = "BatchedEKF.update"
        batch = self._batch
        R = self._float(R, "R", where)
        if m == 1 and R.numel() == 1 and R.ndim <= 3:
            R = R.reshape(())
        elif m == 1 and tuple(R.shape) in ((batch, 1), (batch, 1, 1)):
            R = R.reshape(-1)
        if R.ndim == 0:
            value = float(R)
            if not 0.0 < value < math.inf:
                raise NeuralMapError(
                    f"{where}: 'R' = {value!r} is not a valid measurement variance; it must be "
                    "finite and > 0 (a positive definite noise covariance)."
                )
            return R if m == 1 else R * torch.eye(m, dtype=self._dtype, device=self._device)
        if R.ndim == 1:
            if m != 1 or R.shape[0] != batch:
                raise shape_error(
                    where, "R",
                    f"a float, (N,) = ({batch},) [m = 1 only], (m, m) = ({m}, {m}) or "
                    f"(N, m, m) = ({batch}, {m}, {m})", R.shape,
                )
            bad = R <= 0 if mask is None else (R <= 0) & mask
            if bool(bad.any()):
                i = int(torch.nonzero(bad)[0, 0])
                kind = "negative" if float(R[i]) < 0 else "zero"
                raise NeuralMapError(
                    f"{where}: 'R' has a {kind} variance {float(R[i])!r} at sample {i}. "
                    "Measurement variances must be > 0 (a NaN entry only flags its sample "
                    "unhealthy; use 'mask' to skip samples without a measurement)."
                )
            return R
        if R.ndim == 2 and tuple(R.shape) == (m, m):
            return check_covariance(R, name="R", where=where, definite=True)
        if R.ndim == 3 and tuple(R.shape) == (batch, m, m):
            sel = torch.isfinite(R.reshape(batch, -1)).all(-1)
            if mask is not None:
                sel = sel & mask
            check_covariance(R[sel], name="R", where=where, definite=True, symmetrize=False)
            return symmetrize(R)
        raise shape_error(
            where, "R",
            f"a float, (m, m) = ({m}, {m}) or (N, m, m) = ({batch}, {m}, {m})"
            + (f", or (N,) = ({batch},) for m = 1" if m == 1 else ""),
            R.shape,
        )

    def update(
        self,
        residual: torch.Tensor,
        H: torch.Tensor,
        R: torch.Tensor | float,
        *,
        mask: torch.Tensor | None = None,
        policy: FilterPolicy | None = None,
    ) -> UpdateDiagnostics:
        """Measurement update of every healthy, unmasked sample (Joseph form).

        ``S = H P⁻ Hᵀ + R``; ``K = P⁻ Hᵀ S⁻¹``; ``x⁺ = x⁻ + K r``;
        ``P⁺ = (I − KH) P⁻ (I − KH)ᵀ + K R Kᵀ`` (symmetric); ``NIS = rᵀ S⁻¹ r``;
        ``ℓ = −½ (m ln 2π + ln det S + NIS)``. Scalar measurements (m = 1) with n ≤ 8 take
        a fast path of elementwise kernels; vector measurements use ``cholesky_ex`` /
        ``cholesky_solve`` on ``(N, m, m)`` (`neuralmap.filters.kalman`).

        Masked samples are sanitised before any arithmetic (residual and H set to 0, R to
        1), so a NaN in a skipped sample's inputs cannot reach its outputs or the gradients
        of the others.

        Args:
            residual: ``(N,)`` or ``(N, m)`` innovation ``z − h(x⁻)`` computed by the
                caller.
            H: ``(N, m, n)`` per-sample Jacobian, ``(N, n)`` per-sample row (m = 1), or a
                shared ``(m, n)`` / ``(n,)`` one.
            R: Measurement-noise covariance: a float (``R·I``), ``(N,)`` per-sample
                variances (m = 1), ``(m, m)`` shared or ``(N, m, m)`` per-sample. A NaN in
                a sample's entries flags that sample unhealthy; negative or zero variances
                (of unmasked samples) are errors.
            mask: ``(N,)`` bool, False = skip this sample (no measurement, off the map);
                its ``x``, ``P`` and health are left unchanged whatever its inputs hold.
            policy: Optional `FilterPolicy` (robust or
                adaptive update); see that module for the protocol. The ``Q`` of the last
                predict reaches the policy (``context.process_noise``) on the first update
                after that predict only: a second update without a predict between sees
                ``None``, since its ``P`` is a posterior and not ``Φ P Φᵀ + Q``
                (inflation then scales the whole ``P``; Sage-Husa skips its Q estimate).

        Returns:
            `UpdateDiagnostics` (innovation, S, NIS, gain, health, applied, prior
            x and P, log-likelihood, what the policy did).

        Raises:
            NeuralMapError: Shape mismatches (expected vs received shapes), a shared ``R``
                that is not symmetric positive definite, or non-positive variances.
        """
        where = "BatchedEKF.update"
        r, H, m = self._parse_measurement(residual, H)
        if mask is not None:
            mask = check_mask(mask, where=where, batch=self._batch, device=self._device)
        R = self._parse_noise(R, m, mask)
        if mask is not None and not bool(mask.all()):
            r, H, R = self._sanitise(r, H, R, mask)
        if policy is not None:
            out = self._update_policy(r, H, R, mask, policy)
        elif m == 1 and R.ndim <= 1 and self._small:
            out = self._update_scalar(r[:, 0], H, R, mask)
        else:
            out = self._update_vector(r, H, R, mask)
        self._last_Q = None  # P is now a posterior, no longer Φ P Φᵀ + Q
        return out

    def _sanitise(
        self, r: torch.Tensor, H: torch.Tensor, R: torch.Tensor, mask: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Neutral inputs (r = 0, H = 0, R = 1) for masked samples, before any arithmetic."""
        r = torch.where(mask.unsqueeze(-1), r, 0.0)
        if H.ndim == 3:
            H = torch.where(mask.reshape(-1, 1, 1), H, 0.0)
        if R.ndim == 1:
            R = torch.where(mask, R, 1.0)
        elif R.ndim == 3:
            eye = torch.eye(R.shape[-1], dtype=R.dtype, device=R.device)
            R = torch.where(mask.reshape(-1, 1, 1), R, eye)
        return r, H, R

    def _dense_R(self, R: torch.Tensor, m: int) -> torch.Tensor:
        """Any accepted R form as ``(N, m, m)``."""
        batch = self._batch
        if R.ndim == 0:
            return (R * torch.eye(m, dtype=self._dtype, device=self._device)).expand(batch, m, m)
        if R.ndim == 1:
            return R.reshape(batch, 1, 1)
        if R.ndim == 2:
            return R.expand(batch, m, m)
        return R

    def _update_scalar(
        self, r: torch.Tensor, H: torch.Tensor, R: torch.Tensor, mask: torch.Tensor | None
    ) -> UpdateDiagnostics:
        """Fast path for one scalar measurement per sample (m = 1, n ≤ 8)."""
        n, batch = self._n, self._batch
        if H.ndim == 3:
            ht = H[:, 0, :].t().contiguous()  # (n, N): contiguous rows are ~2x faster
            h = [ht[j] for j in range(n)]
        else:
            h = [H[0, j] for j in range(n)]
        x_prior, p_prior = self.x, self.P
        xt, p_up, S, kt = update_scalar_upper(self._xt, self._Pt, r, h, R)
        applied = self._commit(xt, p_up, mask, extra_ok=(S > 0) & (S < math.inf))
        nis = r * r / S
        return UpdateDiagnostics(
            innovation=r.unsqueeze(-1),
            S=S.reshape(batch, 1, 1),
            nis=nis,
            gain=kt.t().unsqueeze(-1),
            healthy=self._healthy,
            applied=applied,
            x_prior=x_prior,
            P_prior=p_prior,
            log_likelihood=gaussian_log_likelihood(nis, S.log(), 1),
        )

    def _update_vector(
        self, r: torch.Tensor, H: torch.Tensor, R: torch.Tensor, mask: torch.Tensor | None
    ) -> UpdateDiagnostics:
        """General path: ``(N, m, m)`` innovation covariances and Cholesky solves."""
        batch, m = self._batch, r.shape[1]
        if H.ndim == 2:
            H = H.expand(batch, m, self._n)
        x_prior, p_prior = self.x, self.P
        out = update_dense(x_prior, p_prior, r, H, self._dense_R(R, m))
        applied = self._commit(
            out.x.t().contiguous(), self._rows(out.P.permute(1, 2, 0)), mask, extra_ok=out.s_ok
        )
        return UpdateDiagnostics(
            innovation=r, S=out.S, nis=out.nis, gain=out.gain, healthy=self._healthy,
            applied=applied, x_prior=x_prior, P_prior=p_prior,
            log_likelihood=gaussian_log_likelihood(out.nis, out.log_det_S, m),
        )

    def _update_policy(
        self,
        r: torch.Tensor,
        H: torch.Tensor,
        R: torch.Tensor,
        mask: torch.Tensor | None,
        policy: FilterPolicy,
    ) -> UpdateDiagnostics:
        """Update driven by a policy (see `neuralmap.filters.policy`)."""
        if r.shape[1] == 1 and self._small:
            return self._update_policy_scalar(r, H, R, mask, policy)
        return self._update_policy_dense(r, H, R, mask, policy)

    def _update_policy_dense(
        self,
        r: torch.Tensor,
        H: torch.Tensor,
        R: torch.Tensor,
        mask: torch.Tensor | None,
        policy: FilterPolicy,
    ) -> UpdateDiagnostics:
        """Policy-driven update with ``(N, m, m)`` kernels (any m, n)."""
        n, batch, m = self._n, self._batch, r.shape[1]
        H = H.expand(batch, m, n) if H.ndim == 2 else H
        R = self._dense_R(R, m)
        x_prior, p_prior = self.x, self.P
        active = self._healthy if mask is None else self._healthy & mask
        hpht = torch.matmul(torch.matmul(H, p_prior), H.transpose(1, 2))
        context = UpdateContext(
            x_prior=x_prior, P_prior=p_prior, residual=r, H=H, R=R,
            HPHt=symmetrize(hpht), mask=active,
            process_noise=None if self._last_Q is None else (
                self._last_Q if self._last_Q.ndim == 3 else self._last_Q.expand(batch, n, n)
            ),
            step=self._n_updates,
        )
        adaptation = policy.adapt(context)
        posterior: Posterior | None = None
        out = None
        for _ in range(max(1, int(policy.iterations))):
            p_use, r_use, res_use, h_use, any_kept = self._adapted_inputs(
                context, adaptation
            )
            out = update_dense(x_prior, p_use, res_use, h_use, r_use)
            posterior = Posterior(x=out.x, P=out.P, P_prior=p_use, R=r_use, S=out.S,
                                  gain=out.gain, residual=res_use)
            nxt = policy.refine(context, adaptation, posterior)
            if nxt is None:
                break
            adaptation = nxt
        assert out is not None and posterior is not None
        candidates = any_kept if mask is None else any_kept & mask
        applied = self._commit(
            out.x.t().contiguous(), self._rows(out.P.permute(1, 2, 0)), candidates,
            extra_ok=out.s_ok,
        )
        policy.commit(context, adaptation, posterior, applied)
        self._n_updates += 1
        return UpdateDiagnostics(
            innovation=r, S=out.S, nis=out.nis, gain=out.gain, healthy=self._healthy,
            applied=applied, x_prior=x_prior, P_prior=p_prior,
            log_likelihood=gaussian_log_likelihood(out.nis, out.log_det_S, m),
            policy_info=dict(adaptation.info),
        )

    def _update_policy_scalar(
        self,
        r: torch.Tensor,
        H: torch.Tensor,
        R: torch.Tensor,
        mask: torch.Tensor | None,
        policy: FilterPolicy,
    ) -> UpdateDiagnostics:
        """Policy-driven update for a scalar measurement (m = 1, n ≤ 8), entry by entry.

        The same protocol and the same equations as the dense path: the context's
        ``H P⁻ Hᵀ`` is ``Σ_j h_j (P⁻ hᵀ)_j`` on length-N vectors, and every pass is
        `update_scalar_upper` (the expanded Joseph form)
        on the adapted ``P⁻`` (``p_scale·P⁻`` or the replacement), ``R`` and the kept
        measurement (a rejected one: ``r = 0``, ``h = 0``, ``R = 1``, not applied). Only
        rounding differs from the dense ``(N, m, m)`` kernels.
        """
        n, batch = self._n, self._batch
        if H.ndim == 3:
            ht = H[:, 0, :].t().contiguous()
            h = [ht[j] for j in range(n)]
            H3 = H
        else:
            h = [H[0, j] for j in range(n)]
            H3 = H.expand(batch, 1, n)
        pt = self._Pt
        u = []
        for i in range(n):  # u = P⁻ hᵀ, h P⁻ hᵀ = Σ_i h_i u_i
            acc = pt[i, 0] * h[0]
            for j in range(1, n):
                acc = torch.addcmul(acc, pt[i, j], h[j])
            u.append(acc if acc.ndim else acc.expand(batch))
        hph = u[0] * h[0]
        for i in range(1, n):
            hph = torch.addcmul(hph, u[i], h[i])
        x_prior, p_prior = self.x, self.P
        active = self._healthy if mask is None else self._healthy & mask
        r1 = r[:, 0]
        context = UpdateContext(
            x_prior=x_prior, P_prior=p_prior, residual=r, H=H3, R=self._dense_R(R, 1),
            HPHt=hph.reshape(batch, 1, 1), mask=active,
            process_noise=None if self._last_Q is None else (
                self._last_Q if self._last_Q.ndim == 3 else self._last_Q.expand(batch, n, n)
            ),
            step=self._n_updates,
        )
        adaptation = policy.adapt(context)
        posterior: Posterior | None = None
        for _ in range(max(1, int(policy.iterations))):
            # A rejected measurement: r = 0, h = 0 (so P⁻hᵀ = 0), R = 1 and the stored P⁻
            # (not the adapted one); then K = 0 and x⁺ = x⁻, P⁺ = P⁻ bitwise, so the
            # sample is committed with the others (no per-entry selection) and reported
            # as not applied.
            any_kept: torch.Tensor | None = None
            if adaptation.keep is not None:
                any_kept = adaptation.keep.to(torch.bool)[:, 0]
            pt_use: torch.Tensor = pt
            u_use: list[torch.Tensor] | None = u
            if adaptation.P_prior is not None:
                pt_use = adaptation.P_prior.permute(1, 2, 0).contiguous()
                if any_kept is not None:
                    pt_use = torch.where(any_kept, pt_use, pt)
                u_use = None
            if adaptation.p_scale is not None:
                scale = adaptation.p_scale
                if any_kept is not None:
                    scale = torch.where(any_kept, scale, 1.0)
                pt_use = pt_use * scale
                if u_use is not None:
                    u_use = [ui * scale for ui in u_use]
            r_use = R if adaptation.R is None else adaptation.R.reshape(batch)
            res_use, h_use = r1, h
            if any_kept is not None:
                res_use = torch.where(any_kept, r1, 0.0)
                h_use = [torch.where(any_kept, hj, 0.0) for hj in h]
                r_use = torch.where(any_kept, r_use, 1.0)
                if u_use is not None:
                    u_use = [torch.where(any_kept, ui, 0.0) for ui in u_use]
            xt, p_up, S, kt = update_scalar_upper(self._xt, pt_use, res_use, h_use, r_use,
                                                  u=u_use)
            p_full = full_from_upper(p_up, n)
            r_used = r_use.expand(batch) if r_use.ndim == 0 else r_use
            posterior = Posterior(
                x=xt.t(), P=p_full.permute(2, 0, 1),
                P_prior=pt_use.permute(2, 0, 1), R=r_used.reshape(batch, 1, 1),
                S=S.reshape(batch, 1, 1), gain=kt.t().unsqueeze(-1),
                residual=res_use.unsqueeze(-1),
            )
            nxt = policy.refine(context, adaptation, posterior)
            if nxt is None:
                break
            adaptation = nxt
        assert posterior is not None
        applied = self._commit(xt, p_up, mask, extra_ok=(S > 0) & (S < math.inf),
                               stacked=p_full)
        if any_kept is not None:
            applied = applied & any_kept
        policy.commit(context, adaptation, posterior, applied)
        self._n_updates += 1
        nis = res_use * res_use / S
        return UpdateDiagnostics(
            innovation=r, S=S.reshape(batch, 1, 1), nis=nis, gain=kt.t().unsqueeze(-1),
            healthy=self._healthy, applied=applied, x_prior=x_prior, P_prior=p_prior,
            log_likelihood=gaussian_log_likelihood(nis, S.log(), 1),
            policy_info=dict(adaptation.info),
        )

    def _adapted_inputs(
        self, context: UpdateContext, adaptation: Adaptation
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """P⁻, R, residual, H after an adaptation; rejected components dropped exactly.

        Returns ``(P⁻, R, r, H, any_kept)``; ``any_kept`` ``(N,)`` is False for samples
        whose every component was rejected (they are not updated).
        """
        p_use = context.P_prior if adaptation.P_prior is None else adaptation.P_prior
        if adaptation.p_scale is not None:
            p_use = p_use * adaptation.p_scale.reshape(-1, 1, 1)
        r_use = context.R if adaptation.R is None else adaptation.R
        res_use, h_use = context.residual, context.H
        any_kept = torch.ones(self._batch, dtype=torch.bool, device=self._device)
        if adaptation.keep is not None:
            keep = adaptation.keep.to(torch.bool)
            m = keep.shape[1]
            both = keep.unsqueeze(-1) & keep.unsqueeze(-2)
            eye = torch.eye(m, dtype=self._dtype, device=self._device)
            # A rejected component: residual 0, H row 0, R row/column of the identity —
            # exactly the update without that component.
            r_use = torch.where(both, r_use, eye)
            res_use = torch.where(keep, res_use, 0.0)
            h_use = torch.where(keep.unsqueeze(-1), h_use, 0.0)
            any_kept = keep.any(-1)
        return p_use, r_use, res_use, h_use, any_kept
