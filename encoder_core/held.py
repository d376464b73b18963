"""The positions a drive holds: a servo that dwells at a few angles and moves between them faster than its
sample clock shows the ellipse too little of the circle in any window, but each held position is one true angle,
and its mean raw point moves only with temperature and the drive's own changes. `held_points` finds them in a
window's (or a band's) angle bins; the drift monitor compares each with its last visit (an offset step moves
every position by the same vector).
"""

from __future__ import annotations

import numpy as np

from .stats import WindowStats

MIN_HELD_COUNT = 20  # samples in an angle bin for it to count as a held position
MAX_SPREAD_RAD = np.radians(0.2)  # a held position scatters ~0.08° along the circle; a bin crossed in transit, wider


def held_points(stats: WindowStats) -> list[tuple[np.ndarray, float]]:
    """(mean raw point, variance of that mean per axis) of each position the window held: runs of neighbouring
    angle bins with enough samples, summed (a position on a bin edge, or pushed across one by a step, is one
    point), and scattered along the circle no more than a held position is (two positions a few degrees apart,
    or a bin a move crosses, scatter wider)."""
    full = stats.bins[:, 0] >= MIN_HELD_COUNT
    if full.all() or not full.any():
        return []  # nothing held, or a drive that turns: every bin is full
    # the circle walked from an empty bin (so no run wraps), the other bins emptied: each run's sums in one reduceat
    order = np.roll(np.arange(full.size), -int(np.flatnonzero(~full)[0]))
    kept = full[order]
    starts = np.flatnonzero(kept & ~np.concatenate(([False], kept[:-1])))
    sums = np.add.reduceat(np.where(kept[:, None], stats.bins[order], 0.0), starts)
    n = sums[:, 0]
    mean = sums[:, 1:3] / n[:, None]
    sxx, sxy, syy = (
        sums[:, 3:6] / n[:, None] - np.column_stack([mean[:, 0] ** 2, mean[:, 0] * mean[:, 1], mean[:, 1] ** 2])
    ).T
    r2 = np.einsum("ij,ij->i", mean, mean)
    with np.errstate(divide="ignore", invalid="ignore"):
        tangential = (mean[:, 1] ** 2 * sxx - 2 * mean[:, 0] * mean[:, 1] * sxy + mean[:, 0] ** 2 * syy) / r2
        held = (r2 > 0) & (np.sqrt(np.maximum(tangential, 0.0) / r2) < MAX_SPREAD_RAD)
    centre = np.array([stats.center_d, stats.center_q])
    var = np.maximum((sxx + syy) / 2, 1e-12) * stats.scale**2 / n
    return [(centre + stats.scale * mean[k], float(var[k])) for k in np.flatnonzero(held)]
