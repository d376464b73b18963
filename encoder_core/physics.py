"""Hall signals to angle (seed 000, eq. 1-3) and the angle-error helpers every part shares."""

from __future__ import annotations

import math

import numpy as np

ADC_BITS = 12
ADC_MAX = 2**ADC_BITS - 1
ADC_MID = 2 ** (ADC_BITS - 1)
REFERENCE_TEMP_C = 20.0  # seed 000's target temperature: the +20 °C table
BAND_WIDTH_C = 10.0  # coefficients are fitted per temperature band of this width


def band_of(temp_c):
    """Temperature band index: band k holds [10k, 10k + 10) °C. An int for a number, an int array for an array."""
    if isinstance(temp_c, (float, int)) and math.isfinite(temp_c):  # one number, as the wire checks it: 10x faster
        return math.floor(temp_c / BAND_WIDTH_C)
    bands = np.floor(np.asarray(temp_c, dtype=float) / BAND_WIDTH_C).astype(int)
    return int(bands) if bands.ndim == 0 else bands


def halls_to_dq(a_plus, a_minus, b_plus, b_minus) -> tuple[np.ndarray, np.ndarray]:
    """Differential pairs (seed 000, eq. 1-2): d = B+ - B-, q = A+ - A-."""
    d = np.asarray(b_plus, dtype=float) - np.asarray(b_minus, dtype=float)
    q = np.asarray(a_plus, dtype=float) - np.asarray(a_minus, dtype=float)
    return d, q


def angle(d, q) -> np.ndarray:
    """Electrical angle in radians (seed 000, eq. 3), four-quadrant."""
    return np.arctan2(np.asarray(q, dtype=float), np.asarray(d, dtype=float))


def wrap_rad(x) -> np.ndarray:
    """Wrap to [-pi, pi)."""
    return (np.asarray(x, dtype=float) + np.pi) % (2 * np.pi) - np.pi


def circular_mean(angles, axis: int | None = None):
    """Mean direction of angles in radians (immune to the wrap at ±π): a number, or along `axis` an array."""
    mean = np.angle(np.mean(np.exp(1j * np.asarray(angles, dtype=float)), axis=axis))
    return float(mean) if axis is None else mean


def angle_error_deg(theta_est, theta_ref) -> np.ndarray:
    """Signed error est - ref in degrees, wrapped to [-180, 180)."""
    return np.degrees(wrap_rad(np.asarray(theta_est) - np.asarray(theta_ref)))


def rms(x) -> float:
    x = np.asarray(x, dtype=float)
    return float(np.sqrt(np.mean(x * x))) if x.size else float("nan")


def error_summary(theta_est, theta_ref) -> dict:
    """RMS and max absolute angle error in degrees."""
    err = angle_error_deg(theta_est, theta_ref)
    return {"rms_error_deg": rms(err), "max_error_deg": float(np.max(np.abs(err))) if err.size else float("nan")}
