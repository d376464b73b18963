"""Recording CSV (the contract in docs/architecture.md): read with line-precise errors, write from Samples."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np

from encoder_core.physics import halls_to_dq
from encoder_core.samples import InputError, Samples
from encoder_fleet.outputs import replaced

HALL_COLUMNS = ("a_plus", "a_minus", "b_plus", "b_minus")
OPTIONAL = ("temp_c", "theta_ref_deg", "speed_rpm", "run")
ABSOLUTE_ZERO_C = -273.15  # a temperature below it is a broken reading, not a cold drive
CHUNK_ROWS = 65536  # rows parsed into Python floats before they are moved into arrays


def read_recording(path: str | Path, *, broken_temperatures: bool = False) -> Samples:
    """Parse a recording; any problem raises InputError naming the file, line and column. broken_temperatures: a
    temp_c below absolute zero (a logger's no-reading sentinel, an open sensor) is kept as read, for an agent's
    replay, which rejects such a reading's sample as the drive's own agent would; else it is refused."""
    path = Path(path)
    try:
        handle = path.open(newline="", encoding="utf-8-sig")  # -sig: a byte-order mark before the header is dropped
    except OSError as exc:
        raise InputError(f"{path}: cannot open: {exc.strerror}") from exc
    with handle:
        reader = csv.reader(handle)
        try:
            return _parse(path, reader, broken_temperatures)
        except UnicodeDecodeError as exc:
            raise InputError(
                f"{path}: not UTF-8 text (byte {exc.object[exc.start]:#04x} "
                f"{f'after line {reader.line_num}' if reader.line_num else 'in its first lines'}): "
                "a recording is a CSV text file"
            ) from None


def _parse(path: Path, reader, broken_temperatures: bool) -> Samples:
    """The rows of an open recording as Samples (read_recording's body; its errors name the line and column)."""
    try:
        header = [h.strip() for h in next(reader)]
    except StopIteration:
        raise InputError(f"{path}: the file is empty (expected a header row)") from None
    except csv.Error as exc:
        raise InputError(f"{path}, line 1: not valid CSV: {exc}") from None
    known = ("t", "d", "q", *HALL_COLUMNS, *OPTIONAL)  # one that is read must not be ambiguous; others are left
    twice = sorted({h for h in header if h in known and header.count(h) > 1})
    if twice:
        raise InputError(f"{path}, line 1: column {twice[0]!r} appears twice in the header")
    if "t" not in header:
        raise InputError(f"{path}: missing column 't' (header has: {', '.join(header)})")
    has_dq = "d" in header and "q" in header
    has_halls = all(h in header for h in HALL_COLUMNS)
    if not (has_dq or has_halls):
        raise InputError(
            f"{path}: missing columns: need 'd' and 'q', or all of {', '.join(HALL_COLUMNS)}"
            f" (header has: {', '.join(header)})"
        )
    wanted = ["t"] + (["d", "q"] if has_dq else list(HALL_COLUMNS)) + [c for c in OPTIONAL if c in header]
    index = {name: header.index(name) for name in wanted}
    columns: dict[str, list[float]] = {name: [] for name in wanted}
    lines: list[int] = []  # the file line of each data row, for messages about rows
    # the rows read so far, as arrays: a Python float in a list takes 32 bytes, an array's 8, and a day at 20 Hz
    # held as lists to the end took ~400 MB to read (one agent process per drive replays a fleet at once)
    chunks: dict[str, list[np.ndarray]] = {name: [] for name in wanted}
    line_chunks: list[np.ndarray] = []

    def flush() -> None:
        for name, values in columns.items():
            chunks[name].append(np.asarray(values, dtype=float))
            values.clear()
        line_chunks.append(np.asarray(lines, dtype=np.int64))
        lines.clear()

    try:
        for row in reader:
            line = reader.line_num
            if not row or all(not cell.strip() for cell in row):
                continue
            lines.append(line)
            if len(row) < len(header) or any(cell.strip() for cell in row[len(header) :]):
                raise InputError(f"{path}, line {line}: {len(row)} fields, expected {len(header)}")
            for name, col in index.items():
                cell = row[col].strip()
                try:
                    value = float(cell)
                except ValueError:
                    raise InputError(f"{path}, line {line}, column '{name}': not a number: {cell!r}") from None
                if not math.isfinite(value):
                    raise InputError(f"{path}, line {line}, column '{name}': not a finite number: {cell!r}")
                if name == "temp_c" and value < ABSOLUTE_ZERO_C and not broken_temperatures:
                    raise InputError(f"{path}, line {line}, column 'temp_c': {cell} °C is below absolute zero")
                columns[name].append(value)
            if len(lines) >= CHUNK_ROWS:
                flush()
    except csv.Error as exc:
        raise InputError(f"{path}, line {reader.line_num}: not valid CSV: {exc}") from None
    flush()
    arrays = {k: np.concatenate(v) for k, v in chunks.items()}
    row_lines = np.concatenate(line_chunks)
    t = arrays["t"]
    if t.size == 0:
        raise InputError(f"{path}: no data rows after the header")
    step = np.diff(t)
    bad = np.flatnonzero(step <= 0)
    if bad.size:
        row = bad[0] + 1  # the row whose t is not after the one before it
        raise InputError(
            f"{path}, line {row_lines[row]}, column 't': does not increase "
            f"({t[row - 1]} on line {row_lines[row - 1]}, then {t[row]})"
        )
    if has_dq:
        d, q = arrays["d"], arrays["q"]
        halls = None
    else:
        halls = {h: arrays[h] for h in HALL_COLUMNS}
        d, q = halls_to_dq(halls["a_plus"], halls["a_minus"], halls["b_plus"], halls["b_minus"])
    theta = np.radians(arrays["theta_ref_deg"]) if "theta_ref_deg" in arrays else None
    return Samples(
        t=t,
        d=d,
        q=q,
        temp_c=arrays.get("temp_c"),
        theta_ref=theta,
        run=arrays.get("run"),
        speed_rpm=arrays.get("speed_rpm"),
        halls=halls,
    )


def write_recording(samples: Samples, path: str | Path, *, halls: bool = False) -> None:
    """Write the CSV contract: t, d, q (or the four halls), then whichever optional columns exist."""
    cols: dict[str, np.ndarray] = {"t": samples.t}
    if halls and samples.halls is not None:
        cols.update({h: samples.halls[h] for h in HALL_COLUMNS})
    else:
        cols.update({"d": samples.d, "q": samples.q})
    if samples.temp_c is not None:
        cols["temp_c"] = samples.temp_c
    if samples.theta_ref is not None:
        cols["theta_ref_deg"] = np.degrees(samples.theta_ref)
    if samples.speed_rpm is not None:
        cols["speed_rpm"] = samples.speed_rpm
    if samples.run is not None:
        cols["run"] = samples.run
    fmt = {"t": "%.4f", "run": "%d"}
    matrix = np.column_stack(list(cols.values()))
    with replaced(path) as out:  # whole or not at all
        np.savetxt(
            out, matrix, delimiter=",", header=",".join(cols), comments="", fmt=[fmt.get(c, "%.6g") for c in cols]
        )
