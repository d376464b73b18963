"""Additive window statistics: what an agent ships instead of samples.

Channels are normalised first (x = (d - center_d)/scale, same for q) because raw 12-bit counts
to the 4th power lose precision in a sum. A window holds

- sums of the 15 monomials x^i·y^j with i + j <= 4: the scatter matrix of a conic fit;
- per raw-angle bin (64 bins of atan2(y, x)): count, Σx, Σy, Σx², Σxy, Σy², which give the
  sample density along the circle and the radius of any later affine correction per bin;
- temperature count, Σ, Σ², min, max.

Two windows with the same normalisation merge by addition, in any order.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .correction import BandedCorrection
from .physics import ADC_MAX, REFERENCE_TEMP_C
from .samples import InputError, Samples

MONOMIALS: tuple[tuple[int, int], ...] = tuple((i, k - i) for k in range(5) for i in range(k, -1, -1))
N_BINS = 64
BIN_COLUMNS = ("count", "sx", "sy", "sxx", "sxy", "syy")


@dataclass
class WindowStats:
    scale: float
    center_d: float = 0.0
    center_q: float = 0.0
    moments: np.ndarray = field(default_factory=lambda: np.zeros(len(MONOMIALS)))
    bins: np.ndarray = field(default_factory=lambda: np.zeros((N_BINS, len(BIN_COLUMNS))))
    temp_n: int = 0
    temp_sum: float = 0.0
    temp_sq_sum: float = 0.0
    temp_min: float = float("inf")
    temp_max: float = float("-inf")
    rejected: int = 0  # samples kept out: clipped, non-finite or implausible radius
    # Σ over merged windows of the window's mean temperature × its count in each angle bin: when in a band each
    # angle was seen (a drive that reverses or dwells sees some angles only while the band is warm). None for
    # one window, where it follows from temp_mean and the counts; not on the wire, kept by the store's sums.
    bin_temp: np.ndarray | None = None

    @property
    def n(self) -> int:
        return int(round(self.moments[0]))

    @property
    def temp_mean(self) -> float:
        return self.temp_sum / self.temp_n if self.temp_n else float("nan")

    def bin_temps(self) -> np.ndarray:
        """Σ window mean temperature × count per angle bin (see bin_temp)."""
        if self.bin_temp is not None:
            return self.bin_temp
        return (self.temp_mean if self.temp_n else 0.0) * self.bins[:, 0]

    def normalise(self, d, q) -> tuple[np.ndarray, np.ndarray]:
        return (np.asarray(d, float) - self.center_d) / self.scale, (np.asarray(q, float) - self.center_q) / self.scale

    def add(self, d, q, temp_c=None) -> WindowStats:
        """Accumulate samples in place; returns self."""
        x, y = self.normalise(d, q)
        powers_x = [np.ones_like(x), x, x * x, x * x * x, (x * x) ** 2]
        powers_y = [np.ones_like(y), y, y * y, y * y * y, (y * y) ** 2]
        self.moments = self.moments + np.array([np.dot(powers_x[i], powers_y[j]) for i, j in MONOMIALS])
        idx = angle_bin(x, y)
        # per-bin sums by bincount, which adds in sample order as np.add.at did, at a tenth of its cost
        cols = (x, y, powers_x[2], x * y, powers_y[2])  # BIN_COLUMNS after the count
        binned = np.column_stack(
            [np.bincount(idx, minlength=N_BINS)] + [np.bincount(idx, weights=c, minlength=N_BINS) for c in cols]
        )
        self.bins = self.bins + binned
        if temp_c is not None:
            temp = np.asarray(temp_c, float)
            if temp.size:
                self.temp_n += int(temp.size)
                self.temp_sum += float(temp.sum())
                self.temp_sq_sum += float(np.dot(temp, temp))
                self.temp_min = min(self.temp_min, float(temp.min()))
                self.temp_max = max(self.temp_max, float(temp.max()))
        return self

    def same_frame(self, other: WindowStats) -> bool:
        """Both normalised alike (same scale and centre): what merge and subtract require."""
        return (self.scale, self.center_d, self.center_q) == (other.scale, other.center_d, other.center_q)

    def merge(self, other: WindowStats) -> WindowStats:
        """A new statistics object holding both: addition, so order does not matter."""
        if not self.same_frame(other):
            raise InputError(
                "cannot merge window statistics with different normalisation "
                f"({self.scale}, {self.center_d}, {self.center_q}) vs "
                f"({other.scale}, {other.center_d}, {other.center_q})"
            )
        return WindowStats(
            scale=self.scale,
            center_d=self.center_d,
            center_q=self.center_q,
            moments=self.moments + other.moments,
            bins=self.bins + other.bins,
            temp_n=self.temp_n + other.temp_n,
            temp_sum=self.temp_sum + other.temp_sum,
            temp_sq_sum=self.temp_sq_sum + other.temp_sq_sum,
            temp_min=min(self.temp_min, other.temp_min),
            temp_max=max(self.temp_max, other.temp_max),
            rejected=self.rejected + other.rejected,
            bin_temp=self.bin_temps() + other.bin_temps(),
        )

    def subtract(self, other: WindowStats) -> WindowStats:
        """Take a window back out of a sum (merge's inverse for every sum; min and max stay those seen)."""
        if not self.same_frame(other):
            raise InputError("cannot subtract window statistics with different normalisation")
        return WindowStats(
            scale=self.scale,
            center_d=self.center_d,
            center_q=self.center_q,
            moments=self.moments - other.moments,
            bins=self.bins - other.bins,
            temp_n=self.temp_n - other.temp_n,
            temp_sum=self.temp_sum - other.temp_sum,
            temp_sq_sum=self.temp_sq_sum - other.temp_sq_sum,
            temp_min=self.temp_min,
            temp_max=self.temp_max,
            rejected=self.rejected - other.rejected,
            bin_temp=self.bin_temps() - other.bin_temps(),
        )

    def moment(self, i: int, j: int) -> float:
        return float(self.moments[MONOMIALS.index((i, j))])

    def to_dict(self) -> dict:
        finite = self.temp_n > 0
        return {
            "scale": self.scale,
            "center_d": self.center_d,
            "center_q": self.center_q,
            "moments": self.moments.tolist(),
            "bins": self.bins.tolist(),
            "temp_n": self.temp_n,
            "temp_sum": self.temp_sum,
            "temp_sq_sum": self.temp_sq_sum,
            "temp_min": self.temp_min if finite else None,
            "temp_max": self.temp_max if finite else None,
            "rejected": self.rejected,
        }

    @classmethod
    def from_dict(cls, data: dict) -> WindowStats:
        moments = np.asarray(data["moments"], dtype=float)
        bins = np.asarray(data["bins"], dtype=float)
        if moments.shape != (len(MONOMIALS),):
            raise InputError(f"moments must have {len(MONOMIALS)} values, got shape {moments.shape}")
        if bins.shape != (N_BINS, len(BIN_COLUMNS)):
            raise InputError(f"bins must be {N_BINS}x{len(BIN_COLUMNS)}, got shape {bins.shape}")
        if not (np.all(np.isfinite(moments)) and np.all(np.isfinite(bins))):
            raise InputError("window statistics contain a non-finite value")
        return cls(
            scale=float(data["scale"]),
            center_d=float(data["center_d"]),
            center_q=float(data["center_q"]),
            moments=moments,
            bins=bins,
            temp_n=int(data["temp_n"]),
            temp_sum=float(data["temp_sum"]),
            temp_sq_sum=float(data["temp_sq_sum"]),
            temp_min=float("inf") if data.get("temp_min") is None else float(data["temp_min"]),
            temp_max=float("-inf") if data.get("temp_max") is None else float(data["temp_max"]),
            rejected=int(data.get("rejected", 0)),
        )


def angle_bin(x, y) -> np.ndarray:
    theta = np.arctan2(y, x) % (2 * np.pi)
    return np.minimum((theta * (N_BINS / (2 * np.pi))).astype(int), N_BINS - 1)


def bin_edges() -> np.ndarray:
    return np.arange(N_BINS + 1) * (2 * np.pi / N_BINS)


def plausible_mask(d, q, *, center=(0.0, 0.0), tolerance: float = 0.12) -> np.ndarray:
    """Finite samples whose radius is within ±tolerance of the block's median radius.

    An impulse on one hall moves the point off the circle; the fits' 4th-order sums must not see it.
    """
    d = np.asarray(d, float)
    q = np.asarray(q, float)
    ok = np.isfinite(d) & np.isfinite(q)
    r = np.hypot(d - center[0], q - center[1])
    if ok.sum() == 0:
        return ok
    med = np.median(r[ok])
    return ok & (np.abs(r - med) <= tolerance * med)


REJECT_REASONS = ("non_finite", "clipped", "outlier")  # each rejected sample counts once, under the first


def pinned_mask(d, q, *, min_count: int = 4) -> np.ndarray:
    """Samples of a channel pinned at its block's extreme value while the other channel moves: clipping
    recognised from the data (diagnose's rule), so a rail of unknown value (a replay in counts of any
    range, a converter whose reference sagged) is found as well as 0 and 4095."""
    d = np.asarray(d, float)
    q = np.asarray(q, float)
    pinned = np.zeros(d.size, bool)
    ok = np.isfinite(d) & np.isfinite(q)
    if ok.sum() < 8:
        return pinned
    for chan, other in ((d, q), (q, d)):
        span_other = np.ptp(other[ok])
        values = chan[ok]
        for value in (values.max(), values.min()):
            at = ok & (chan == value)
            count = int(at.sum())
            if count < max(min_count, 0.0005 * d.size):
                continue
            # a rail piles samples up at one value; a quantised peak spreads them over its neighbours
            rest = values[values != value]
            if rest.size:
                nearest = rest.max() if value == values.max() else rest.min()
                if count < 3 * int((values == nearest).sum()):
                    continue
            moving = other[at]
            if np.unique(moving).size >= min(5, count) and np.ptp(moving) > 0.01 * span_other:
                pinned |= at
    return pinned


def rejection_masks(samples: Samples) -> dict[str, np.ndarray]:
    """Why samples are kept out of the statistics, one mask per reason of REJECT_REASONS (disjoint). A sample whose
    temperature reads NaN or inf is non_finite too: summed, one such reading made the whole window's temperature
    NaN and the window unsendable."""
    finite = np.isfinite(samples.d) & np.isfinite(samples.q)
    if samples.temp_c is not None:
        finite &= np.isfinite(samples.temp_c)
    clipped = pinned_mask(samples.d, samples.q) & finite
    if samples.halls is not None:
        for hall in samples.halls.values():
            clipped |= finite & ~((hall > 0) & (hall < ADC_MAX))
    outlier = ~plausible_mask(samples.d, samples.q) & finite & ~clipped
    return {"non_finite": ~finite, "clipped": clipped, "outlier": outlier}


def usable_mask(samples: Samples) -> np.ndarray:
    """Samples that say something about the circle: finite, near it, no channel pinned at a rail."""
    masks = rejection_masks(samples)
    return ~(masks["non_finite"] | masks["clipped"] | masks["outlier"])


def rejected_by_reason(samples: Samples) -> tuple[np.ndarray, dict[str, int]]:
    """The usable mask and the count of rejected samples per reason (the window's rejected_by_reason)."""
    masks = rejection_masks(samples)
    counts = {reason: int(masks[reason].sum()) for reason in REJECT_REASONS}
    return ~(masks["non_finite"] | masks["clipped"] | masks["outlier"]), counts


def block_statistics(samples: Samples, scale: float) -> tuple[WindowStats, dict[str, int]]:
    """What an agent makes of one block: the window's statistics and its rejected samples per reason."""
    keep, counts = rejected_by_reason(samples)
    return window_stats(samples, scale, keep), counts


def window_stats(samples: Samples, scale: float, keep: np.ndarray | None = None) -> WindowStats:
    """The one way statistics are made from samples: the usable ones summed, the others counted as rejected."""
    keep = usable_mask(samples) if keep is None else keep
    stats = WindowStats(scale=scale)
    stats.add(samples.d[keep], samples.q[keep], None if samples.temp_c is None else samples.temp_c[keep])
    stats.rejected = int((~keep).sum())
    return stats


def normalisation_scale(factory: BandedCorrection) -> float:
    """A device's fixed statistics scale (its windows must merge for life): the channel amplitude the
    factory set implies near +20 °C, rounded."""
    ref = min(factory.bands, key=lambda b: abs((b.temp_c or REFERENCE_TEMP_C) - REFERENCE_TEMP_C))
    return float(round(1.0 / abs(ref.w1)))
