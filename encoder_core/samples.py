"""The one in-memory form of a recording: what every method fits on and every tool reads."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np


class InputError(ValueError):
    """Input that cannot be used, with a message that says what and where."""


@dataclass
class Samples:
    """Time-ordered encoder samples. d, q in any unit; angles in radians; temperatures in °C."""

    t: np.ndarray
    d: np.ndarray
    q: np.ndarray
    temp_c: np.ndarray | None = None  # reported temperature
    theta_ref: np.ndarray | None = None  # reference (machine) angle, rad
    run: np.ndarray | None = None
    speed_rpm: np.ndarray | None = None
    halls: dict[str, np.ndarray] | None = field(default=None, repr=False)

    def __post_init__(self):
        n = None
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None or f.name == "halls":
                continue
            arr = np.asarray(value, dtype=float)
            if arr.ndim != 1:
                raise InputError(f"column {f.name!r} must be one-dimensional, got shape {arr.shape}")
            if n is None:
                n = arr.size
            elif arr.size != n:
                raise InputError(f"column {f.name!r} has {arr.size} values, expected {n} like column 't'")
            setattr(self, f.name, arr)

    def __len__(self) -> int:
        return int(self.t.size)

    @property
    def has_reference(self) -> bool:
        return self.theta_ref is not None

    @property
    def has_temperature(self) -> bool:
        return self.temp_c is not None

    def subset(self, index) -> Samples:
        """Rows selected by a boolean mask or an index array."""
        kwargs = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name == "halls":
                kwargs["halls"] = None if value is None else {k: v[index] for k, v in value.items()}
            else:
                kwargs[f.name] = None if value is None else value[index]
        return Samples(**kwargs)


def check_finite(name: str, *arrays) -> None:
    """Raise InputError naming the first non-finite value of any array."""
    for i, arr in enumerate(arrays):
        if arr is None:
            continue
        arr = np.asarray(arr, dtype=float)
        bad = np.flatnonzero(~np.isfinite(arr))
        if bad.size:
            raise InputError(
                f"{name}: argument {i} has a non-finite value (NaN or inf) at index {int(bad[0])} ({bad.size} in all)"
            )


def check_fit_input(d, q, *, min_samples: int = 8, theta_ref=None, temp_c=None) -> tuple[np.ndarray, np.ndarray]:
    """Validate d/q (and optional reference, temperature) before a fit."""
    d = np.asarray(d, dtype=float)
    q = np.asarray(q, dtype=float)
    if d.ndim != 1 or q.ndim != 1:
        raise InputError("d and q must be one-dimensional arrays")
    if d.size != q.size:
        raise InputError(f"d has {d.size} values but q has {q.size}: lengths must match")
    for name, other in (("theta_ref", theta_ref), ("temp_c", temp_c)):
        if other is not None and np.asarray(other).size != d.size:
            raise InputError(f"{name} has {np.asarray(other).size} values but d has {d.size}: lengths must match")
    if d.size == 0:
        raise InputError("no samples: d and q are empty")
    if d.size < min_samples:
        raise InputError(f"too few samples for a fit: {d.size}, need at least {min_samples}")
    check_finite("fit input (d, q, theta_ref, temp_c)", d, q, theta_ref, temp_c)
    return d, q


def check_angle_coverage(theta, *, min_sectors: int = 6, sectors: int = 12, what: str = "angle") -> None:
    """A fit of a circle needs samples spread around it: at least min_sectors of 12 sectors populated."""
    theta = np.asarray(theta, dtype=float)
    occupied = np.unique(np.floor((theta % (2 * np.pi)) / (2 * np.pi) * sectors).astype(int))
    if occupied.size < min_sectors:
        raise InputError(
            f"too little {what} coverage for a fit: samples fall in {occupied.size} of {sectors}"
            f" 30° sectors, need at least {min_sectors}"
        )
