"""The positions a drive holds: a servo that dwells at a few angles and moves between them faster than its
sample clock shows the ellipse too little of the circle in any window, but each held position is one true angle,
and its mean raw point moves only with temperature and the drive's own changes. `held_points` finds them in a
window's (or a band's) angle bins; the drift monitor compares each with its last visit (an offset step moves
every position by the same vector).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .differential import TERMS, BenchLocus, DriftModel, TermModel
from .physics import circular_mean
from .stats import WindowStats

MIN_HELD_COUNT = 20  # samples in an angle bin for it to count as a held position
MAX_SPREAD_RAD = np.radians(0.2)  # a held position scatters ~0.08° along the circle; a bin crossed in transit, wider


DWELT_BINS = 16.0  # a band whose samples fill fewer angle bins than this (Kish's count) was a drive holding positions


def dwelt(stats: WindowStats) -> bool:
    """The samples sit in a few angle bins (a drive holding positions), by Kish's effective count."""
    counts = stats.bins[:, 0]
    return float(counts.sum() ** 2 / max(float(np.sum(counts**2)), 1e-12)) < DWELT_BINS


@dataclass
class HeldPoint:
    point: np.ndarray  # mean raw (d, q)
    var: float  # variance of that mean per axis, raw units²
    temp_c: float  # mean temperature of its samples (the windows' means, weighted by their counts in its bins)
    count: float
    spread: float = 0.0  # scatter of its samples along the circle, rad


def held_points(stats: WindowStats) -> list[tuple[np.ndarray, float]]:
    """(mean raw point, variance of that mean per axis) of each position the window held: runs of neighbouring
    angle bins with enough samples, summed (a position on a bin edge, or pushed across one by a step, is one
    point), and scattered along the circle no more than a held position is (two positions a few degrees apart,
    or a bin a move crosses, scatter wider)."""
    return [(h.point, h.var) for h in held_runs(stats)]


def held_runs(stats: WindowStats, *, split: bool = False) -> list[HeldPoint]:
    """held_points with each position's temperature and count (from a band's bin temperatures, see
    WindowStats.bin_temp). split: a run of bins too wide to be one position gives each of its bins that is one,
    inside the bin by EDGE_SDS of its scatter (two positions a few degrees apart in neighbouring bins, which a
    band's sums over hours show; a position astride an edge would leave each bin a truncated, biased half)."""
    full = stats.bins[:, 0] >= MIN_HELD_COUNT
    if full.all() or not full.any():
        return []  # nothing held, or a drive that turns: every bin is full
    # the circle walked from an empty bin (so no run wraps), the other bins emptied: each run's sums in one reduceat
    order = np.roll(np.arange(full.size), -int(np.flatnonzero(~full)[0]))
    kept = full[order]
    starts = np.flatnonzero(kept & ~np.concatenate(([False], kept[:-1])))
    rows = np.where(kept[:, None], stats.bins[order], 0.0)
    temps = np.where(kept, stats.bin_temps()[order], 0.0)
    runs = _held_of(stats, np.add.reduceat(rows, starts), np.add.reduceat(temps, starts))
    out = [h for h, _, ok in runs if ok]
    if split:
        wide = [k for k, (_, _, ok) in enumerate(runs) if not ok]
        for k in wide:
            stop = starts[k + 1] if k + 1 < starts.size else kept.size
            for h, spread, ok in _held_of(stats, rows[starts[k] : stop], temps[starts[k] : stop]):
                angle = np.arctan2(*((h.point - (stats.center_d, stats.center_q))[::-1])) % (2 * np.pi)
                inside = np.remainder(angle, 2 * np.pi / stats.bins.shape[0])
                margin = min(inside, 2 * np.pi / stats.bins.shape[0] - inside)
                if ok and h.count >= MIN_HELD_COUNT and margin > EDGE_SDS * spread:
                    out.append(h)
    return out


EDGE_SDS = 5.0


def _held_of(stats: WindowStats, sums: np.ndarray, temp_sums: np.ndarray) -> list[tuple[HeldPoint, float, bool]]:
    """Each row of bin sums as a point: (the point, its scatter along the circle in rad, held: narrow enough)."""
    n = sums[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        mean = sums[:, 1:3] / n[:, None]
        sxx, sxy, syy = (
            sums[:, 3:6] / n[:, None] - np.column_stack([mean[:, 0] ** 2, mean[:, 0] * mean[:, 1], mean[:, 1] ** 2])
        ).T
        r2 = np.einsum("ij,ij->i", mean, mean)
        tangential = (mean[:, 1] ** 2 * sxx - 2 * mean[:, 0] * mean[:, 1] * sxy + mean[:, 0] ** 2 * syy) / r2
        spread = np.sqrt(np.maximum(tangential, 0.0) / r2)
        held = (n > 0) & (r2 > 0) & (spread < MAX_SPREAD_RAD)
        var = np.maximum((sxx + syy) / 2, 1e-12) * stats.scale**2 / n
        temps = temp_sums / n
    centre = np.array([stats.center_d, stats.center_q])
    return [
        (
            HeldPoint(centre + stats.scale * mean[k], float(var[k]), float(temps[k]), float(n[k]), float(spread[k])),
            spread[k],
            held[k],
        )
        for k in range(n.size)
        if n[k] > 0
    ]


# --- drift from held positions ----------------------------------------------------------------------------------

MIN_POSITIONS = 3  # held positions seen in two bands or more, while the bench holds (the gap check below refuses
# three bunched together: three within 18° left the rest of the circle a guess). A servo holds 3-6 positions; at four,
# a quarter of the dwelling drive-runs (three positions) never got a drift curve and ran their factory set for 3 days
MIN_POSITIONS_STEPPED = 4  # ... and after a step, whose terms at the bench are fitted too: two more unknowns the
# positions near the bench must pin beside their own angles (three positions: s2-5hz-10's curve after its offset step
# stated 0.03-0.05° and was 0.10-0.15° wrong, ten hours worse than the factory set; s3-5hz-22 after a gain step, five)
# ... spread around the circle: no gap between them wider than this (288°: the set's error is the largest around the
# whole circle, gap included; at 180° s12-20hz-02, s3-20hz-02, s5-20hz-10 and s7-20hz-06 kept sets 1.2-3.5x worse; at
# 225° s6-5hz-14's three positions within 125° kept its factory set, moved for its gain step, 15 hours worse than the
# factory set, and s3-20hz-22's six; with a curve, 2.7x and 3.4x; at 252° s5-20hz-10 2.4x, at 288° 3.2x, and no drive
# worse in any hour. With no limit s4-5hz-14's four positions within 80° gave a curve after its gain step that was
# five hours worse than the factory set)
MAX_GAP_RAD = 1.6 * np.pi
# ... and the positions along the circle fitted by one drift curve within this many times their own errors: past it
# they moved in a way no drift in temperature does (an offset step the monitor did not name, s5-20hz-02: with it the
# fit was 3.6 times its errors along the circle, and confidently 1° wrong; before it, 1.5-2)
MAX_ALONG_SCALE = 2.5
SAME_POSITION_RAD = np.radians(0.4)  # held points of two bands this close along the circle are one position (the
# drift moves a position by ~0.2° at most; servos' positions a degree apart are there)
OUTLIER_SIGMAS = 5.0
SPREAD_EXCESS = 1.5  # a held point scattering wider than this times the drive's typical held point mixes positions
POSITION_REACH_C = 10.0  # a position's angle at a temperature is measured where it was held this close to it
BENCH_REACH_C = 10.0  # a position held this close to the bench's temperature is tied to the factory's angle there
HELD_FLOOR = 5e-5  # a held point's error floor per axis, fraction of the radius (0.003°): a servo's repeatability
# each term's curve: a line plus a square in temperature (DriftModel's), and the rotation of both axes, which held
# positions see (the ellipse fit cannot); `common` (the channels' common gain) moves no angle
HELD_TERMS = (*TERMS, "common", "zero")
# a term's value at the bench is, to the held positions, one more turn of each θ_k: it is held to the factory's (no
# drift there, as DriftModel's bench point), and the θ_k take the rest
AT_BENCH_PRIOR = 1e-6
# a loose prior on each term's slope per 10 K, several times a hall encoder's typical tempcos (offsets ~0.05
# counts/K on 1,500, gain ratio ~1.5e-4/K, axes ~1.5e-5 rad/K, common gain ~1e-3/K), and on its square per (10 K)²
# a tenth of that (the squares are a tenth of the slopes over ±10 K or less): where the held positions do not pin a
# combination of terms, it stays near the factory's (no drift) instead of anywhere. A position held only at +17 and
# +41 °C, with the square as loose as the slope, was extrapolated to 0.95° at -20 °C (s6-20hz-06; its truth 0.04°)
SQUARE_PRIOR = 0.1
SLOPE_PRIOR = {"offset_d": 1e-3, "offset_q": 1e-3, "imbalance": 5e-3, "axis": 1e-3, "common": 3e-2, "zero": 1e-3}
# after a step the terms it moved are the step's at the bench: held loosely (fraction of the radius, or log gain; the
# monitor names steps of 0.2-1 %), so the held points' radial parts measure them and their angles along the circle
# still tie each θ_k to the factory's (a shift or a stretch of the circle is no turn of it). A step the held test could
# not judge (no position held before it was left to compare with) is named an offset step, and may have been one
# channel's gain: both are fitted and the one the points sit closer to across the circle is taken (s4-20hz-22, a q
# gain step: 60-80 times the points' errors squared as an offset step, 11-15 as a gain step; s1-20hz-02, an offset
# step: 0.7-8 as one, no fit at all as a gain step)
STEP_PRIOR = 0.05
STEP_KINDS = {"offset": ("offset_d", "offset_q"), "gain": ("common", "imbalance")}  # the terms each kind moves


@dataclass
class HeldDrift:
    """The drift since the bench measured at the positions a drive holds (`held_drift_model`)."""

    model: DriftModel  # the four angle terms, and `common` and `zero`, as DriftModel's curves
    theta: np.ndarray  # each position's bench angle (rad, the locus's)
    positions: int  # positions seen in two bands or more
    points: int
    chi2_dof: float
    misfit: np.ndarray  # (points, 2): each held point's misfit across and along the circle, in its own error (nan:
    # left out as an outlier)
    scale: np.ndarray  # how far the misfit scaled those errors up, across and along
    position_temps: list = field(default_factory=list)  # the temperatures each position was held at
    _along: object = None  # (params) -> each position's angle drift at each temperature asked (see angle_error)
    _params: np.ndarray | None = None
    _cov: np.ndarray | None = None
    _step_share: np.ndarray | None = None  # which parameters are a step's, not drift (offsets_stepped)
    step: str | None = None  # the kind of step fitted (STEP_KINDS), None when the bench holds
    failed: str = ""  # the check the curve failed ("a gap" between positions, the misfit "along" the circle), or ""

    @property
    def across_misfit(self) -> float:
        """Mean square of the kept points' misfit across the circle, in their own errors."""
        across = self.misfit[:, 0]
        return float(np.mean(across[np.isfinite(across)] ** 2))

    def covers(self, temp_c: float) -> bool:
        """Every position was held within POSITION_REACH_C of this temperature: the positions' angles there are
        measured, not carried from other temperatures by the terms (s6-20hz-06: a position held only at +17 and
        +41 °C read 0.35° at -20 °C, ±0.06°, where its truth was 0.04°; the other two positions had pinned the
        terms only in the directions they see)."""
        return all(np.min(np.abs(np.asarray(t) - temp_c)) <= POSITION_REACH_C for t in self.position_temps)

    def angle_error(self, temp_c: float) -> float:
        """Standard error (rad) of the angle's drift since the bench at a temperature, the largest around the
        circle: what a set made from the model is uncertain by, beside the factory's set (the values at the bench,
        which no held position tells from its own angle, are the factory's uncertainty too; after an offset step
        the step's offsets are the fit's, and their error is in this one). Around the whole
        circle, not only at the held positions, where it is far smaller: the servo may hold another position next,
        and three positions within 18° of each other left the rest of s5-20hz-02's circle 1° off."""
        bench = self.model.terms["offset_d"].bench_c
        circle = np.linspace(0.0, 2 * np.pi, 72, endpoint=False)

        def since_bench(p: np.ndarray) -> np.ndarray:
            # against the bench without the step: a set after an offset step carries the step too, and its error
            return self._along(p, temp_c, circle) - self._along(np.where(self._step_share, 0.0, p), bench, circle)

        base = since_bench(self._params)
        steps = np.sqrt(np.maximum(np.diag(self._cov), 1e-24)) * 1e-3
        jac = np.column_stack(
            [
                (since_bench(self._params + np.eye(self._params.size)[j] * steps[j]) - base) / steps[j]
                for j in range(self._params.size)
            ]
        )
        return float(np.sqrt(np.max(np.einsum("ij,jk,ik->i", jac, self._cov, jac))))


def held_drift_model(
    bands: list[WindowStats], locus: BenchLocus, *, offsets_stepped: bool = False, iterations: int = 6
) -> HeldDrift | None:
    """The drift curve (each term a line plus a square in temperature, as DriftModel's) from the positions a
    drive holds, where its bands' samples fill too few angle bins for the ellipse fit (`fit_drifts`).

    Each held position is one true angle θ_k, the same in every band: the bench locus maps it to where the
    bench saw it, and the drift at the point's temperature maps that to where the field shows it. So the
    points of one position in bands of different temperatures see the drift along the circle as well as
    across it (the ellipse fit sees only across), the rotation of both axes included. Unknowns: every θ_k and
    each term's curve through the bench (its value there held to the factory's, AT_BENCH_PRIOR; its slope and
    square to SLOPE_PRIOR and SQUARE_PRIOR); least squares over every band's held points at their own
    temperatures. Across the circle a held point moves with the channels' common gain (0.1 %/K) times the die's
    lag behind the temperature the windows report, along it with the angle's drift alone: each direction's errors
    are scaled by its own misfit. None when fewer than MIN_POSITIONS positions (MIN_POSITIONS_STEPPED after a step)
    were held in two bands or more.
    The bench's zero drift is what ties the θ_k to the factory's angles, so only while the bench holds, or after
    offset or gain steps alone (offsets_stepped: the band sums hold only windows since the last step, and the step's
    values at the bench are fitted too, STEP_PRIOR; an axis step's rotation half would turn every θ_k alike, which
    no held point tells from the factory's zero). The step may have been an offset step or one channel's gain
    (STEP_KINDS): both are fitted, and the one closer to the points across is taken if it passes its checks (none
    otherwise)."""
    kinds = STEP_KINDS if offsets_stepped else [None]
    # the kind is chosen before its checks: a kind that fails them leaves the step unmeasured, not the other kind's
    # (s10-20hz-14, a gain step: as one, 16 times the points' errors squared across and 3.4 along, past
    # MAX_ALONG_SCALE; as an offset step 58 across and 2.2 along, which passed, and its set was 0.3° wrong where the
    # factory set left 0.1°)
    fits = [f for f in (_held_drift(bands, locus, kind, iterations) for kind in kinds) if f is not None]
    best = min(fits, key=lambda f: f.across_misfit, default=None)
    return best if best is not None and not best.failed else None


def _held_drift(bands: list[WindowStats], locus: BenchLocus, step: str | None, iterations: int) -> HeldDrift | None:
    """held_drift_model's fit, the terms of a step of this kind (STEP_KINDS) fitted at the bench too."""
    obs = [h for stats in bands for h in held_runs(stats, split=True)]
    if obs:
        # a held position scatters along the circle with the channels' noise, the same at every position of a drive;
        # a point that scatters wider holds a second position nearby now and then (s6-20hz-06: 118.3° and 120.6°
        # in one angle bin, mixed in another proportion in each band, read as 0.6° of drift)
        typical = float(np.median([h.spread for h in obs]))
        obs = [h for h in obs if h.spread <= SPREAD_EXCESS * typical]
    need = MIN_POSITIONS if step is None else MIN_POSITIONS_STEPPED
    if len(obs) < 2 * need:
        return None
    c = np.array([locus.d[0], locus.q[0]])
    radius = locus.radius
    grid = np.linspace(0.0, 2 * np.pi, 4096, endpoint=False)
    gd, gq = locus.points(grid)
    first = np.array([grid[np.argmin((gd - h.point[0]) ** 2 + (gq - h.point[1]) ** 2)] for h in obs])
    position = _positions(first)
    temps = np.array([h.temp_c for h in obs])
    # only positions the drive held near the bench's temperature: there the factory's angle is right, which ties
    # each θ_k to the reference (elsewhere the curve would be extrapolated to the bench to find it)
    tied = np.isin(position, position[np.abs(temps - locus.temp_c) <= BENCH_REACH_C])
    obs, first, temps = [h for h, t in zip(obs, tied) if t], first[tied], temps[tied]
    _, position = np.unique(position[tied], return_inverse=True)
    k_pos = int(position.max()) + 1 if position.size else 0
    if sum(np.sum(position == k) >= 2 for k in range(k_pos)) < need:
        return None
    points = np.array([h.point for h in obs])
    sd = np.sqrt(np.array([h.var for h in obs]) + (HELD_FLOOR * radius) ** 2)
    outward = (points - c) / np.hypot(*(points - c).T)[:, None]  # each point's radial direction
    n_coef = 3  # square, slope, value at the bench (np.vander's order)
    stepped = STEP_KINDS[step] if step else ()
    at_bench = [STEP_PRIOR if t in stepped else AT_BENCH_PRIOR for t in HELD_TERMS]
    prior = np.concatenate([[SQUARE_PRIOR * SLOPE_PRIOR[t], SLOPE_PRIOR[t], b] for t, b in zip(HELD_TERMS, at_bench)])
    # the step's share of the parameters (the stepped offsets at the bench): the drift since the bench leaves it out
    step_share = np.zeros(k_pos + prior.size, bool)
    step_share[[k_pos + j * n_coef + n_coef - 1 for j, t in enumerate(HELD_TERMS) if t in stepped]] = True

    def field(p: np.ndarray, theta: np.ndarray, temp_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where the field shows bench angle θ at a temperature: S⁻¹ of the bench point about the bench centre
        (Drift.inverse), turned by the rotation of both axes, moved by the offsets."""
        powers = np.vander((np.asarray(temp_c, float) - locus.temp_c) / 10.0, n_coef)
        coef = p[k_pos:].reshape(len(HELD_TERMS), n_coef)
        term = {name: powers @ coef[j] for j, name in enumerate(HELD_TERMS)}
        ld, lq = locus.points(theta)
        s11 = np.exp(term["common"] - term["imbalance"])
        s22 = np.exp(term["common"] + term["imbalance"])
        ud, uq = ld - c[0], lq - c[1]
        vd, vq = ud / s11, uq / s22 - 2 * term["axis"] * ud / s11  # S = [[s11, 0], [2·axis·s22, s22]], inverted
        cz, sz = np.cos(term["zero"]), np.sin(term["zero"])
        return c[0] + radius * term["offset_d"] + cz * vd - sz * vq, c[1] + radius * term[
            "offset_q"
        ] + sz * vd + cz * vq

    scale = np.ones(2)  # the errors' scale across and along the circle
    keep = np.ones(len(obs), bool)  # points not (yet) found to be outliers

    def residuals(p: np.ndarray) -> np.ndarray:
        fd, fq = field(p, p[:k_pos][position], temps)
        ed, eq = points[:, 0] - fd, points[:, 1] - fq
        across = keep * (ed * outward[:, 0] + eq * outward[:, 1]) / (sd * scale[0])
        along = keep * (eq * outward[:, 0] - ed * outward[:, 1]) / (sd * scale[1])
        # each θ_k held loosely to where it started (a radian): a position whose points were all left out keeps a
        # defined column, and no measured position notices it
        return np.concatenate([across, along, p[k_pos:] / prior, p[:k_pos] - theta0])

    def jacobian(p: np.ndarray, r: np.ndarray) -> np.ndarray:
        return np.column_stack([(residuals(p + np.eye(p.size)[j] * steps[j]) - r) / steps[j] for j in range(p.size)])

    theta0 = np.array([circular_mean(first[position == k]) for k in range(k_pos)])
    params = np.concatenate([theta0, np.zeros(prior.size)])
    steps = np.concatenate([np.full(k_pos, 1e-6), np.full(prior.size, 1e-7)])
    # fit; scale each direction's errors by its misfit; leave out points beyond OUTLIER_SIGMAS of it (a bin where
    # two positions a fraction of a degree apart mix, or a move's stops); fit again
    for attempt in range(5):
        for _ in range(iterations):
            r = residuals(params)
            delta, *_ = np.linalg.lstsq(jacobian(params, r), -r, rcond=None)
            params = params + delta
            if np.max(np.abs(delta)) < 1e-10:
                break
        r = residuals(params)
        if not np.all(np.isfinite(r)):
            return None
        dof = max(2 * int(keep.sum()) - k_pos, 2)  # the priors stand for the terms' own degrees of freedom
        chi2 = np.array([np.sum(r[: len(obs)] ** 2), np.sum(r[len(obs) : 2 * len(obs)] ** 2)]) / (dof / 2)
        scale = scale * np.sqrt(np.maximum(chi2, 1.0))
        worst = np.maximum(
            np.abs(r[: len(obs)]) / np.sqrt(np.maximum(chi2[0], 1.0)),
            np.abs(r[len(obs) : 2 * len(obs)]) / np.sqrt(np.maximum(chi2[1], 1.0)),
        )
        out = keep & (worst > OUTLIER_SIGMAS)
        if not out.any():
            break
        if attempt == 4:
            return None  # still leaving points out after four rounds: no one curve holds these positions
        keep &= ~out
    used = [
        k for k in range(k_pos) if np.sum(keep & (position == k)) >= 2 and np.ptp(temps[keep & (position == k)]) > 0
    ]
    if len(used) < need:
        return None
    failed = "a gap" if _largest_gap(params[used]) > MAX_GAP_RAD else "along" if scale[1] > MAX_ALONG_SCALE else ""
    seen = len(used)
    r = residuals(params)
    jac = jacobian(params, r)
    try:
        cov = np.linalg.inv(jac.T @ jac)
    except np.linalg.LinAlgError:
        return None
    chi2_dof = float(np.sum(r[: 2 * len(obs)] ** 2) / dof)
    # to DriftModel's form: polynomials in kelvin from the bench, highest power first
    to_kelvin = 10.0 ** -np.arange(n_coef - 1, -1, -1)
    models = {}
    for j, name in enumerate(HELD_TERMS):
        sl = slice(k_pos + j * n_coef, k_pos + (j + 1) * n_coef)
        models[name] = TermModel(
            coef=params[sl] * to_kelvin, cov=cov[sl, sl] * np.outer(to_kelvin, to_kelvin), bench_c=locus.temp_c
        )

    def along(p: np.ndarray, temp_c: float, theta: np.ndarray | None = None) -> np.ndarray:
        """The angle drift (rad) at a temperature at each position (or at the bench angles given): the field
        point's turn from its bench point."""
        theta = p[:k_pos] if theta is None else theta
        fd, fq = field(p, theta, np.full(theta.size, temp_c))
        ld, lq = locus.points(theta)
        return np.angle((fd - c[0] + 1j * (fq - c[1])) / (ld - c[0] + 1j * (lq - c[1])))

    misfit = np.column_stack([r[: len(obs)] * scale[0], r[len(obs) : 2 * len(obs)] * scale[1]])
    misfit[~keep] = np.nan  # left out
    return HeldDrift(
        model=DriftModel(terms=models, temps=np.array([*temps, locus.temp_c])),
        theta=params[:k_pos],
        position_temps=[temps[keep & (position == k)].tolist() for k in used],
        positions=int(seen),
        points=len(obs),
        chi2_dof=chi2_dof,
        misfit=misfit,
        scale=scale,
        _along=along,
        _params=params,
        _step_share=step_share,
        step=step,
        _cov=cov,
        failed=failed,
    )


def _largest_gap(angles: np.ndarray) -> float:
    """The widest arc (rad) between neighbouring angles around the circle."""
    ordered = np.sort(np.remainder(angles, 2 * np.pi))
    return float(np.max(np.diff(ordered, append=ordered[0] + 2 * np.pi)))


def _positions(angles: np.ndarray) -> np.ndarray:
    """Each held point's position: points within SAME_POSITION_RAD of the one before along the circle are one."""
    order = np.argsort(angles)
    gaps = np.remainder(np.diff(angles[order], append=angles[order[0]] + 2 * np.pi), 2 * np.pi) > SAME_POSITION_RAD
    # a position's points start after a gap; the circle's wrap joins the last run to the first when no gap is there
    label = np.concatenate([[0], np.cumsum(gaps[:-1])])
    if not gaps[-1] and label[-1] > 0:
        label[label == label[-1]] = 0
    out = np.empty(angles.size, int)
    out[order] = label
    _, out = np.unique(out, return_inverse=True)
    return out
