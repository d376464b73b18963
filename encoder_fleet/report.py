"""The diagnose HTML report: the findings table and matplotlib plots embedded as PNG (one file)."""

from __future__ import annotations

import base64
import html
import io

import numpy as np

from encoder_fleet.outputs import write_file


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90, bbox_inches="tight")
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _thin(n: int, limit: int = 20000) -> np.ndarray:
    """At most `limit` evenly spread rows: plots of 100k points say nothing more and cost seconds."""
    return np.arange(n) if n <= limit else np.linspace(0, n - 1, limit).astype(int)


def _plots(plots: dict) -> list[tuple[str, str]]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    base = np.asarray(plots["baseline_error_deg"])
    ext = np.asarray(plots["extended_error_deg"])
    ang = np.asarray(plots["angle_deg"])
    t = np.asarray(plots["t"])
    idx = _thin(base.size)
    label = "angle error" if plots["metric"] == "reference" else "radius ripple"
    out = []

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), sharey=True)
    for ax, err, name in ((axes[0], base, "baseline"), (axes[1], ext, "extended")):
        ax.plot(ang[idx], err[idx], ".", ms=1.5, alpha=0.5)
        ax.set_title(f"{name}: held-out {label} against angle")
        ax.set_xlabel("angle (°)")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(f"{label} (°)")
    out.append(("Residual against angle", _png(fig)))
    plt.close(fig)

    temp = plots.get("temp_c")
    if temp is not None:
        temp = np.asarray(temp)
        rate = np.asarray(plots["rate_c_per_min"])
        view = np.asarray(plots.get("thermal_view_deg", base))
        view_name = plots.get("thermal_view", "baseline")
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.6), sharey=True)
        for ax, err, name in ((axes[0], view, view_name), (axes[1], ext, "extended")):
            for mask, colour, what in (
                (rate > 0.2, "tab:red", "heating"),
                (rate < -0.2, "tab:blue", "cooling"),
                (np.abs(rate) <= 0.2, "tab:gray", "steady"),
            ):
                m = idx[mask[idx]]
                if m.size:
                    ax.plot(temp[m], err[m], ".", ms=1.5, alpha=0.5, color=colour, label=what)
            ax.set_title(f"{name}: held-out {label} vs temperature", fontsize=10)
            ax.set_xlabel("reported temperature (°C)")
            ax.grid(alpha=0.3)
            ax.legend(markerscale=6, loc="upper right")
        axes[0].set_ylabel(f"{label} (°)")
        out.append(("Residual against temperature (heating red, cooling blue)", _png(fig)))
        plt.close(fig)

    fig, ax = plt.subplots(figsize=(11, 3.2))
    ax.plot(t[idx], base[idx], ".", ms=1.5, alpha=0.5, label="baseline")
    ax.plot(t[idx], ext[idx], ".", ms=1.5, alpha=0.5, label="extended")
    ax.set_xlabel("t (s)")
    ax.set_ylabel(f"{label} (°)")
    ax.set_title("extended model's held-out residual beside the baseline's")
    ax.legend(markerscale=6)
    ax.grid(alpha=0.3)
    out.append(("Baseline and extended residual over time", _png(fig)))
    plt.close(fig)
    return out


def render(diagnosis, title: str = "recording") -> str:
    r = diagnosis.report
    esc = html.escape
    rows = (
        "".join(
            f"<tr><td>{esc(f['cause'])}</td><td>{esc(', '.join(f'{k}={v}' for k, v in f['parameters'].items()))}</td>"
            f"<td>{f['rms_error_deg_before']:.4f}</td><td>{f['rms_error_deg_after']:.4f}</td>"
            f"<td>{esc(f['evidence'])}</td></tr>"
            for f in r["findings"]
        )
        or "<tr><td colspan=5>no findings: the baseline explains the recording down to its noise</td></tr>"
    )
    untestable = (
        "".join(f"<li><b>{esc(n['cause'])}</b>: {esc(n['why'])}</li>" for n in r["not_testable"]) or "<li>none</li>"
    )
    figs = "".join(
        f"<h3>{esc(name)}</h3><img alt='{esc(name)}' src='data:image/png;base64,{png}'>"
        for name, png in _plots(diagnosis.plots)
    )
    b, e = r["baseline"], r["extended"]
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>diagnose: {esc(title)}</title>
<style>body{{font-family:sans-serif;max-width:1150px;margin:2em auto}}td,th{{border:1px solid #ccc;padding:4px 8px;
vertical-align:top}}table{{border-collapse:collapse}}img{{max-width:100%}}</style></head><body>
<h1>diagnose: {esc(title)}</h1>
<p>{r["samples"]} samples; error metric <b>{esc(r["error_metric"])}</b>; every error is measured on held-out data
(held out by {esc(str(r.get("held_out", {}).get("by", "?")))}).</p>
<table><tr><th>model</th><th>RMS (°)</th><th>max (°)</th></tr>
<tr><td>baseline: {esc(b["model"])}</td><td>{b["rms_error_deg"]:.4f}</td><td>{b["max_error_deg"]:.4f}</td></tr>
<tr><td>extended: baseline + {esc(", ".join(e["causes"]) or "nothing")}</td><td>{e["rms_error_deg"]:.4f}</td>
<td>{e["max_error_deg"]:.4f}</td></tr></table>
{_repeatability(r.get("repeatability"))}
<h2>Findings</h2>
<table><tr><th>cause</th><th>parameters</th><th>RMS before (°)</th><th>RMS after (°)</th>
<th>evidence</th></tr>{rows}</table>
<h2>Not testable with this recording</h2><ul>{untestable}</ul>
<h2>Plots</h2>{figs}
</body></html>
"""


def _repeatability(rep: dict | None) -> str:
    """Run-to-run repeatability: a shift per run that no model fitted on other runs can predict."""
    if not rep:
        return ""
    esc = html.escape
    cells = "".join(f"<td>run {esc(run)}: {shift:+.3f}°</td>" for run, shift in rep["runs"].items())
    return (
        f"<h2>Run-to-run repeatability</h2><table><tr>{cells}<td>RMS {rep['rms_deg']:.3f}°</td>"
        f"<td>within runs {rep['within_run_rms_error_deg']:.3f}°</td></tr></table><p>{esc(rep['note'])}</p>"
    )


def write_report(diagnosis, path, title: str = "recording") -> None:
    write_file(path, render(diagnosis, title))
