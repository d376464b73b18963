"""The causes' vocabulary (docs/architecture.md): one `Cause` per name, whatever form the evidence takes.

A `Cause` is the form-independent part of a cause: its name, its parameters (name, unit, meaning),
when it cannot be tested, and the sentence that states it. It knows nothing of samples or window
statistics: diagnose's sample form lives in `terms.py` (one `Term` per cause: how it extends the
model fitted on samples and how its parameters are measured there); a monitor working on window
statistics adds its own form beside it and describes what it finds with the same `Cause`:

    cause = CAUSES["harmonic_distortion"]
    cause.not_testable(Observables(has_reference=False, temp_span_c=30.0, span_s=86400.0))  # None
    cause.state(order=5, amplitude=0.01)  # "the residual has a 4-cycle-per-turn component of 0.573° ..."

Testability rules read only `Observables`, which a recording and a merge of window statistics can
both fill (`Observables.from_window_stats`).
"""

from __future__ import annotations

import math
import string
from collections.abc import Callable
from dataclasses import dataclass, field

MIN_TEMP_SPAN_C = 5.0  # below this a thermal cause cannot be told from noise


@dataclass(frozen=True)
class Observables:
    """What a set of data lets one see, whichever form it came in."""

    has_reference: bool
    temp_span_c: float | None  # None: no temperature recorded
    span_s: float  # operating time covered

    @classmethod
    def from_window_stats(cls, stats, span_s: float) -> Observables:
        """From merged `encoder_core.stats.WindowStats` (windows carry no reference angle)."""
        span = float(stats.temp_max - stats.temp_min) if stats.temp_n else None
        return cls(has_reference=False, temp_span_c=span, span_s=float(span_s))


@dataclass(frozen=True)
class Param:
    name: str
    unit: str
    meaning: str


def _testable(_obs: Observables) -> str | None:
    return None


@dataclass(frozen=True)
class Cause:
    """One cause: identity, parameters, testability and the sentence that states it.

    `statement` is a `str.format` template over the parameters and some extra facts: `derive` computes
    facts from the parameters (a harmonic's cycles per turn from its order), `facts` holds the default
    of those only the caller can know (diagnose's held-out split by heating and cooling). `not_testable`
    gives the reason a cause cannot be tested at all, `partly_testable` what part of it cannot (None
    when there is nothing to say)."""

    name: str
    summary: str
    params: tuple[Param, ...]
    statement: str
    facts: dict = field(default_factory=dict)
    derive: Callable[[dict], dict] | None = None
    not_testable: Callable[[Observables], str | None] = _testable
    partly_testable: Callable[[Observables], str | None] = _testable
    alarm_params: tuple[str, ...] = ()  # the parameters an alarm of this cause carries (the Alarms contract)

    @property
    def param_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.params)

    def state(self, **values) -> str:
        """The statement with these parameter values (and facts: given ones win over derived ones, which
        win over the defaults)."""
        merged = {**self.facts, **(self.derive(values) if self.derive else {}), **values}
        missing = [f for _, f, _, _ in string.Formatter().parse(self.statement) if f and f not in merged]
        if missing:
            raise KeyError(f"{self.name}: statement needs {missing}")
        return self.statement.format(**merged)


def _needs_reference(obs: Observables) -> str | None:
    if obs.has_reference:
        return None
    return (
        "no theta_ref_deg column: a constant angle offset moves every sample along the circle and leaves "
        "no trace in d and q"
    )


def _needs_temperature(obs: Observables) -> str | None:
    if obs.temp_span_c is None:
        return "no temp_c column: nothing thermal can be seen"
    if obs.temp_span_c < MIN_TEMP_SPAN_C:
        return f"temp_c spans only {obs.temp_span_c:.1f} °C (need {MIN_TEMP_SPAN_C:.0f} °C)"
    return None


def _needs_duration(obs: Observables) -> str | None:
    return None if obs.span_s > 0 else "the recording has no duration"


def _low_orders_need_reference(obs: Observables) -> str | None:
    if obs.has_reference:
        return None
    return (
        "orders 2 and 3 only: without a reference order 2 looks like an offset and order 3 like gain or "
        "phase imbalance (orders 4-8 were tested)"
    )


_GAINS = "per axis (d, q), relative to the constant gain"
_OFFSETS = "per axis (d, q), in the recording's unit (counts, mT, ...)"

# In docs/architecture.md's order; diagnose proposes terms in this order.
_ALL = (
    Cause(
        "zero_offset",
        "the encoder's zero is not the machine's: a constant angle offset",
        (Param("offset_deg", "°", "constant angle offset, sensor minus reference"),),
        "the angle error has a constant part of {offset_deg:.3f}° at every angle{half_turn}",
        {"half_turn": ""},
        not_testable=_needs_reference,
    ),
    Cause(
        "phase_nonorthogonality",
        "the channels are not 90° apart (seed 001): a cross term between d and q",
        (Param("phase_error_deg", "°", "β, the departure of the channels from quadrature"),),
        "the residual follows {shape} with β = {phase_error_deg:.3f}°, a cross term between the channels",
        {"shape": "β·sin²θ"},
    ),
    Cause(
        "phase_drift",
        "the channels' phase difference changes with temperature",
        (Param("phase_drift_deg_per_c", "°/°C", "change of β per degree"),),
        "the channels' phase difference changes with temperature by {phase_drift_deg_per_c:.4f}°/°C",
        not_testable=_needs_temperature,
    ),
    Cause(
        "harmonic_distortion",
        "the field is not a pure sinusoid of the angle (seed 001 eq. 18)",
        (
            Param("order", "", "harmonic order n: an angle error of n - 1 cycles per turn"),
            Param("amplitude", "rad", "amplitude of that angle error"),
        ),
        "the residual has a {cycles}-cycle-per-turn component of {amplitude_deg:.3f}° "
        "(harmonic order {order}, seed 001 eq. 18)",
        derive=lambda v: {"cycles": int(v["order"]) - 1, "amplitude_deg": math.degrees(v["amplitude"])},
        partly_testable=_low_orders_need_reference,
    ),
    Cause(
        "thermal_lag",
        "the hall die's temperature lags the sensor that reports it (first order)",
        (Param("tau_s", "s", "time constant of the lag"),),
        "the residual depends on the rate of temperature change{where_fixed}; the die follows temp_c with a "
        "first-order lag of τ = {tau_s:.0f} s",
        {"where_fixed": ""},
        not_testable=_needs_temperature,
    ),
    Cause(
        "nonlinear_temperature",
        "gains and offsets are not linear in temperature",
        (
            Param("gain_tc2_per_c2", "1/°C²", f"quadratic temperature coefficient of the gain, {_GAINS}"),
            Param("offset_tc2_per_c2", "unit/°C²", f"quadratic temperature coefficient of the offset, {_OFFSETS}"),
        ),
        "gains and offsets curve with temperature (d, q gain {gain_d:.2e}, {gain_q:.2e} per °C²)",
        derive=lambda v: dict(zip(("gain_d", "gain_q"), v["gain_tc2_per_c2"], strict=True)),
        not_testable=_needs_temperature,
    ),
    Cause(
        "aging",
        "gains and offsets trend with operating time at equal temperature (magnet, electronics)",
        (
            Param("gain_loss_per_khour", "1/1000 h", f"gain lost per 1000 h of operation, {_GAINS}"),
            Param("offset_per_khour", "unit/1000 h", f"offset change per 1000 h of operation, {_OFFSETS}"),
        ),
        "gains and offsets trend with operating time at equal temperature (gain loss {loss_d:.3f}, "
        "{loss_q:.3f} per 1000 h{over})",
        {"over": ""},
        derive=lambda v: dict(zip(("loss_d", "loss_q"), v["gain_loss_per_khour"], strict=True)),
        not_testable=_needs_duration,
    ),
    Cause(
        "outliers",
        "corrupted samples: dropped reads (field collapsed) and isolated jumps off the circle",
        (Param("fraction", "", "share of the samples rejected"),),
        "{count} samples ({percent:.2f} %) {how}",
        {"count": "some", "how": "are far off the circle"},
        derive=lambda v: {"percent": 100 * v["fraction"]},
        alarm_params=("fraction",),
    ),
    Cause(
        "adc_clipping",
        "a channel stuck at a rail of its converter while the other one moves",
        (
            Param("fraction", "", "share of the samples with a clipped channel"),
            Param("channels", "", "the channels (d, q or a hall) found stuck"),
        ),
        "{where} while the other channel keeps moving",
        {"where": "a channel is stuck at a rail"},
        alarm_params=("fraction",),
    ),
)


def _rate(name: str, meaning: str) -> Param:
    return Param(name, "1/day", meaning)


# Causes only the drift monitor names (from window statistics over time); diagnose does not search them.
_MONITOR_ONLY = (
    Cause(
        "offset_step",
        "channel offsets jumped (knocked magnet, stray field)",
        (
            Param("delta_d", "", "jump of the d channel's offset, fraction of the amplitude"),
            Param("delta_q", "", "jump of the q channel's offset, fraction of the amplitude"),
        ),
        "the channel offsets jumped by {delta_d:+.4f}, {delta_q:+.4f} of the amplitude",
        alarm_params=("delta_d", "delta_q"),
    ),
    Cause(
        "gain_step",
        "the ratio of the channels' gains jumped (a sensor knocked, a connector, an amplifier's gain)",
        (Param("delta_imbalance", "", "jump of log(d amplitude / q amplitude)"),),
        "the ratio of the channel amplitudes (d/q) jumped by {percent:+.2f} %",
        derive=lambda v: {"percent": 100 * math.expm1(v["delta_imbalance"])},
        alarm_params=("delta_imbalance",),
    ),
    Cause(
        "axis_step",
        "the angle between the sensor axes jumped (a sensor tilted on its board, a bent bracket)",
        (Param("delta_skew", "", "jump of the sine of the axes' departure from 90° (the ellipse's skew)"),),
        "the angle between the sensor axes moved by {degrees:+.3f}°",
        derive=lambda v: {"degrees": math.degrees(math.asin(v["delta_skew"]))},
        alarm_params=("delta_skew",),
    ),
    Cause(
        "accelerated_aging",
        "offsets or gains drift far faster than the fleet's normal rate",
        (
            _rate("rate_per_day", "the device's drift rate, fraction of the amplitude per day"),
            _rate("fleet_median_rate_per_day", "the fleet's median rate of the same quantity"),
        ),
        "drifts at {rate_per_day:.4f} of the amplitude per day, the fleet at {fleet_median_rate_per_day:.4f}",
        alarm_params=("rate_per_day", "fleet_median_rate_per_day"),
    ),
    Cause(
        "magnet_weakening",
        "the common field amplitude falls (demagnetisation, growing air gap)",
        (_rate("loss_per_day", "fractional loss of the common amplitude per day"),),
        "the common field amplitude falls by {percent:.2f} % per day",
        derive=lambda v: {"percent": 100 * v["loss_per_day"]},
        alarm_params=("loss_per_day",),
    ),
    Cause(
        "harmonic_growth",
        "a field harmonic grows (eccentricity, wear)",
        (
            Param("order", "", "harmonic order n as in harmonic_distortion ((n - 1) cycles per turn)"),
            Param("amplitude_deg", "°", "the harmonic's angle-error amplitude now"),
        ),
        "harmonic order {order} has grown to {amplitude_deg:.3f}°",
        alarm_params=("order", "amplitude_deg"),
    ),
    Cause(
        "offline",
        "the agent's liveliness is gone",
        (Param("since", "s", "drive clock of the device's last window"),),
        "the agent's liveliness token is gone since drive time {since:.0f} s",
        alarm_params=("since",),
    ),
)

DIAGNOSE_CAUSES: dict[str, Cause] = {c.name: c for c in _ALL}  # what diagnose searches, in its order
CAUSES: dict[str, Cause] = {c.name: c for c in _ALL + _MONITOR_ONLY}
# the drift monitor's vocabulary (docs/architecture.md, "Alarms"): a selection of the one registry
ALARM_CAUSES: dict[str, Cause] = {name: c for name, c in CAUSES.items() if c.alarm_params}


def split_by_testability(obs: Observables) -> tuple[list[str], list[dict]]:
    """The causes that can be tested, and the Diagnose JSON's "not_testable" entries (whole causes
    first, then causes only part of which can be tested)."""
    whole = [{"cause": c.name, "why": why} for c in _ALL if (why := c.not_testable(obs))]
    blocked = {item["cause"] for item in whole}
    part = [{"cause": c.name, "why": why} for c in _ALL if c.name not in blocked and (why := c.partly_testable(obs))]
    return [c.name for c in _ALL if c.name not in blocked], whole + part
