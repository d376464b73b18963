"""An independent field simulator: drives whose physics the refit code did not write.

Written from the physics (seed 000 eq. 4-5, seed 001 eq. 15) and from what drives in the field do,
without reading encoder_core/simulator.py or the simulated drive in edge_agent/sources.py, so that
the fleet is judged on a model its own author did not tune it to.

The shaft angle θ turns a one-pole magnet. Its field at the hall die, as a complex number, is the
fundamental plus harmonics that come from the magnet's shape and the geometry (seed 001 eq. 15,
with both rotation senses), the same at every temperature:

    B(θ) = e^{jθ} + Σ_{n=2..7} P_n·e^{jnθ} + Σ_{n=1..7} N_n·e^{-jnθ}

Each channel measures B along its own sensitivity axis, with its own gain and offset (seed 000
eq. 4-5), all functions of the die temperature (linear plus a small quadratic term) and of the
drive's age (a linear trend plus a random walk), and planted events (steps):

    d = g_d·(cos φ_d·Re B + sin φ_d·Im B) + o_d
    q = g_q·(cos φ_q·Im B − sin φ_q·Re B) + o_q

φ_d and φ_q are the axes' misalignments (their difference is seed 001's phase error β). The die
lags the temperature sensor that reports it (first order). Then noise and 12-bit quantisation.

Shaft motion comes in the regimes agents see: `even` (turning at speeds that change now and then,
incommensurate with the sample clock), `random` (an independent angle per sample), `dwell` (a servo
holding a few positions, moving between them) and `reverse` (back and forth over an arc or turns).
The bench sweep (`bench_sweep`) is the end-of-line calibration: +20 °C, 3600 reference positions.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from encoder_core.samples import Samples

DAY_S = 86400.0
BENCH_TEMP_C = 20.0
REGIMES = ("even", "random", "dwell", "reverse")


@dataclass
class Event:
    """A step at time t_s: offsets (counts), differential gain (fraction of q's gain), q-axis angle (rad)."""

    t_s: float
    kind: str
    d_offset: float = 0.0
    q_offset: float = 0.0
    q_gain: float = 0.0
    q_axis: float = 0.0


@dataclass
class DrivePhysics:
    amplitude: float = 1500.0  # counts of d/q for the fundamental at +20 °C
    pos_harmonics: dict[int, complex] = field(default_factory=dict)  # n -> P_n (relative to the fundamental)
    neg_harmonics: dict[int, complex] = field(default_factory=dict)  # n -> N_n
    gain: tuple[float, float] = (1.0, 1.0)  # relative gains of d, q at +20 °C
    gain_tc: tuple[float, float] = (-1e-3, -1e-3)  # 1/K
    gain_tc2: tuple[float, float] = (0.0, 0.0)  # 1/K²
    offset: tuple[float, float] = (0.0, 0.0)  # counts at +20 °C
    offset_tc: tuple[float, float] = (0.0, 0.0)  # counts/K
    offset_tc2: tuple[float, float] = (0.0, 0.0)  # counts/K²
    axis: tuple[float, float] = (0.0, 0.0)  # φ_d, φ_q at +20 °C, rad
    axis_tc: tuple[float, float] = (0.0, 0.0)  # rad/K
    zero_rad: float = 0.0  # the magnet's angle on the shaft: machine zero vs field zero
    die_lag_s: float = 120.0
    offset_aging: tuple[float, float] = (0.0, 0.0)  # counts/day
    gain_aging: tuple[float, float] = (0.0, 0.0)  # 1/day
    walk_counts: float = 0.0  # offset random walk, counts/sqrt(day)
    walk_seed: int = 0
    events: list[Event] = field(default_factory=list)
    noise_counts: float = 1.5
    quantise: bool = True

    def field_xy(self, theta) -> tuple[np.ndarray, np.ndarray]:
        """Re B, Im B at magnet angle θ (rad)."""
        th = np.asarray(theta, float)
        z = np.cos(th) + 1j * np.sin(th)
        b = z.copy()
        power = z.copy()  # z^n by repeated products: cheaper than a trig call per order
        for n in range(2, max([*self.pos_harmonics, *self.neg_harmonics, 1]) + 1):
            power *= z
            if n in self.pos_harmonics:
                b += self.pos_harmonics[n] * power
            if n in self.neg_harmonics:
                b += self.neg_harmonics[n] * np.conj(power)
        if 1 in self.neg_harmonics:
            b += self.neg_harmonics[1] * np.conj(z)
        return b.real, b.imag

    def _walk(self, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Offset random walk, the same path every call (hourly knots, linear between)."""
        t = np.asarray(t_s, float)
        if self.walk_counts <= 0 or t.size == 0:
            return np.zeros_like(t), np.zeros_like(t)
        hours = int(np.ceil(max(float(t.max()), 0.0) / 3600.0)) + 2
        steps = np.random.default_rng(self.walk_seed).normal(size=(hours, 2)) * self.walk_counts / np.sqrt(24.0)
        knots = np.vstack([np.zeros(2), np.cumsum(steps, axis=0)])
        grid = np.arange(hours + 1) * 3600.0
        return np.interp(t, grid, knots[:, 0]), np.interp(t, grid, knots[:, 1])

    def state(self, die_c, t_s) -> dict[str, np.ndarray]:
        """Gains, offsets and axes at die temperature die_c and drive time t_s (arrays broadcast)."""
        dt = np.asarray(die_c, float) - BENCH_TEMP_C
        t = np.asarray(t_s, float)
        days = t / DAY_S
        walk = self._walk(t)
        out = {}
        for i, ax in enumerate("dq"):
            g = self.gain[i] * (1 + self.gain_tc[i] * dt + self.gain_tc2[i] * dt * dt + self.gain_aging[i] * days)
            o = self.offset[i] + self.offset_tc[i] * dt + self.offset_tc2[i] * dt * dt + self.offset_aging[i] * days
            out[f"g_{ax}"], out[f"o_{ax}"] = g, o + walk[i]
            out[f"phi_{ax}"] = self.axis[i] + self.axis_tc[i] * dt + 0 * t
        for ev in self.events:
            after = t >= ev.t_s
            out["o_d"] = out["o_d"] + after * ev.d_offset
            out["o_q"] = out["o_q"] + after * ev.q_offset
            out["g_q"] = out["g_q"] * (1 + after * ev.q_gain)
            out["phi_q"] = out["phi_q"] + after * ev.q_axis
        return out

    def channels(self, theta, die_c, t_s) -> tuple[np.ndarray, np.ndarray]:
        """Noise-free d, q (counts) at shaft angle θ (machine frame), die temperature and time."""
        bx, by = self.field_xy(np.asarray(theta, float) - self.zero_rad)
        s = self.state(die_c, t_s)
        d = self.amplitude * s["g_d"] * (np.cos(s["phi_d"]) * bx + np.sin(s["phi_d"]) * by) + s["o_d"]
        q = self.amplitude * s["g_q"] * (np.cos(s["phi_q"]) * by - np.sin(s["phi_q"]) * bx) + s["o_q"]
        return d, q

    def measure(self, theta, die_c, t_s, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """What the ADC delivers: channels plus noise, quantised to counts if asked."""
        return self.digitise(*self.channels(theta, die_c, t_s), rng)

    def digitise(self, d, q, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """What the ADC makes of noise-free channels: noise added, quantised to counts if asked."""
        d = d + rng.normal(0.0, self.noise_counts, d.shape)
        q = q + rng.normal(0.0, self.noise_counts, q.shape)
        if self.quantise:
            d, q = np.round(d), np.round(q)
        return d, q

    def clean(self) -> DrivePhysics:
        """The same drive without planted events."""
        return replace(self, events=[])


def _complex(rng: np.random.Generator, amplitude: float) -> complex:
    return complex(amplitude * np.exp(1j * rng.uniform(0, 2 * np.pi)))


def draw_drive(rng: np.random.Generator, *, event: str | None = None, days: float = 3.0) -> DrivePhysics:
    """One production drive: field harmonics from the magnet, channel drifts from the electronics.

    Sizes are typical of hall encoders: a 3rd field harmonic of 0.2-1.2 % (the largest), a
    differential gain tempco of ~1.5e-4/K, offset tempco of ~0.05 counts/K on a 1500-count signal,
    an axis tempco of ~1.5e-5 rad/K per axis, slow aging (~10 counts of offset a year).
    event: None, 'offset_step', 'gain_step', 'axis_step'.
    """
    pos = {3: _complex(rng, rng.uniform(0.002, 0.012)), 2: _complex(rng, rng.uniform(0.0005, 0.004))}
    for n in (4, 5, 6, 7):
        pos[n] = _complex(rng, rng.uniform(0.0, 0.003) / (n - 2))
    neg = {1: _complex(rng, rng.uniform(0.0, 0.006))}
    for n in (2, 3, 4, 5):
        neg[n] = _complex(rng, rng.uniform(0.0, 0.002) / n)
    common_tc = rng.normal(-1.0e-3, 3e-4)
    diff_tc = rng.normal(0.0, 1.5e-4)
    phys = DrivePhysics(
        amplitude=float(rng.uniform(1300, 1700)),
        pos_harmonics=pos,
        neg_harmonics=neg,
        gain=(1.0, float(1 + rng.normal(0, 0.03))),
        gain_tc=(common_tc - diff_tc / 2, common_tc + diff_tc / 2),
        gain_tc2=(float(rng.normal(0, 1e-6)), float(rng.normal(0, 1e-6))),
        offset=(float(rng.normal(0, 15)), float(rng.normal(0, 15))),
        offset_tc=(float(rng.normal(0, 0.05)), float(rng.normal(0, 0.05))),
        offset_tc2=(float(rng.normal(0, 3e-4)), float(rng.normal(0, 3e-4))),
        axis=(float(rng.normal(0, 0.003)), float(rng.normal(0, 0.01))),
        axis_tc=(float(rng.normal(0, 1.5e-5)), float(rng.normal(0, 1.5e-5))),  # no axis is privileged
        zero_rad=float(rng.uniform(-np.pi, np.pi)),
        die_lag_s=float(rng.uniform(30, 600)),
        offset_aging=(float(rng.normal(0, 0.03)), float(rng.normal(0, 0.03))),  # ~10 counts a year
        gain_aging=(float(rng.normal(-1e-5, 3e-6)), float(rng.normal(-1e-5, 3e-6))),  # the magnet: -0.4 %/year
        walk_counts=0.05,
        walk_seed=int(rng.integers(2**31)),
        noise_counts=float(rng.uniform(1.0, 2.5)),
    )
    if event:
        phys.events.append(draw_event(rng, event, days))
    return phys


def draw_event(rng: np.random.Generator, kind: str, days: float) -> Event:
    t = float(rng.uniform(0.3, 0.8) * days * DAY_S)
    sign = rng.choice([-1.0, 1.0])
    if kind == "offset_step":
        axis = rng.integers(2)
        size = sign * rng.uniform(4, 15)
        return Event(t, kind, d_offset=size if axis == 0 else 0.0, q_offset=size if axis == 1 else 0.0)
    if kind == "gain_step":
        return Event(t, kind, q_gain=float(sign * rng.uniform(0.003, 0.01)))
    if kind == "axis_step":
        return Event(t, kind, q_axis=float(sign * rng.uniform(0.002, 0.006)))
    raise ValueError(f"unknown event kind {kind!r}")


# --- temperature ----------------------------------------------------------------------------------


def reported_temperature(t_s, rng: np.random.Generator, *, low: float = -20.0, high: float = 75.0) -> np.ndarray:
    """A daily cycle between low and high with load bumps (heat from the drive's own work) and sensor noise."""
    t = np.asarray(t_s, float)
    if t.size == 0:
        return t.copy()
    grid = np.arange(t.min(), t.max() + 10.0, 5.0)  # temperature is slow: build it on a 5 s grid
    phase = rng.uniform(0, 2 * np.pi)
    mid, amp = (low + high) / 2, (high - low) / 2
    bump_room = 0.12 * (high - low)  # bumps ride on a cycle that leaves them room at the top
    temp = mid - bump_room / 2 + (amp - bump_room / 2) * np.sin(2 * np.pi * grid / DAY_S + phase)
    for _ in range(rng.poisson(6 * max(float(grid[-1] - grid[0]), 1.0) / DAY_S)):
        start = rng.uniform(grid[0], grid[-1])
        size = rng.uniform(0.2, 1.0) * bump_room
        rise, fall, length = rng.uniform(120, 600), rng.uniform(600, 2400), rng.uniform(600, 5400)
        since = np.clip(grid - start, 0.0, None)
        heating = np.minimum(since, length)  # the load runs for `length`, then the drive cools
        cooling = np.clip(since - length, 0.0, None)
        temp = temp + (since > 0) * size * (1 - np.exp(-heating / rise)) * np.exp(-cooling / fall)
    return np.interp(t, grid, temp) + rng.normal(0, 0.05, t.shape)


def lagged(values, t_s, tau_s: float) -> np.ndarray:
    """First-order lag of a sampled signal (the die behind the sensor that reports it)."""
    v = np.asarray(values, float)
    t = np.asarray(t_s, float)
    if v.size == 0 or tau_s <= 0:
        return v.copy()
    # exact for a signal held between samples; steps of any size, no stability limit
    alpha = 1 - np.exp(-np.diff(t, prepend=t[0]) / tau_s)
    out = np.empty_like(v)
    acc = v[0]
    for i in range(v.size):  # a recursive filter: the loop runs once per sample
        acc += alpha[i] * (v[i] - acc)
        out[i] = acc
    return out


def lagged_fast(values, t_s, tau_s: float) -> np.ndarray:
    """The same lag computed on a 10 s grid (cheap for long, fast-sampled runs), read back by interpolation."""
    t = np.asarray(t_s, float)
    if t.size < 2:
        return np.asarray(values, float).copy()
    grid = np.arange(t[0], t[-1] + 10.0, 10.0)
    return np.interp(t, grid, lagged(np.interp(grid, t, values), grid, tau_s))


# --- shaft motion ---------------------------------------------------------------------------------


def sample_times(days: float, rate_hz: float, rng: np.random.Generator) -> np.ndarray:
    """An asynchronous sample clock: nominal period with 1 % jitter."""
    n = int(days * DAY_S * rate_hz)
    period = 1.0 / rate_hz
    return np.arange(n) * period + rng.uniform(-0.01, 0.01, n) * period


def shaft_angle(regime: str, t_s, rng: np.random.Generator) -> np.ndarray:
    """Machine angle (rad) of the shaft at each sample time, for one motion regime."""
    t = np.asarray(t_s, float)
    if regime == "random":
        return rng.uniform(0, 2 * np.pi, t.shape)
    if regime == "even":
        return _even(t, rng)
    if regime == "dwell":
        return _dwell(t, rng)
    if regime == "reverse":
        return _reverse(t, rng)
    raise ValueError(f"unknown motion regime {regime!r} (known: {', '.join(REGIMES)})")


def _segments(t: np.ndarray, rng: np.random.Generator, mean_s: float) -> np.ndarray:
    """Start times of segments of random length covering t."""
    span = float(t[-1] - t[0]) if t.size else 0.0
    lengths = rng.exponential(mean_s, int(span / mean_s * 3) + 10)
    return t[0] + np.concatenate(([0.0], np.cumsum(lengths)))


def _even(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Constant speed per segment (30-3000 rpm, a new set point every ~20 min), plus a slow 0.2 % wander."""
    starts = _segments(t, rng, 1200.0)
    rpm = np.exp(rng.uniform(np.log(30), np.log(3000), starts.size))
    seg = np.searchsorted(starts, t, side="right") - 1
    speed = rpm[seg] * (2 * np.pi / 60) * (1 + 0.002 * np.sin(2 * np.pi * t / rng.uniform(300, 900)))
    # integrate speed exactly per segment start so that the angle is continuous
    dt = np.diff(t, prepend=t[0])
    return (rng.uniform(0, 2 * np.pi) + np.cumsum(speed * dt)) % (2 * np.pi)


def _dwell(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A servo holding one of 3-6 positions for minutes, moving between them at 20-120 rpm."""
    positions = rng.uniform(0, 2 * np.pi, rng.integers(3, 7))
    starts = _segments(t, rng, 300.0)
    targets = positions[rng.integers(positions.size, size=starts.size)]
    speed = rng.uniform(20, 120) * 2 * np.pi / 60
    seg = np.searchsorted(starts, t, side="right") - 1
    prev = np.concatenate(([targets[0]], targets[:-1]))
    move = np.angle(np.exp(1j * (targets - prev)))  # shortest way round
    since = t - starts[seg]
    frac = np.clip(since * speed / np.maximum(np.abs(move[seg]), 1e-9), 0, 1)
    theta = prev[seg] + move[seg] * frac
    return (theta + rng.normal(0, np.radians(0.02), t.shape)) % (2 * np.pi)


def _reverse(t: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Back and forth: a triangle (constant speed) or a sine, over an arc of 60-720°, period 2-120 s."""
    starts = _segments(t, rng, 3600.0)
    seg = np.searchsorted(starts, t, side="right") - 1
    k = starts.size
    center = rng.uniform(0, 2 * np.pi, k)
    half_arc = np.radians(rng.uniform(30, 360, k))
    period = np.exp(rng.uniform(np.log(2), np.log(120), k))
    triangle = rng.random(k) < 0.5
    phase = 2 * np.pi * t / period[seg]
    tri = 2 / np.pi * np.arcsin(np.sin(phase))
    wave = np.where(triangle[seg], tri, np.sin(phase))
    return (center[seg] + half_arc[seg] * wave) % (2 * np.pi)


# --- runs -----------------------------------------------------------------------------------------


@dataclass
class FieldRun:
    """A field recording (what the agent sees) and the truth behind it (what only the scorer sees)."""

    samples: Samples  # t, d, q, temp_c (reported)
    theta: np.ndarray  # true machine angle, rad
    die_c: np.ndarray  # die temperature, °C
    physics: DrivePhysics
    regime: str
    rate_hz: float
    clean: tuple[np.ndarray, np.ndarray] | None = None  # noise-free d, q at every sample: true_error_deg's, made once


def field_run(
    phys: DrivePhysics,
    *,
    days: float,
    rate_hz: float,
    regime: str,
    rng: np.random.Generator,
    low_c: float = -20.0,
    high_c: float = 75.0,
) -> FieldRun:
    t = sample_times(days, rate_hz, rng)
    temp = reported_temperature(t, rng, low=low_c, high=high_c)
    die = lagged_fast(temp, t, phys.die_lag_s)
    theta = shaft_angle(regime, t, rng)
    clean = phys.channels(theta, die, t)
    d, q = phys.digitise(*clean, rng)
    return FieldRun(Samples(t=t, d=d, q=q, temp_c=temp), theta, die, phys, regime, rate_hz, clean)


def bench_sweep(phys: DrivePhysics, rng: np.random.Generator, *, positions: int = 3600) -> Samples:
    """End-of-line calibration: +20 °C, the shaft stepped through `positions` reference angles (seed 000's
    0.1° table), the drive new (time 0), the reference encoder good to ~0.002°."""
    theta = np.arange(positions) * (2 * np.pi / positions)
    t = np.arange(positions) * 0.5
    temp = np.full(positions, BENCH_TEMP_C)
    d, q = phys.measure(theta, temp, np.zeros(positions), rng)
    ref = theta + rng.normal(0, np.radians(0.002), positions)
    return Samples(t=t, d=d, q=q, temp_c=temp + rng.normal(0, 0.05, positions), theta_ref=ref % (2 * np.pi))


def true_error_deg(correction, run: FieldRun, index=None, temp_c=None) -> np.ndarray:
    """Angle error (degrees) of a correction on the run's noise-free signals at the samples' true angles:
    what the coefficients leave, not the sensor's noise. The correction sees the reported temperature, or
    temp_c (the selected samples' temperature as the agent reads it)."""
    idx = slice(None) if index is None else index
    theta = run.theta[idx]
    if run.clean is not None:
        d, q = run.clean[0][idx], run.clean[1][idx]
    else:
        d, q = run.physics.channels(theta, run.die_c[idx], run.samples.t[idx])
    est = correction.angle(d, q, run.samples.temp_c[idx] if temp_c is None else temp_c)
    return np.degrees((est - theta + np.pi) % (2 * np.pi) - np.pi)
