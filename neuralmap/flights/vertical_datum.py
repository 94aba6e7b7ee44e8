"""Which vertical datum the INS altitude is on, and a check that it is the map's.

A radar altimeter measures clearance ``c = h − H(x, y)``: the INS altitude ``h`` and the
map height ``H`` must be on the same vertical datum, or the filter reads the datum offset
as an altitude error it cannot resolve (a geoid undulation is 20–100 m, larger than any
altimeter σ).

Assumption (default ``alt_datum="dem"``): the log's altitude is above the DEM's own
vertical datum (orthometric heights for SRTM/NED/Copernicus: EGM96/EGM2008/NAVD88).
``alt_datum="ellipsoidal"`` declares WGS-84 ellipsoidal heights (GNSS, KF-GINS navigation
results); the geoid undulation ``N`` of the area must then be given and the altitude
used is ``h − N`` (orthometric = ellipsoidal − undulation). Without ``N`` it is refused.

`check_datum` refuses a log whose altitudes disagree with the map and the radar by
more than the filter's own uncertainty can explain — the symptom of a wrong datum.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError

__all__ = ["ALT_DATUMS", "apply_datum", "check_datum"]

#: Accepted vertical datums of a log's altitude.
ALT_DATUMS = ("dem", "ellipsoidal")


def apply_datum(altitude: np.ndarray, alt_datum: str, geoid_undulation: float | None, *,
                where: str) -> np.ndarray:
    """The altitude on the DEM's datum: unchanged (``"dem"``) or ``h − N`` (``"ellipsoidal"``).

    Args:
        altitude: ``(...)`` altitudes from the log, m.
        alt_datum: ``"dem"`` or ``"ellipsoidal"``.
        geoid_undulation: ``N`` in metres (geoid above the ellipsoid) for ellipsoidal input.
        where: The log and column, for messages.

    Raises:
        NeuralMapError: Unknown datum, or ellipsoidal input without an undulation.
    """
    if alt_datum not in ALT_DATUMS:
        raise NeuralMapError(
            f"--alt_datum {alt_datum!r}: choose one of {', '.join(ALT_DATUMS)} (dem = the "
            "altitude is above the DEM's vertical datum; ellipsoidal = WGS-84 ellipsoidal "
            "heights).")
    if alt_datum == "dem":
        if geoid_undulation is not None:
            raise NeuralMapError(
                f"--geoid_undulation {geoid_undulation} applies only with --alt_datum "
                "ellipsoidal (with the default --alt_datum dem the altitude is already on "
                "the DEM's datum).")
        return np.asarray(altitude, dtype=np.float64)
    if geoid_undulation is None or not np.isfinite(geoid_undulation):
        raise NeuralMapError(
            f"{where}: the altitude is ellipsoidal (WGS-84) but the DEM's heights are on "
            "its own vertical datum (usually a geoid); give the area's geoid undulation N "
            "with --geoid_undulation N (metres; the altitude used is h - N), or 0 when the "
            "DEM's heights are ellipsoidal too.")
    return np.asarray(altitude, dtype=np.float64) - float(geoid_undulation)


def check_datum(altitude: np.ndarray, map_height: np.ndarray, clearance: np.ndarray, *,
                sigma_m: float, n_sigma: float = 5.0, alt_datum: str, where: str
                ) -> dict[str, Any]:
    """Refuses a log whose altitude is inconsistent with map height + clearance.

    With ``d = h − H(x_INS) − c`` over the epochs with a clearance, the log is refused when
    (a) the INS altitude lies below the map surface (``h < H``) at more than half the
    epochs, or (b) ``|median d| > n_sigma · sigma_m`` where ``sigma_m`` is the spread the
    navigator itself allows (initial altitude σ, altimeter σ and map σ combined). Both are
    what a datum mistake (an ellipsoidal altitude read as orthometric, or feet) looks like.

    Args:
        altitude: ``(M,)`` INS altitude on the assumed datum, m.
        map_height: ``(M,)`` map height under the INS position, m (NaN off the map).
        clearance: ``(M,)`` measured clearance, m (NaN = none).
        sigma_m: Combined σ the navigator allows, m.
        n_sigma: Threshold in σ.
        alt_datum: The assumed datum (named in the message).
        where: The log, for messages.

    Returns:
        ``{"median_offset_m", "below_ground_fraction", "n_checked", "threshold_m"}``.

    Raises:
        NeuralMapError: One of the two tests fails; the message names the datum assumed
            and how to declare another.
    """
    ok = np.isfinite(altitude) & np.isfinite(map_height) & np.isfinite(clearance)
    summary: dict[str, Any] = {"n_checked": int(ok.sum()), "threshold_m": n_sigma * sigma_m,
                               "median_offset_m": None, "below_ground_fraction": None}
    if not ok.any():
        return summary
    d = altitude[ok] - map_height[ok] - clearance[ok]
    median = float(np.median(d))
    below = float(np.mean(altitude[ok] < map_height[ok]))
    summary.update(median_offset_m=median, below_ground_fraction=below)
    assumed = ("above the DEM's vertical datum (--alt_datum dem)" if alt_datum == "dem"
               else "WGS-84 ellipsoidal minus --geoid_undulation (--alt_datum ellipsoidal)")
    fix = ("If the altitude is ellipsoidal (GNSS/INS), pass --alt_datum ellipsoidal "
           "--geoid_undulation N; check also the units (feet vs metres)." if alt_datum == "dem"
           else "Check --geoid_undulation (N = geoid minus ellipsoid, metres) or use "
                "--alt_datum dem if the altitude is already orthometric.")
    if below > 0.5:
        raise NeuralMapError(
            f"{where}: the INS altitude lies below the map surface at {below:.0%} of the "
            f"{int(ok.sum())} epochs with a clearance (median altitude - map height - "
            f"clearance = {median:+.1f} m), assuming the altitude is {assumed}. {fix}")
    if abs(median) > n_sigma * sigma_m:
        raise NeuralMapError(
            f"{where}: altitude - map height - radar clearance has median {median:+.1f} m "
            f"over {int(ok.sum())} epochs, more than {n_sigma:g} σ ({n_sigma * sigma_m:.1f} m) "
            f"of what the navigator allows, assuming the altitude is {assumed}. This looks like a "
            f"vertical datum mismatch (or a bias in the INS altitude). {fix}")
    return summary
