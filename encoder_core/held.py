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
    if not full.any():
        return []
    if full.all():
        return []  # a drive that turns: every bin is full, nothing is held
    start = int(np.flatnonzero(~full)[0])  # walk the circle from an empty bin, so no run wraps
    runs, run = [], []
    for k in [(start + i) % len(full) for i in range(len(full))]:
        if full[k]:
            run.append(k)
        elif run:
            runs, run = runs + [run], []
    runs += [run] if run else []
    out = []
    for run in runs:
        sums = stats.bins[run].sum(axis=0)
        n = sums[0]
        mean = sums[1:3] / n
        sxx, sxy, syy = sums[3:6] / n - np.array([mean[0] ** 2, mean[0] * mean[1], mean[1] ** 2])
        r2 = float(mean @ mean)
        if r2 <= 0:
            continue
        tangential = (mean[1] ** 2 * sxx - 2 * mean[0] * mean[1] * sxy + mean[0] ** 2 * syy) / r2
        if not np.sqrt(max(tangential, 0.0) / r2) < MAX_SPREAD_RAD:
            continue
        point = np.array([stats.center_d, stats.center_q]) + stats.scale * mean
        out.append((point, max((sxx + syy) / 2, 1e-12) * stats.scale**2 / n))
    return out
