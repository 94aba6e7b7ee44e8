"""Rate-distortion fronts: Pareto fronts, bytes at equal error, and the Bjøntegaard delta rate.

A map format is a curve of stored bytes against error. Comparisons between two formats are
made on their fronts (the points no other point of the same format beats in both bytes and
error):

* `bytes_at_error`: the bytes a front needs for a given error, interpolated linearly
  in ``log(bytes)`` over ``log(error)`` between its points (None outside the front's range);
* `bd_rate`: the Bjøntegaard delta rate (G. Bjøntegaard, VCEG-M33, 2001): the mean
  relative difference in bytes of curve B against curve A over their common error range,
  ``exp(mean(log R_B - log R_A)) - 1`` with the mean taken uniformly in ``log(error)``
  (the distortion axis; ``-20 log10(error)`` is a PSNR up to a constant, so this is the
  usual BD-rate with PSNR). The log-rates are interpolated piecewise linearly (robust with
  few points, unlike the original cubic fit) on a fine grid of the common range. Negative
  values: B needs fewer bytes than A at equal error;
* `gaussian_rd_bytes`: how few bytes any coder could need for a node RMSE if the tile
  were a Gaussian field with its own (smoothed) spectrum, by reverse water-filling over the
  tile's DCT coefficients (T. M. Cover and J. A. Thomas, *Elements of Information Theory*,
  2nd ed., Theorem 10.3.3). Among fields of a given covariance the Gaussian one is the
  hardest to code, so a coder below this rate exploits structure beyond the spectrum
  (non-stationarity, non-Gaussian shapes); one above it has room left that a linear
  transform coder could take. With ``oracle=True`` each coefficient is its own variance:
  the rate a coder would need if it knew every coefficient's variance exactly, far below
  anything a real coder reaches (it is told most of the answer). For a given covariance
  the Gaussian source is the hardest (Cover & Thomas, Thm. 10.3.3 with the maximum-entropy
  property, Thm. 8.6.5): its R(D) is an **upper** bound on the R(D) of a non-Gaussian,
  non-stationary source with the same spectrum, such as terrain; a codec may sit below it;
* `shannon_lower_bound_bytes`: the Shannon lower bound
  ``R(D) ≥ h̄ − ½ log2(2πe D)`` bits per node (Cover & Thomas, Problem 10.8; Berger 1971,
  §4.3), with the differential entropy rate ``h̄`` of the field estimated by
  `innovation_entropy_bits`: the entropy of the innovations of a causal linear
  predictor given a causal context of local roughness. Since
  ``h(X | past) = h(X − f(past) | past) ≤ h(X − f(past) | c(past))`` for any causal ``f``
  and context ``c``, that entropy is an upper estimate of ``h̄``: the bound computed from it
  is an estimate of the Shannon lower bound from above (a better predictor would lower it).
  No coder of the tile at node RMSE ``√D`` can need fewer bits than the true bound.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.fft import dctn
from scipy.optimize import brentq
from scipy.stats import differential_entropy

__all__ = ["bd_rate", "bytes_at_error", "causal_innovations", "gaussian_rd_bytes",
           "innovation_entropy_bits", "pareto_front", "shannon_lower_bound_bytes"]

#: Causal neighbourhood (row, column offsets) of the innovation predictor: the raster-order
#: past within two rows and two columns (12 neighbours).
CAUSAL_OFFSETS: tuple[tuple[int, int], ...] = (
    (0, -1), (0, -2),
    (-1, -2), (-1, -1), (-1, 0), (-1, 1), (-1, 2),
    (-2, -2), (-2, -1), (-2, 0), (-2, 1), (-2, 2),
)


def pareto_front(sizes: list[float], errors: list[float | None]) -> list[int]:
    """Indices of the rate-distortion front: no other point is smaller and more accurate.

    Args:
        sizes: Stored bytes per point.
        errors: Error per point (NaN / None points are skipped).

    Returns:
        Indices on the front, by increasing size (and decreasing error).
    """
    points = [
        (s, e, i) for i, (s, e) in enumerate(zip(sizes, errors, strict=True))
        if e is not None and math.isfinite(e)
    ]
    points.sort(key=lambda p: (p[0], p[1]))
    front: list[int] = []
    best = math.inf
    for _, err, index in points:
        if err < best:
            front.append(index)
            best = err
    return front


def _curve(sizes: list[float], errors: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """``(log error, log bytes)`` of the front, by increasing log error; errors > 0 only."""
    idx = pareto_front(sizes, errors)
    pts = [(math.log(errors[i]), math.log(sizes[i])) for i in idx if errors[i] > 0]
    pts.sort()
    if not pts:
        return np.zeros(0), np.zeros(0)
    log_e, log_r = (np.asarray(v, dtype=np.float64) for v in zip(*pts, strict=True))
    return log_e, log_r


def bytes_at_error(sizes: list[float], errors: list[float], error: float) -> float | None:
    """Bytes the front of ``(sizes, errors)`` needs for ``error`` (log-log interpolation).

    Returns:
        The interpolated bytes; None when ``error`` is outside the front's error range
        (no extrapolation) or the front is empty.
    """
    log_e, log_r = _curve(sizes, errors)
    if log_e.size == 0 or not (error > 0):
        return None
    x = math.log(error)
    if x < log_e[0] - 1e-12 or x > log_e[-1] + 1e-12:
        return None
    return float(math.exp(np.interp(x, log_e, log_r)))


def bd_rate(
    sizes_a: list[float], errors_a: list[float], sizes_b: list[float], errors_b: list[float],
    *, n_grid: int = 256,
) -> float | None:
    """Bjøntegaard delta rate of curve B against curve A (see the module docstring).

    Args:
        sizes_a: Bytes of the anchor's points (e.g. JPEG 2000).
        errors_a: Their errors (> 0; e.g. node RMSE).
        sizes_b: Bytes of the tested format's points.
        errors_b: Their errors.
        n_grid: Points of the integration grid over the common log-error range.

    Returns:
        The BD-rate as a fraction (``-0.3`` = B needs 30 % fewer bytes); None when the two
        fronts do not overlap in error (or one has fewer than 2 points).
    """
    ea, ra = _curve(sizes_a, errors_a)
    eb, rb = _curve(sizes_b, errors_b)
    if ea.size < 2 or eb.size < 2:
        return None
    lo, hi = max(ea[0], eb[0]), min(ea[-1], eb[-1])
    if not hi > lo:
        return None
    grid = np.linspace(lo, hi, int(n_grid))
    diff = np.interp(grid, eb, rb) - np.interp(grid, ea, ra)
    return float(math.expm1(float(np.trapezoid(diff, grid) / (hi - lo))))


def _dct_variances(coefficients: np.ndarray, radial_bins: int, angle_bins: int) -> np.ndarray:
    """Per-coefficient variance: the mean power over (log radius, angle) cells of the spectrum.

    Args:
        coefficients: ``(ny, nx)`` orthonormal DCT-II coefficients of the mean-free field.
        radial_bins: Cells in log spatial frequency (from the lowest to the highest).
        angle_bins: Cells in orientation over the quarter plane (anisotropic relief).

    Returns:
        ``(ny, nx)`` variance of each coefficient (the DC term keeps its own power).
    """
    ny, nx = coefficients.shape
    ky, kx = np.meshgrid(np.arange(ny) / ny, np.arange(nx) / nx, indexing="ij")
    radius = np.hypot(ky, kx)
    edges = np.linspace(math.log(1.0 / max(ny, nx)), math.log(math.sqrt(2.0)), radial_bins)
    ring = np.digitize(np.log(np.maximum(radius, 1e-12)), edges)
    sector = np.minimum((np.arctan2(ky, kx) / (math.pi / 2) * angle_bins).astype(int),
                        angle_bins - 1)
    cell = (ring * angle_bins + sector).ravel()
    power = coefficients.ravel() ** 2
    mean_power = np.bincount(cell, power) / np.maximum(np.bincount(cell), 1)
    variances = mean_power[cell].reshape(ny, nx)
    variances[0, 0] = coefficients[0, 0] ** 2
    return variances


def gaussian_rd_bytes(
    heights: np.ndarray, rmse_m: float, *, oracle: bool = False,
    radial_bins: int = 40, angle_bins: int = 12,
) -> float:
    """Bytes a Gaussian field with the tile's spectrum needs at a node RMSE (reverse water-filling).

    The mean-free node heights ``h`` are transformed by the orthonormal 2-D DCT-II (close to
    the Karhunen-Loève transform of a stationary field); coefficient ``k`` gets variance
    ``σ²_k`` (the mean power of its spectral cell, or ``c_k²`` with ``oracle``); then with
    the water level ``θ`` solving ``mean_k min(θ, σ²_k) = D = rmse²``,
    ``R(D) = Σ_k max(0, ½ log2(σ²_k / θ))`` bits (Cover & Thomas, Thm. 10.3.3).

    Args:
        heights: ``(ny, nx)`` node heights, m (voids must be filled first).
        rmse_m: Node RMSE, m (> 0).
        oracle: Each coefficient's own power as its variance (see the module docstring).
        radial_bins: Log-frequency cells of the smoothed spectrum.
        angle_bins: Orientation cells of the smoothed spectrum.

    Returns:
        ``R(D) / 8`` in bytes (0 when ``D`` is at least the field's variance).

    Raises:
        ValueError: Non-finite heights, a non-2-D array or ``rmse_m <= 0``.
    """
    field = np.asarray(heights, dtype=np.float64)
    if field.ndim != 2 or not np.all(np.isfinite(field)):
        raise ValueError("gaussian_rd_bytes: heights must be a finite 2-D array (fill voids "
                         "first, e.g. neuralmap.terrain.grid.fill_voids_nearest).")
    if not rmse_m > 0:
        raise ValueError(f"gaussian_rd_bytes: rmse_m must be > 0, got {rmse_m!r}.")
    coefficients = dctn(field - field.mean(), norm="ortho")
    variances = (np.maximum(coefficients**2, 1e-300) if oracle
                 else _dct_variances(coefficients, radial_bins, angle_bins))
    distortion = float(rmse_m) ** 2
    if distortion >= float(np.mean(variances)):
        return 0.0
    theta = brentq(lambda t: float(np.mean(np.minimum(t, variances))) - distortion,
                   1e-300, float(variances.max()))
    return float(np.sum(np.maximum(0.0, 0.5 * np.log2(variances / theta))) / 8.0)


def _finite_field(heights: np.ndarray, where: str) -> np.ndarray:
    field = np.asarray(heights, dtype=np.float64)
    if field.ndim != 2 or not np.all(np.isfinite(field)):
        raise ValueError(f"{where}: heights must be a finite 2-D array (fill voids first, e.g. "
                         "neuralmap.terrain.grid.fill_voids_nearest).")
    return field


def causal_innovations(heights: np.ndarray) -> np.ndarray:
    """Innovations of the least-squares causal linear predictor of each node.

    Every node ``x[i, j]`` at least two rows/columns inside the tile is predicted from its
    raster-order past `CAUSAL_OFFSETS` by one linear predictor with an intercept,
    fitted by least squares over the tile: ``e = x − (a₀ + Σ_m a_m x[i + di_m, j + dj_m])``.

    Args:
        heights: ``(ny, nx)`` node heights, m (finite; ``ny, nx ≥ 5``).

    Returns:
        ``((ny − 2)·(nx − 4),)`` innovations, m.

    Raises:
        ValueError: Non-finite heights, a non-2-D array, or a tile smaller than 5 × 5.
    """
    field = _finite_field(heights, "causal_innovations")
    ny, nx = field.shape
    if ny < 5 or nx < 5:
        raise ValueError(f"causal_innovations: the tile must be at least 5 x 5 nodes, got "
                         f"{ny} x {nx}.")
    target = field[2:, 2:nx - 2].ravel()
    columns = [np.ones_like(target)]
    columns += [field[2 + di:ny + di, 2 + dj:nx - 2 + dj].ravel() for di, dj in CAUSAL_OFFSETS]
    design = np.stack(columns, axis=1)
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    return target - design @ coef  # e = x − x̂(past)


def innovation_entropy_bits(heights: np.ndarray, *, context_bins: int = 8) -> float:
    """Conditional differential entropy of the causal innovations, bits per node: an upper
    estimate of the field's entropy rate ``h̄`` (see the module docstring).

    The innovations ``e`` of `causal_innovations` are grouped by a causal context, the
    local activity ``c = ¼ (|e_W| + |e_NW| + |e_N| + |e_NE|)`` of the four already-coded
    neighbours (a function of the past, so ``h(X | past) ≤ h(e | c) ≤ h(e)``), cut into
    ``context_bins`` equally populated bins; ``h(e | c) = Σ_b p_b h(e | b)``, each term
    estimated from its sample with ``scipy.stats.differential_entropy`` (m-spacing
    estimators; Vasicek 1976, Ebrahimi et al. 1994), in nats, then divided by ``ln 2``. The
    context captures non-stationary roughness (flat and rough parts of a tile); with
    ``context_bins=1`` the estimate is the marginal entropy of the innovations.

    Args:
        heights: ``(ny, nx)`` node heights, m (finite; at least 5 × 5).
        context_bins: Activity bins (≥ 1).

    Returns:
        The entropy estimate, bits per node.

    Raises:
        ValueError: Bad heights (see `causal_innovations`) or ``context_bins < 1``.
    """
    if int(context_bins) < 1:
        raise ValueError(f"innovation_entropy_bits: context_bins must be >= 1, got "
                         f"{context_bins!r}.")
    field = _finite_field(heights, "innovation_entropy_bits")
    ny, nx = field.shape
    e = causal_innovations(field).reshape(ny - 2, nx - 4)
    if int(context_bins) == 1:
        return float(differential_entropy(e.ravel())) / math.log(2.0)
    a = np.abs(e)
    current = e[1:, 1:-1].ravel()
    activity = (0.25 * (a[1:, :-2] + a[:-1, :-2] + a[:-1, 1:-1] + a[:-1, 2:])).ravel()
    edges = np.quantile(activity, np.linspace(0.0, 1.0, int(context_bins) + 1)[1:-1])
    context = np.digitize(activity, edges)
    entropy = 0.0
    for b in np.unique(context):
        sample = current[context == b]
        entropy += sample.size / current.size * float(differential_entropy(sample))
    return entropy / math.log(2.0)


def shannon_lower_bound_bytes(heights: np.ndarray, rmse_m: float, *,
                              entropy_bits: float | None = None) -> float:
    """Shannon lower bound of the bytes any coder needs at a node RMSE (estimated).

    ``R_SLB(D) = n · max(0, h̄ − ½ log2(2πe D)) / 8`` bytes for ``n`` nodes and
    ``D = rmse²`` (Cover & Thomas, Problem 10.8), with ``h̄`` from
    `innovation_entropy_bits` unless given.

    Args:
        heights: ``(ny, nx)`` node heights, m (voids filled).
        rmse_m: Node RMSE, m (> 0).
        entropy_bits: Entropy rate in bits per node, to skip the estimate (e.g. computed
            once for many RMSEs).

    Returns:
        The bound in bytes (0 where ``½ log2(2πe D) ≥ h̄``).

    Raises:
        ValueError: Non-finite heights or ``rmse_m <= 0``.
    """
    field = _finite_field(heights, "shannon_lower_bound_bytes")
    if not rmse_m > 0:
        raise ValueError(f"shannon_lower_bound_bytes: rmse_m must be > 0, got {rmse_m!r}.")
    h_bar = innovation_entropy_bits(field) if entropy_bits is None else float(entropy_bits)
    per_node = h_bar - 0.5 * math.log2(2.0 * math.pi * math.e * float(rmse_m) ** 2)
    return float(field.size * max(0.0, per_node) / 8.0)
