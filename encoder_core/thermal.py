"""The hall die's temperature: a first-order lag of the sensor that reports it.

The drift of gains, offsets and axes follows the die, but a drive reports the temperature of a sensor beside
it, which the die follows with a time constant τ (30-600 s on the drives `encoder_fleet/fieldsim.py` draws,
from the board's thermal mass). Read against the reported temperature, every drift has a loop: warming, the
die is cooler than reported; cooling, warmer. A band's statistics mix both, and a set applied at the reported
temperature is off by its drift's slope times τ times the rate, in opposite senses on the way up and down.

- `DieTemperature` (agent): the die estimate, sample by sample, carried across windows; the agent corrects the
  angle and writes its windows' temperatures with it, so the refit fits drift against the die.
- `LagEstimate` (service): τ from the windows' amplitude. The channels' common gain moves ~0.1 %/K with the
  die, the largest temperature effect there is, and every sample sees it, whatever the angle. For each τ of a
  grid, the windows' temperature ramps (mean and rate, one window after another) are lagged by τ exactly, and
  the log amplitude is fitted on the die temperature that gives (a + b·x + c·x² + e·t, t drive days for aging);
  τ is where that fit's misfit is least. (A first try, amplitude on temperature and rate, read the lag as
  τ·rate: load bumps change the rate faster than the die follows, and it found 0.6 τ on fieldsim's drives.)
  A drive that holds positions shows no ellipse and no amplitude: there each held position's radius, which the
  common gain moves alike, is fitted the same way on the same die path, one curve per position (`tau_of` sums
  their misfits; DeviceMonitor.held_lag).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

BENCH_C = 20.0  # the regression's temperature origin (the factory bench)
MAX_LAG_S = 1800.0  # a boardmate sensor half an hour behind is not a lag but a broken sensor
MIN_WINDOWS = 60  # before this many windows ...
MIN_HOURS = 6.0  # ... and this much drive time the estimate is not used
MIN_SPAN_C = 10.0  # temperature span the windows must cover: the gain slope must be measured first
MEMORY_S = 2 * 86400.0  # windows older than this (drive time) weigh e times less
SIGMAS = 3.0  # a new τ is sent when it is this many standard errors from the one the drive runs ...
# ... and at least this far: a minute's lag at a cycle's 10 °C/h is 0.17 °C, a few millidegrees of angle at most,
# while the project's own simulator (no lag at all) showed a 32 ± 2 s estimate for an hour on one drive (the
# amplitude's temperature curve is not exactly a square there: misfit, not lag)
MIN_CHANGE_S = 60.0


def first_order_lag(t: np.ndarray, x: np.ndarray, tau_s: float, y0: float | None = None) -> np.ndarray:
    """y' = (x - y)/tau, exact for piecewise-constant x between samples. tau <= 0 returns x."""
    x = np.asarray(x, dtype=float)
    if tau_s <= 0 or x.size == 0:
        return x.copy()
    t = np.asarray(t, dtype=float)
    y_start = x[0] if y0 is None else y0
    dt = np.diff(t, prepend=t[0])
    if np.allclose(dt[1:], dt[1] if dt.size > 1 else 0.0):
        a = np.exp(-(dt[1] if dt.size > 1 else 0.0) / tau_s)
        # y[i] = a*y[i-1] + (1-a)*x[i-1]: the input held over the step that ends at sample i
        x_prev = np.concatenate(([y_start], x[:-1]))
        from scipy.signal import lfilter  # here, not at the top: importing scipy.signal costs every process ~1.3 s

        y, _ = lfilter([1 - a], [1, -a], x_prev[1:], zi=[a * y_start])
        return np.concatenate(([y_start], y))
    # an irregular clock: y[i] = a_i·y[i-1] + (1 - a_i)·x[i-1] with a_i = e^(-dt_i/τ), whose products telescope
    # to e^(-(t_i - t_0)/τ): in closed form, block by block (50 τ at most, so the exponentials stay finite)
    y = np.empty_like(x)
    y[0] = y_prev = y_start
    start = 0
    while start < x.size - 1:
        end = int(np.searchsorted(t, t[start] + 50 * tau_s, side="right")) - 1
        end = min(max(end, start + 1), x.size - 1)
        grow = np.exp(np.minimum((t[start : end + 1] - t[start]) / tau_s, 600.0))  # e^((t_i - t_start)/τ)
        gain = (1 - grow[:-1] / grow[1:]) * x[start:end] * grow[1:]  # (1 - a_i)·x[i-1]·e^((t_i - t_start)/τ)
        y[start + 1 : end + 1] = (y_prev + np.cumsum(gain)) / grow[1:]
        y_prev, start = y[end], end
    return y


def reported_temp(die_c: float, lag_s: float, die_rate_c_per_s: float) -> float:
    """The temperature the drive reported, from a window written at a die lag (its mean die estimate and that
    estimate's rate): a first-order lag's die follows T = die + τ·d(die)/dt."""
    return die_c + lag_s * die_rate_c_per_s


class DieTemperature:
    """The agent's die estimate: the reported temperature lagged by τ, continued from the last sample it saw
    (a window's first samples follow from the window before). Non-finite readings pass through unchanged and
    do not move the estimate."""

    def __init__(self) -> None:
        self.last: tuple[float, float, float] | None = None  # (t, reported, die) of the last finite sample

    def __call__(self, t: np.ndarray, temp: np.ndarray, tau_s: float) -> np.ndarray:
        temp = np.asarray(temp, dtype=float)
        out = temp.copy()
        ok = np.isfinite(temp) & np.isfinite(t)
        if not ok.any():
            return out
        tk, xk = np.asarray(t, float)[ok], temp[ok]
        if self.last is None or tk[0] <= self.last[0]:  # the first samples, or a clock that ran back: start here
            die = first_order_lag(tk, xk, tau_s)
        else:
            t0, x0, y0 = self.last
            die = first_order_lag(np.concatenate(([t0], tk)), np.concatenate(([x0], xk)), tau_s, y0=y0)[1:]
        out[ok] = die
        self.last = (float(tk[-1]), float(xk[-1]), float(die[-1]))
        return out


LAG_GRID_S = (0, 20, 40, 60, 90, 120, 160, 210, 270, 340, 420, 520, 640, 800, 1000, 1250, 1500, 1800)
N_TERMS = 4  # 1, x, x², t


def ramp_lag(y0: np.ndarray, start_c: float, rate_c_per_s: float, length_s: float, tau_s: np.ndarray):
    """A first-order lag of time constants tau_s (array) starting at y0 (one per τ) and driven by the ramp
    start_c + rate·t over length_s: (the lag's mean over the ramp, its value at the end)."""
    tau = np.maximum(np.asarray(tau_s, float), 1e-9)
    u = length_s / tau
    decay = np.exp(-u)
    # y(t) = T(t) - r·τ + (y0 - T0 + r·τ)·e^{-t/τ}
    lead = y0 - start_c + rate_c_per_s * tau
    with np.errstate(over="ignore", invalid="ignore"):
        frac = np.where(u > 1e-9, (1 - decay) / np.maximum(u, 1e-300), 1.0)  # mean of e^{-t/τ} over the window
    mean = start_c + rate_c_per_s * length_s / 2 - rate_c_per_s * tau + lead * frac
    end = start_c + rate_c_per_s * length_s - rate_c_per_s * tau + lead * decay
    return mean, end


@dataclass
class LagEstimate:
    """τ by profile least squares over a grid: for each candidate τ the windows' mean die temperature (their
    temperature ramps, one after another, lagged by τ) and an exponentially weighted (drive time) fit of the
    log amplitude on it (a + b·x + c·x² + e·t); τ is where the misfit is least, its error where the misfit grows
    by one (after scaling it to one per window)."""

    die: np.ndarray | None = None  # per candidate τ: the die at the end of the last window
    last_end: tuple | None = None  # (t, reported temperature) at the end of the last window
    sxx: np.ndarray = field(default_factory=lambda: np.zeros((len(LAG_GRID_S), N_TERMS, N_TERMS)))
    sxy: np.ndarray = field(default_factory=lambda: np.zeros((len(LAG_GRID_S), N_TERMS)))
    syy: float = 0.0
    sw: float = 0.0  # the windows' count, decayed
    n: int = 0
    t0: float | None = None
    x_min: float = 1e9
    x_max: float = -1e9
    t_fit: float | None = None  # the last fitted window's end

    def add(
        self,
        *,
        start: float,
        end: float,
        temp_c: float,
        rate_c_per_s: float,
        lag_used_s: float,
        log_amp: float | None,
        sd: float | None,
    ) -> np.ndarray | None:
        """One window, in drive order: its start and end (drive s), mean temperature and rate as the agent wrote
        them (lagged by lag_used_s, the τ of the set it ran: undone here as for a ramp), and its log amplitude
        with that value's standard error (None: the window still moves the die, but is not fitted). Returns the
        window's mean die temperature per candidate τ (None for a window out of order or not finite), which
        `fit` takes for another amplitude of the same window."""
        if not all(math.isfinite(v) for v in (start, end, temp_c, rate_c_per_s, lag_used_s)) or end < start:
            return None
        if self.last_end is not None and end <= self.last_end[0]:
            return None  # out of order: the die's path is drawn forwards only
        grid = np.asarray(LAG_GRID_S, float)
        length = end - start
        reported_mean = reported_temp(temp_c, lag_used_s, rate_c_per_s)
        start_c = reported_mean - rate_c_per_s * length / 2
        if self.die is None:
            y0 = np.full(grid.size, start_c)
        else:
            t_prev, temp_prev = self.last_end
            # a gap between windows: the die relaxes towards the last temperature reported
            gap = max(start - t_prev, 0.0)
            y0 = temp_prev + (self.die - temp_prev) * np.exp(-gap / np.maximum(grid, 1e-9))
        mean, y_end = ramp_lag(y0, start_c, rate_c_per_s, length, grid)
        self.die, self.last_end = y_end, (end, start_c + rate_c_per_s * length)
        self.fit(mean, end, log_amp, sd)
        return mean

    def fit(self, mean: np.ndarray, end: float, log_amp: float | None, sd: float | None) -> None:
        """One window's log amplitude against its mean die temperature per candidate τ (from `add`), weighed by its
        standard error; nothing when either is missing."""
        if log_amp is None or sd is None or not (math.isfinite(log_amp) and math.isfinite(sd) and sd > 0):
            return
        if self.t0 is None:
            self.t0 = end
        f = 1.0 if self.t_fit is None else math.exp(-max(end - self.t_fit, 0.0) / MEMORY_S)
        self.t_fit = end
        x = mean - BENCH_C
        rows = np.column_stack([np.ones_like(x), x, x * x, np.full_like(x, (end - self.t0) / 86400.0)])
        w = 1.0 / sd**2
        self.sxx = self.sxx * f + w * rows[:, :, None] * rows[:, None, :]
        self.sxy = self.sxy * f + w * rows * log_amp
        self.syy = self.syy * f + w * log_amp * log_amp
        self.sw = self.sw * f + 1.0
        self.n += 1
        self.x_min, self.x_max = min(self.x_min, float(x[0])), max(self.x_max, float(x[0]))

    def restart(self) -> None:
        """Forget the fit (a gain step moved the amplitude: windows from before it would read as a lag); the
        die's path goes on."""
        die, last_end = self.die, self.last_end
        self.__init__()
        self.die, self.last_end = die, last_end

    def profile(self) -> np.ndarray | None:
        """Residual sum of squares per candidate τ (None before the windows can measure it)."""
        if self.n < MIN_WINDOWS or self.x_max - self.x_min < MIN_SPAN_C or self.t_fit - self.t0 < MIN_HOURS * 3600.0:
            return None  # (n > 0: t0 and t_fit are set)
        a, b = self.sxx, self.sxy
        try:
            coef = np.linalg.solve(a, b[..., None])[..., 0]
        except np.linalg.LinAlgError:
            return None
        rss = self.syy - np.einsum("gk,gk->g", coef, b)
        return rss if np.all(np.isfinite(rss)) else None

    def tau(self) -> tuple[float, float] | None:
        """(τ s, its standard error) where the windows measure it, else None."""
        return tau_of([self])

    def to_dict(self) -> dict:
        """Plain JSON (the drift monitor's saved state)."""
        out = {k: getattr(self, k) for k in self.__dataclass_fields__}
        return {k: v.tolist() if isinstance(v, np.ndarray) else v for k, v in out.items()}

    @classmethod
    def from_dict(cls, d: dict) -> LagEstimate:
        d = dict(d)
        for name in ("die", "sxx", "sxy"):
            if d.get(name) is not None:
                d[name] = np.asarray(d[name], float)
        if d.get("last_end") is not None:
            d["last_end"] = tuple(d["last_end"])
        return cls(**d)


def tau_of(estimates: list[LagEstimate]) -> tuple[float, float] | None:
    """(τ s, its standard error) from the summed misfit of estimates that share one die (each its own amplitude
    curve: the positions a drive holds each have their radius), where any measures it; else None."""
    profiles = [(e.profile(), e.sw) for e in estimates]
    profiles = [(rss, sw) for rss, sw in profiles if rss is not None]
    if not profiles:
        return None
    rss = np.sum([p for p, _ in profiles], axis=0)
    dof = sum(max(sw - N_TERMS - 1, 1.0) for _, sw in profiles)
    grid = np.asarray(LAG_GRID_S, float)
    k = int(np.argmin(rss))
    scale = max(rss[k] / dof, 1e-300)  # misfit per window: one
    chi2 = rss / scale
    if k in (0, grid.size - 1):  # at the grid's edge: the edge, and how far the misfit allows
        inside = grid[chi2 - chi2[k] < 1.0]
        return float(grid[k]), float(max(inside.max() - inside.min(), grid[1] - grid[0]))
    # a parabola through the minimum and its neighbours
    x0, x1, x2 = grid[k - 1 : k + 2]
    y0, y1, y2 = chi2[k - 1 : k + 2]
    denom = (x0 - x1) * (x0 - x2) * (x1 - x2)
    curv = (x2 * (y1 - y0) + x1 * (y0 - y2) + x0 * (y2 - y1)) / denom
    lin = (x2 * x2 * (y0 - y1) + x1 * x1 * (y2 - y0) + x0 * x0 * (y1 - y2)) / denom
    if not curv > 0:
        return None
    best = float(np.clip(-lin / (2 * curv), x0, x2))
    return best, float(1.0 / math.sqrt(curv))


def lag_to_send(estimate: tuple[float, float] | None, running_s: float) -> float | None:
    """The τ a new set should carry, when the estimate stands clear of the one the drive runs; else None."""
    if estimate is None:
        return None
    tau, se = estimate
    tau = min(max(tau, 0.0), MAX_LAG_S)
    if abs(tau - running_s) > max(SIGMAS * se, MIN_CHANGE_S) and se < MAX_LAG_S / 10:
        return round(tau, 1)
    return None
