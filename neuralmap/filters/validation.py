"""Input checks for the batched filters: shapes, symmetry, (semi-)definiteness, variances.

Every check raises `NeuralMapError` with a message that says
which argument is wrong, the expected and the received shape or value, the first offending
sample of a batch, and how to fix it. The checks are meant for user-supplied matrices
(``P0``, ``Q``, ``R``, a shared ``F``); per-sample problems that arise while filtering
(a NaN residual, a covariance that loses definiteness) are not errors but health flags of
`BatchedEKF`.
"""

from __future__ import annotations

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.threads import one_thread

#: Relative tolerance of the symmetry check, in units of the dtype's machine epsilon
#: (``|M - M^T| <= SYMMETRY_EPS_FACTOR * eps * max|M|`` per matrix).
SYMMETRY_EPS_FACTOR = 1.0e4


def as_float_tensor(
    value: object, *, name: str, where: str, dtype: torch.dtype, device: torch.device
) -> torch.Tensor:
    """Converts an array-like or number to a floating tensor of the filter's dtype/device.

    Args:
        value: Tensor, NumPy array, nested list or Python number.
        name: Argument name used in error messages.
        where: Calling function (``"BatchedEKF.predict"``), used in error messages.
        dtype: Target floating dtype.
        device: Target device.

    Returns:
        The tensor, cast and moved (no copy when it already matches).

    Raises:
        NeuralMapError: ``value`` cannot be converted to a numeric tensor.
    """
    if isinstance(value, torch.Tensor):
        if value.is_complex() or value.dtype == torch.bool:
            raise NeuralMapError(
                f"{where}: '{name}' must be a real floating tensor, got dtype {value.dtype}."
            )
        return value.to(dtype=dtype, device=device)
    try:
        return torch.as_tensor(value, dtype=dtype, device=device)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise NeuralMapError(
            f"{where}: '{name}' must be a tensor or array of numbers, got "
            f"{type(value).__name__} ({exc})."
        ) from exc


def shape_error(
    where: str, name: str, expected: str, got: torch.Size | tuple[int, ...]
) -> NeuralMapError:
    """Builds the standard shape-mismatch error.

    Args:
        where: Calling function.
        name: Argument name.
        expected: Human-readable accepted shapes, e.g. ``"(5, 5) or (N, 5, 5) = (100, 5, 5)"``.
        got: The received shape.

    Returns:
        The error (the caller raises it).
    """
    return NeuralMapError(
        f"{where}: '{name}' has shape {tuple(got)}, expected {expected}. Pass a tensor of "
        "one of the expected shapes (batch dimension first)."
    )


def _first_bad(bad: torch.Tensor) -> int:
    """Index of the first True entry of a ``(B,)`` bool tensor (``-1`` if none)."""
    idx = torch.nonzero(bad.reshape(-1))
    return int(idx[0, 0]) if idx.numel() else -1


def _sample_text(batched: bool, index: int) -> str:
    return f" (sample {index})" if batched else ""


def check_matrix_shape(
    m: torch.Tensor, *, name: str, where: str, n: int, batch: int
) -> torch.Tensor:
    """Checks that ``m`` is ``(n, n)`` or ``(batch, n, n)``.

    Args:
        m: The matrix or batch of matrices.
        name: Argument name.
        where: Calling function.
        n: Required matrix size.
        batch: Batch size ``N`` accepted as leading dimension.

    Returns:
        ``m`` unchanged.

    Raises:
        NeuralMapError: Wrong shape (message gives expected vs received).
    """
    ok = (m.ndim == 2 and tuple(m.shape) == (n, n)) or (
        m.ndim == 3 and tuple(m.shape) == (batch, n, n)
    )
    if not ok:
        expected = f"({n}, {n}) or (N, {n}, {n}) = ({batch}, {n}, {n})"
        raise shape_error(where, name, expected, m.shape)
    return m


def check_finite(m: torch.Tensor, *, name: str, where: str) -> torch.Tensor:
    """Raises when any entry of ``m`` is NaN or infinite.

    Args:
        m: ``(n, n)``, ``(B, n, n)`` or any tensor whose first dimension (if 3-D) is a batch.
        name: Argument name.
        where: Calling function.

    Returns:
        ``m`` unchanged.

    Raises:
        NeuralMapError: Non-finite entries (first offending sample named).
    """
    finite = torch.isfinite(m)
    if not bool(finite.all()):
        batched = m.ndim == 3
        index = _first_bad(~finite.reshape(m.shape[0], -1).all(-1)) if batched else 0
        raise NeuralMapError(
            f"{where}: '{name}' contains NaN or infinite values{_sample_text(batched, index)}. "
            "Pass finite numbers."
        )
    return m


def check_covariance(
    m: torch.Tensor,
    *,
    name: str,
    where: str,
    definite: bool,
    symmetrize: bool = True,
) -> torch.Tensor:
    """Checks a covariance (or a batch of them): finite, symmetric, variances, definiteness.

    Definiteness is tested with a Cholesky factorisation (``torch.linalg.cholesky_ex``):
    ``definite=True`` requires ``M`` positive definite; ``definite=False`` accepts positive
    semi-definite matrices (zero process noise on some states) by factorising
    ``M + δI`` with ``δ = sqrt(eps) · max(diag M)``, which still rejects any eigenvalue
    clearly below zero. A diagonal matrix needs no factorisation (its variances are its
    eigenvalues); small matrices are factorised on one torch thread
    (`neuralmap.threads.one_thread`).

    Args:
        m: ``(n, n)`` or ``(B, n, n)`` floating tensor.
        name: Argument name (``"P0"``, ``"Q"``, ``"R"``).
        where: Calling function.
        definite: Require positive definiteness (else semi-definiteness).
        symmetrize: Return ``(M + M^T) / 2`` (exactly symmetric) instead of ``M``.

    Returns:
        The (symmetrised) matrix.

    Raises:
        NeuralMapError: Non-finite entries, asymmetry beyond the tolerance, a negative
            (or, when ``definite``, zero) variance on the diagonal, or a matrix that is not
            positive (semi-)definite; the first offending sample is named.
    """
    check_finite(m, name=name, where=where)
    batched = m.ndim == 3
    mb = m if batched else m.unsqueeze(0)
    eps = torch.finfo(m.dtype).eps
    scale = mb.abs().amax(dim=(-2, -1))
    asym = (mb - mb.transpose(-2, -1)).abs().amax(dim=(-2, -1))
    bad = asym > SYMMETRY_EPS_FACTOR * eps * scale
    if bool(bad.any()):
        i = _first_bad(bad)
        raise NeuralMapError(
            f"{where}: '{name}' is not symmetric{_sample_text(batched, i)}: "
            f"max |M - M^T| = {float(asym[i]):.3g} for max |M| = {float(scale[i]):.3g}. "
            "A covariance must be symmetric; pass (M + M.mT) / 2."
        )
    diag = mb.diagonal(dim1=-2, dim2=-1)
    neg = (diag < 0).any(-1)
    if bool(neg.any()):
        i = _first_bad(neg)
        raise NeuralMapError(
            f"{where}: '{name}' has a negative variance on its diagonal"
            f"{_sample_text(batched, i)}: {diag[i].tolist()}. Variances must be >= 0 "
            "(check the sign, and that you passed variances, not their negatives)."
        )
    need = "positive definite" if definite else "positive semi-definite"
    if definite:
        zero = (diag <= 0).any(-1)
        if bool(zero.any()):
            i = _first_bad(zero)
            raise NeuralMapError(
                f"{where}: '{name}' must be {need} but has a zero variance"
                f"{_sample_text(batched, i)}: diagonal {diag[i].tolist()}. Give every state "
                "(or measurement) a variance > 0."
            )
        test = mb
    else:
        delta = (eps**0.5) * diag.amax(-1).clamp_min(torch.finfo(m.dtype).tiny)
        eye = torch.eye(m.shape[-1], dtype=m.dtype, device=m.device)
        test = mb + delta[:, None, None] * eye
    if not bool((mb - torch.diag_embed(diag)).any()):
        # diagonal: the variance checks above already prove (semi-)definiteness
        return 0.5 * (m + m.transpose(-2, -1)) if symmetrize else m
    with one_thread(m.shape[-1]):  # small factorisations: no parallel-region waits
        info = torch.linalg.cholesky_ex(test).info
    bad = info != 0
    if bool(bad.any()):
        i = _first_bad(bad)
        eig = torch.linalg.eigvalsh(mb[i]).min()
        raise NeuralMapError(
            f"{where}: '{name}' is not {need}{_sample_text(batched, i)}: smallest "
            f"eigenvalue {float(eig):.6g} (Cholesky fails at leading minor {int(info[i])}). "
            "Check the off-diagonal covariances (|cov_ij| must be below "
            "sqrt(var_i * var_j)) or use a diagonal matrix."
        )
    if symmetrize:
        m = 0.5 * (m + m.transpose(-2, -1))
    return m


def check_mask(mask: object, *, where: str, batch: int, device: torch.device) -> torch.Tensor:
    """Checks an update mask: a ``(N,)`` bool tensor.

    Args:
        mask: The mask (True = apply the update to this sample).
        where: Calling function.
        batch: Batch size ``N``.
        device: Device of the filter.

    Returns:
        The mask on ``device``.

    Raises:
        NeuralMapError: Not a bool tensor of shape ``(N,)``.
    """
    if not isinstance(mask, torch.Tensor) or mask.dtype != torch.bool:
        kind = mask.dtype if isinstance(mask, torch.Tensor) else type(mask).__name__
        raise NeuralMapError(
            f"{where}: 'mask' must be a bool tensor of shape (N,) = ({batch},), got {kind}. "
            "Build it with a comparison, e.g. terrain.contains(xy)."
        )
    if tuple(mask.shape) != (batch,):
        raise shape_error(where, "mask", f"(N,) = ({batch},)", mask.shape)
    return mask.to(device)
