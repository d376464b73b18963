"""The drift monitor's cause vocabulary (docs/architecture.md, "Alarms"; contract, additions only).

One small registry, shaped as the cause registry diagnose is getting (one cause object, two data forms:
samples for `encoder-fleet diagnose`, window statistics for the monitor). When that registry lands,
`CAUSES` below becomes a selection of its objects and this module shrinks to that selection; nothing
else in the monitor names a cause or a parameter by itself.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class Cause:
    name: str
    description: str
    parameters: dict[str, str] = field(default_factory=dict)  # name -> meaning and unit
    forms: tuple[str, ...] = ("windows",)  # data forms that can show it: "samples" (diagnose), "windows" (monitor)
    diagnose_name: str | None = None  # the same effect in diagnose's vocabulary, where it has one


_ALL = (
    Cause(
        "offset_step",
        "channel offsets jumped (knocked magnet, stray field)",
        {
            "delta_d": "jump of the d channel's offset, fraction of the amplitude",
            "delta_q": "jump of the q channel's offset, fraction of the amplitude",
        },
    ),
    Cause(
        "accelerated_aging",
        "offsets or gains drift far faster than the fleet's normal rate",
        {
            "rate_per_day": "the device's drift rate, fraction of the amplitude per day",
            "fleet_median_rate_per_day": "the fleet's median rate of the same quantity",
        },
        forms=("samples", "windows"),
        diagnose_name="aging",
    ),
    Cause(
        "magnet_weakening",
        "the common field amplitude falls (demagnetisation, growing air gap)",
        {"loss_per_day": "fractional loss of the common amplitude per day"},
    ),
    Cause(
        "harmonic_growth",
        "a field harmonic grows (eccentricity, wear)",
        {
            "order": "harmonic order n as in diagnose's harmonic_distortion ((n - 1) cycles per turn)",
            "amplitude_deg": "the harmonic's amplitude now, degrees",
        },
        forms=("samples", "windows"),
        diagnose_name="harmonic_distortion",
    ),
    Cause(
        "outliers",
        "a share of samples are spikes (EMI, failing sensor)",
        {"fraction": "share of samples rejected as off the circle"},
        forms=("samples", "windows"),
        diagnose_name="outliers",
    ),
    Cause(
        "adc_clipping",
        "channels pinned at the converter's rail",
        {"fraction": "share of samples pinned at a channel's extreme value"},
        forms=("samples", "windows"),
        diagnose_name="adc_clipping",
    ),
    Cause("offline", "the agent's liveliness is gone", {"since": "drive clock of the last window, s"}),
)

CAUSES: dict[str, Cause] = {c.name: c for c in _ALL}


def cause(name: str) -> Cause:
    try:
        return CAUSES[name]
    except KeyError:
        raise KeyError(f"unknown cause {name!r}; known: {', '.join(CAUSES)}") from None


def check_parameters(name: str, parameters: dict) -> dict:
    """An alarm's parameters must be exactly its cause's (the contract's names)."""
    expected = set(cause(name).parameters)
    if set(parameters) != expected:
        raise ValueError(f"{name}: parameters {sorted(parameters)} differ from the contract's {sorted(expected)}")
    return parameters
