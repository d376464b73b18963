"""The drift monitor's cause vocabulary (docs/architecture.md, "Alarms"; contract, additions only).

A selection of the one cause registry (`encoder_core.diagnose.causes`): the same `Cause` objects
diagnose names from samples, the monitor names from window statistics. Nothing else in the monitor
names a cause or a parameter by itself.
"""

from __future__ import annotations

from .diagnose.causes import ALARM_CAUSES as CAUSES
from .diagnose.causes import Cause

__all__ = ["CAUSES", "Cause", "cause", "check_parameters"]


def cause(name: str) -> Cause:
    try:
        return CAUSES[name]
    except KeyError:
        raise KeyError(f"unknown cause {name!r}; known: {', '.join(CAUSES)}") from None


def check_parameters(name: str, parameters: dict) -> dict:
    """An alarm's parameters must be exactly its cause's (the contract's names)."""
    expected = set(cause(name).alarm_params)
    if set(parameters) != expected:
        raise ValueError(f"{name}: parameters {sorted(parameters)} differ from the contract's {sorted(expected)}")
    return parameters
