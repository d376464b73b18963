"""A magneto-electric encoder with every error effect behind a switch.

Signal chain, in order (each stage is off at its default):

1. mechanical angle + zero offset                   -> electrical angle θe
2. harmonics, seed 001 eq. 15:  z = e^{jθe} + Σ K_n e^{j(nθe+φ_n)}
3. amplitude imbalance α and phase error β on the d channel (seed 001 eq. 4, 10),
   β may drift with temperature:   d = (1+α)·Re(z·e^{jβ(T)}),  q = Im z
4. per-axis gain and offset drift with the die temperature (seed 000 eq. 4-5),
   linear and optionally quadratic in T, plus aging over operating hours
5. the die temperature lags the reported temperature (first-order, τ)
6. four halls around the ADC mid-scale, Gaussian noise, impulses,
   12-bit quantisation and clipping at the rails.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from .physics import ADC_MAX, ADC_MID, REFERENCE_TEMP_C, halls_to_dq
from .samples import Samples
from .thermal import first_order_lag


@dataclass(frozen=True)
class EncoderModel:
    hall_amplitude: float = 700.0  # counts per hall at +20 °C; d and q swing twice this
    # seed 001: amplitude imbalance, phase non-orthogonality, harmonics (n, K_n, phase rad)
    amplitude_imbalance: float = 0.0
    phase_error_rad: float = 0.0
    phase_drift_rad_per_c: float = 0.0
    harmonics: tuple[tuple[int, float, float], ...] = ()
    # seed 000: per-axis (d, q) gain and offset against the die temperature
    gain_tc_per_c: tuple[float, float] = (0.0, 0.0)
    gain_tc2_per_c2: tuple[float, float] = (0.0, 0.0)  # non-linear temperature coefficient
    offset_counts: tuple[float, float] = (0.0, 0.0)
    offset_tc_counts_per_c: tuple[float, float] = (0.0, 0.0)
    offset_tc2_counts_per_c2: tuple[float, float] = (0.0, 0.0)
    # what real drives add
    thermal_lag_tau_s: float = 0.0
    aging_gain_per_khour: float = 0.0  # fractional gain loss per 1000 operating hours
    aging_offset_counts_per_khour: tuple[float, float] = (0.0, 0.0)
    zero_offset_rad: float = 0.0
    noise_counts: float = 0.0  # Gaussian, per hall
    impulse_fraction: float = 0.0  # share of samples with one corrupted hall
    impulse_counts: float = 0.0
    quantize: bool = True  # 12-bit ADC: rounding and clipping at 0 and 4095

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict) -> EncoderModel:
        data = dict(data)
        if "harmonics" in data:
            data["harmonics"] = tuple(tuple(h) for h in data["harmonics"])
        for key, value in data.items():
            if isinstance(value, list):
                data[key] = tuple(value)
        return cls(**data)

    def with_(self, **changes) -> EncoderModel:
        return replace(self, **changes)


def clean_signals(model: EncoderModel, theta_mech, die_temp_c, hours) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free d and q in counts before the ADC: stages 1-4."""
    theta_e = np.asarray(theta_mech, dtype=float) + model.zero_offset_rad
    z = np.exp(1j * theta_e)
    for n, k, phase in model.harmonics:
        z = z + k * np.exp(1j * (n * theta_e + phase))
    dT = np.asarray(die_temp_c, dtype=float) - REFERENCE_TEMP_C
    beta = model.phase_error_rad + model.phase_drift_rad_per_c * dT
    amp = 2.0 * model.hall_amplitude
    d0 = amp * (1 + model.amplitude_imbalance) * np.real(z * np.exp(1j * beta))
    q0 = amp * np.imag(z)
    khours = np.asarray(hours, dtype=float) / 1000.0
    aging = 1.0 - model.aging_gain_per_khour * khours
    out = []
    for axis, sig in ((0, d0), (1, q0)):
        gain = (1 + model.gain_tc_per_c[axis] * dT + model.gain_tc2_per_c2[axis] * dT**2) * aging
        offset = (
            model.offset_counts[axis]
            + model.offset_tc_counts_per_c[axis] * dT
            + model.offset_tc2_counts_per_c2[axis] * dT**2
            + model.aging_offset_counts_per_khour[axis] * khours
        )
        out.append(gain * sig + offset)
    return out[0], out[1]


def to_halls(model: EncoderModel, d, q, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Split d/q over four halls around mid-scale, add noise and impulses, then the ADC (stage 6)."""
    n = np.asarray(d).size
    halls = {
        "a_plus": ADC_MID + q / 2,
        "a_minus": ADC_MID - q / 2,
        "b_plus": ADC_MID + d / 2,
        "b_minus": ADC_MID - d / 2,
    }
    if model.noise_counts > 0:
        for key in halls:
            halls[key] = halls[key] + rng.normal(0.0, model.noise_counts, n)
    if model.impulse_fraction > 0 and n:
        hit = np.flatnonzero(rng.random(n) < model.impulse_fraction)
        which = rng.integers(0, 4, hit.size)
        sign = rng.choice([-1.0, 1.0], hit.size)
        for k, key in enumerate(halls):
            rows = hit[which == k]
            halls[key] = np.array(halls[key], dtype=float)
            halls[key][rows] += sign[which == k] * model.impulse_counts
    if model.quantize:
        halls = {k: np.clip(np.round(v), 0, ADC_MAX) for k, v in halls.items()}
    return halls


def simulate(
    model: EncoderModel,
    t,
    theta_mech,
    temp_reported_c,
    rng: np.random.Generator,
    *,
    hours_offset: float = 0.0,
    die_temp0: float | None = None,
) -> tuple[Samples, np.ndarray]:
    """Samples as the drive would record them, and the die temperature (kept from the fits)."""
    t = np.asarray(t, dtype=float)
    temp_reported_c = np.asarray(temp_reported_c, dtype=float)
    die = first_order_lag(t, temp_reported_c, model.thermal_lag_tau_s, die_temp0)
    hours = hours_offset + (t - (t[0] if t.size else 0.0)) / 3600.0
    d_clean, q_clean = clean_signals(model, theta_mech, die, hours)
    halls = to_halls(model, d_clean, q_clean, rng)
    d, q = halls_to_dq(halls["a_plus"], halls["a_minus"], halls["b_plus"], halls["b_minus"])
    theta_ref = np.asarray(theta_mech, dtype=float) % (2 * np.pi)
    return Samples(t=t, d=d, q=q, temp_c=temp_reported_c, theta_ref=theta_ref, halls=halls), die


# --- operating profiles -----------------------------------------------------------------------


@dataclass
class Profile:
    """Where the rotor is and what the temperature sensor reports, sample by sample."""

    t: np.ndarray
    theta: np.ndarray
    temp_c: np.ndarray
    run: np.ndarray | None = None
    speed_rpm: np.ndarray | None = None


def bench_profile(
    plateaus=(20.0, -40.0, 60.0, 20.0),
    *,
    positions: int = 3600,
    step_s: float = 0.003,
    ramp_rate_c_per_min: float = 2.0,
    ramp_sample_s: float = 0.5,
    soak_s: float = 600.0,
    soak_sample_s: float = 5.0,
    rng: np.random.Generator | None = None,
) -> Profile:
    """Seed 000's bench: at each temperature plateau the rotor steps through `positions` equal steps
    (0.1° at 3600, one every 3 ms as in the paper); between plateaus the chamber ramps while the
    rotor keeps turning at the same speed. Soaks before each sweep let the die settle."""
    rev_s = positions * step_s
    omega = 2 * np.pi / rev_s
    ts, thetas, temps, runs = [], [], [], []
    now = 0.0
    current = float(plateaus[0])
    for k, target in enumerate(plateaus):
        target = float(target)
        if k > 0 and target != current:
            dur = abs(target - current) / ramp_rate_c_per_min * 60.0
            tt = np.arange(0.0, dur, ramp_sample_s)
            ts.append(now + tt)
            temps.append(current + (target - current) * tt / dur)
            thetas.append(omega * (now + tt))
            runs.append(np.full(tt.size, k))
            now += dur
        current = target
        if soak_s > 0:
            tt = np.arange(0.0, soak_s, soak_sample_s)
            ts.append(now + tt)
            temps.append(np.full(tt.size, target))
            thetas.append(omega * (now + tt))
            runs.append(np.full(tt.size, k))
            now += soak_s
        tt = np.arange(positions) * step_s
        ts.append(now + tt)
        temps.append(np.full(positions, target))
        thetas.append(np.arange(positions) * (2 * np.pi / positions))
        runs.append(np.full(positions, k))
        now += positions * step_s
    t = np.concatenate(ts)
    return Profile(
        t=t,
        theta=np.concatenate(thetas) % (2 * np.pi),
        temp_c=np.concatenate(temps),
        run=np.concatenate(runs).astype(float),
        speed_rpm=np.full(t.size, 60.0 / rev_s),
    )


def field_profile(
    days: float = 3.0,
    *,
    sample_s: float = 10.0,
    ambient_c: float = 25.0,
    ambient_swing_c: float = 8.0,
    load_rise_c: float = 40.0,
    load_tau_s: float = 1200.0,
    rng: np.random.Generator,
) -> Profile:
    """A drive in the field: random positions, temperature = daily ambient cycle plus load heating
    that follows a random duty schedule through a first-order thermal path."""
    t = np.arange(0.0, days * 86400.0, sample_s)
    ambient = ambient_c + ambient_swing_c * np.sin(2 * np.pi * (t / 86400.0 - 0.3))
    # load switches between idle and busy levels at random times (mean 2 h)
    n_switch = max(1, int(days * 12))
    switch_t = np.sort(rng.uniform(0, t[-1] if t.size else 1.0, n_switch))
    levels = rng.uniform(0.0, 1.0, n_switch + 1)
    load = levels[np.searchsorted(switch_t, t)]
    heating = first_order_lag(t, load * load_rise_c, load_tau_s, y0=0.0)
    theta = rng.uniform(0.0, 2 * np.pi, t.size)
    speed = load * 3000.0
    return Profile(t=t, theta=theta, temp_c=ambient + heating, speed_rpm=speed)


def cycle_profile(
    hours: float,
    *,
    sample_s: float,
    t_min: float = -40.0,
    t_max: float = 85.0,
    cycle_hours: float = 12.0,
    t0: float = 0.0,
    rng: np.random.Generator,
) -> Profile:
    """A temperature cycle between t_min and t_max (cosine, starting at +20 °C side) with random
    positions: the fleet's simulated drives run through heating and cooling."""
    t = t0 + np.arange(0.0, hours * 3600.0, sample_s)
    mid, half = (t_max + t_min) / 2, (t_max - t_min) / 2
    phase0 = np.arccos(np.clip((REFERENCE_TEMP_C - mid) / half, -1, 1))
    temp = mid + half * np.cos(2 * np.pi * t / (cycle_hours * 3600.0) + phase0)
    return Profile(t=t, theta=rng.uniform(0.0, 2 * np.pi, t.size), temp_c=temp)


def record(
    model: EncoderModel,
    profile: Profile,
    rng: np.random.Generator,
    *,
    reference: bool = True,
    temperature: bool = True,
    halls: bool = False,
) -> Samples:
    """Run a model through a profile and keep what a recorder would keep."""
    samples, _ = simulate(model, profile.t, profile.theta, profile.temp_c, rng)
    return Samples(
        t=samples.t,
        d=samples.d,
        q=samples.q,
        temp_c=samples.temp_c if temperature else None,
        theta_ref=samples.theta_ref if reference else None,
        run=profile.run,
        speed_rpm=profile.speed_rpm,
        halls=samples.halls if halls else None,
    )


def typical_drive(rng: np.random.Generator, **overrides) -> EncoderModel:
    """A plausible production encoder drawn at random: NdFeB-like gain loss with temperature
    (about -0.1 %/°C, different per axis), offset drift, a little phase error and 3rd harmonic."""
    base = dict(
        hall_amplitude=rng.uniform(600, 800),
        amplitude_imbalance=rng.uniform(-0.03, 0.03),
        phase_error_rad=np.radians(rng.uniform(-1.5, 1.5)),
        harmonics=((3, rng.uniform(0.003, 0.01), rng.uniform(-np.pi, np.pi)),),
        gain_tc_per_c=(rng.uniform(-0.0025, -0.0005), rng.uniform(-0.0025, -0.0005)),
        offset_counts=(rng.uniform(-20, 20), rng.uniform(-20, 20)),
        offset_tc_counts_per_c=(rng.uniform(-0.6, 0.6), rng.uniform(-0.6, 0.6)),
        noise_counts=2.0,
    )
    base.update(overrides)
    return EncoderModel(**base)
