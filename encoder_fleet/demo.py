"""`encoder-fleet demo`: the service (with its embedded router) in this process, one agent process
per simulated drive, the rollout as it happens, and a summary scored against the simulator's truth.

The truth is used here only, after the run: neither the agents nor the service ever see it.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from edge_agent.sources import SimulatedDrive, drive_model, evaluation_set, factory_calibration
from encoder_core.correction import BandedCorrection
from encoder_core.physics import angle_error_deg, rms
from encoder_fleet.logs import to_file
from fleet_wire.session import free_port, loopback_endpoint
from service.auth import TokenAuth
from service.guard import service_security
from service.mcap_export import export_mcap
from service.runtime import BAND_HORIZON_H, FleetService, HttpServer, open_session
from service.store import Store

WINDOW_S = 60.0
KNOCK_AT_HOUR = 14.0  # the demo knocks drive-000's magnet here (offsets jump by 1.5 % of the amplitude)


def errors(
    device_seed: int, bands: list[dict] | None, *, knocked: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Temperature, and the factory's and the fleet's angle errors (degrees) over a -40…+85 °C cycle, on
    noise-free signals: they measure the coefficients, not the sensor's noise."""
    model = drive_model(device_seed)
    factory = factory_calibration(model, device_seed)  # the factory calibrated the drive before any knock
    if knocked:  # the drive as it is now: its magnet knocked (what the fleet's coefficients must correct)
        model = SimulatedDrive(device_seed, hours=0.0, knock_at_s=0.0).knocked
    truth = evaluation_set(model.with_(noise_counts=0.0), device_seed)
    fleet = BandedCorrection.from_dict({"bands": bands}) if bands else factory
    return (
        truth.temp_c,
        angle_error_deg(factory.angle(truth.d, truth.q, truth.temp_c), truth.theta_ref),
        angle_error_deg(fleet.angle(truth.d, truth.q, truth.temp_c), truth.theta_ref),
    )


def score(device_seed: int, bands: list[dict] | None, *, knocked: bool = False) -> dict:
    """RMS and max angle error of factory and fleet coefficients over the cycle."""
    _, f, g = errors(device_seed, bands, knocked=knocked)
    return {
        "rms_error_deg_factory": rms(f),
        "max_error_deg_factory": float(np.abs(f).max()),
        "rms_error_deg_fleet": rms(g),
        "max_error_deg_fleet": float(np.abs(g).max()),
    }


def plot_errors(
    curves: dict[str, tuple],
    path: Path,
    alarms: dict[str, list[dict]] | None = None,
    knock: tuple[str, float] | None = None,
    hours: float | None = None,
) -> None:
    """RMS angle error against temperature, factory (dashed) and fleet (solid), one colour per drive; below
    it, when alarms are given, each drive's timeline with the planted event and the alarms the monitor raised."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    edges = np.arange(-40.0, 90.0, 5.0)
    if alarms is None:
        fig, ax = plt.subplots(figsize=(9, 4.5))
    else:
        fig, (ax, tl) = plt.subplots(2, 1, figsize=(9, 6.5), gridspec_kw={"height_ratios": [3, 1.3]})
        names = list(curves)
        for k, name in enumerate(names):
            tl.hlines(k, 0, hours or 0, color=f"C{k}", lw=2, alpha=0.5)
            for a in alarms.get(name, []):
                if a["cause"] == "offline":
                    continue
                h = a["raised_at"] / 3600
                tl.plot(h, k, "rv", ms=9)
                tl.annotate(f"{a['cause']} ({h:.2f} h)", (h, k), xytext=(6, 6), textcoords="offset points", fontsize=8)
        if knock is not None:
            k = names.index(knock[0])
            tl.plot(knock[1], k, "k|", ms=18, mew=2)
            tl.annotate("magnet knocked", (knock[1], k), xytext=(-80, -14), textcoords="offset points", fontsize=8)
        tl.set_yticks(range(len(names)), names, fontsize=8)
        tl.set_ylim(-0.7, len(names) - 0.3)
        tl.set_xlabel("drive time (h)")
        tl.set_title("Drift monitor: planted event (|) and alarms raised (▼)", fontsize=9)
        tl.grid(alpha=0.3)
    for k, (name, (temp, f, g)) in enumerate(curves.items()):
        idx = np.digitize(temp, edges) - 1
        centers = edges[:-1] + 2.5
        for err, style, label in ((f, "--", "factory"), (g, "-", "fleet")):
            per_bin = [rms(err[idx == i]) if np.any(idx == i) else np.nan for i in range(len(centers))]
            ax.plot(centers, per_bin, style, color=f"C{k}", label=f"{name} {label}")
    ax.set_xlabel("temperature (°C)")
    ax.set_ylabel("RMS angle error (°)")
    ax.set_title("Angle error across the cycle: factory (+20 °C) coefficients against the fleet's")
    ax.legend(fontsize=7, ncol=2)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def applied_set(store: Store, device: str) -> dict | None:
    """The newest coefficient set the agent acknowledged as applied."""
    applied = [a["version"] for a in store.acks(device) if a["status"] == "applied"]
    if not applied:
        return None
    version = max(applied)
    return store.coefficient_set(device, version)


def demo_pki(pki_dir: Path, names: list[str]) -> Path:
    """The demo's own CA, the service's certificate and signing key, one certificate per drive."""
    from encoder_fleet.pki import init_ca, issue
    from fleet_wire.security import ROLE_SERVICE, SERVICE_NAME

    init_ca(pki_dir)
    issue(pki_dir, SERVICE_NAME, ROLE_SERVICE)
    for name in names:
        issue(pki_dir, name)
    return pki_dir


def run_demo(
    *, devices: int, sim_hours: float, out_dir: Path, json_path: Path | None = None, insecure: bool = False
) -> int:
    out_dir = Path(out_dir)
    if out_dir.exists():
        shutil.rmtree(out_dir)
    (out_dir / "outbox").mkdir(parents=True)
    log_path = out_dir / "service.log"
    with to_file(log_path):  # the service's events in a file: stderr shows progress and the summary
        return _serve(
            devices=devices,
            sim_hours=sim_hours,
            out_dir=out_dir,
            log_path=log_path,
            json_path=json_path,
            insecure=insecure,
        )


def _serve(
    *, devices: int, sim_hours: float, out_dir: Path, log_path: Path, json_path: Path | None, insecure: bool
) -> int:
    """The demo's fleet: service, agents, summary (the service's log events go to log_path)."""
    db = out_dir / "fleet.sqlite"
    endpoint = loopback_endpoint()
    http_port = free_port()
    names = [f"drive-{i:03d}" for i in range(devices)]
    log = sys.stderr
    print(f"encoder-fleet demo: {devices} drives, {sim_hours:g} simulated hours each (-40…+85 °C cycles)", file=log)
    if insecure:
        pki, security_args = None, ["--insecure"]
        print("WARNING: demo --insecure: plain TCP, no certificates, no ACL, unsigned sets, open REST", file=log)
    else:
        endpoint = endpoint.replace("tcp/", "tls/", 1)
        pki = demo_pki(out_dir / "pki", names)
        security_args = ["--pki", str(pki)]
    store = Store.open(db, band_horizon_s=BAND_HORIZON_H * 3600.0)
    session = open_session(listen=[endpoint], pki=pki)
    service = FleetService(store, session, refit_interval_s=1.0, **service_security(store, pki)).start()
    auth = None
    if not insecure:
        auth = TokenAuth(store)
        token_file = auth.first_admin_token(out_dir / "admin-token")
    http = HttpServer(store, http_port, auth=auth).start()
    print(f"service: router {endpoint}, REST http://127.0.0.1:{http_port}/docs, database {db}", file=log)
    if pki is not None:
        print(f"security: PKI {pki} (mTLS, ACL, signed sets); admin REST token in {token_file}", file=log)
    agents = [
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "encoder_fleet.cli",
                "agent",
                "--device",
                name,
                "--seed",
                str(i),
                "--connect",
                endpoint,
                "--sim-hours",
                str(sim_hours),
                "--window-s",
                str(WINDOW_S),
                "--outbox",
                str(out_dir / "outbox" / f"{name}.sqlite"),
                *security_args,
            ]
            + (["--knock-at-hour", str(KNOCK_AT_HOUR)] if i == 0 and sim_hours > KNOCK_AT_HOUR else []),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i, name in enumerate(names)
    ]
    expected = devices * int(round(sim_hours * 3600 / WINDOW_S))
    try:
        with tqdm(total=expected, desc="windows stored", unit="win", file=log) as bar:
            while any(a.poll() is None for a in agents):
                stored = sum(d["windows"] for d in store.devices())
                bar.n = stored
                bar.set_postfix(rollouts=service.counters.rollouts, refresh=False)  # drawn once, below
                bar.refresh()
                time.sleep(0.5)
            bar.n = sum(d["windows"] for d in store.devices())
            bar.refresh()
        agent_logs = [a.communicate()[0].strip() for a in agents]
        failed = [(n, a.returncode, text) for n, a, text in zip(names, agents, agent_logs) if a.returncode != 0]
        if failed:
            for name, code, text in failed:
                print(f"agent {name} exited with {code}:\n{text}", file=log)
            return 1
        summary = {"devices": {}, "database": str(db)}
        curves = {}
        for i, name in enumerate(names):
            applied = applied_set(store, name)
            versions = sorted({a["version"] for a in store.acks(name) if a["status"] == "applied"})
            knocked = i == 0 and sim_hours > KNOCK_AT_HOUR
            curves[name] = errors(i, applied["bands"] if applied else None, knocked=knocked)
            summary["devices"][name] = {
                **score(i, applied["bands"] if applied else None, knocked=knocked),
                "windows": store.device(name)["windows"],
                "coefficient_versions": versions,
            }
        plot_path = out_dir / "angle-error-vs-temperature.png"
        knock = (names[0], KNOCK_AT_HOUR) if sim_hours > KNOCK_AT_HOUR else None
        alarms = {name: list(reversed(store.alarms(name))) for name in names}
        summary["planted"] = None if knock is None else {"device": knock[0], "cause": "offset_step", "hour": knock[1]}
        summary["alarms"] = [a for name in names for a in alarms[name] if a["cause"] != "offline"]
        summary["offline_alarms"] = sum(a["cause"] == "offline" for name in names for a in alarms[name])
        plot_errors(curves, plot_path, alarms=alarms, knock=knock, hours=sim_hours)
        summary["plot"] = str(plot_path)
        summary["mcap"] = []
        for name in names:  # one audit file per drive, DIR/<device>.mcap
            with open(out_dir / f"{name}.mcap", "wb") as out:
                export_mcap(store, name, out)
            summary["mcap"].append(str(out_dir / f"{name}.mcap"))
        summary["rejections"] = store.rejection_counts()
        summary["security"] = "insecure" if insecure else f"mTLS + ACL + signed sets, PKI {pki}"
    finally:
        for a in agents:
            if a.poll() is None:
                a.kill()
        http.stop()
        service.stop()
        session.close()
        store.close()
    summary["service_log"] = {"path": str(log_path), "events": log_path.read_text(encoding="utf-8").count("\n")}
    print(format_summary(summary))
    if json_path is not None:
        json_path.write_text(json.dumps(summary, indent=1) + "\n")
    return 0


def format_alarms(summary: dict) -> list[str]:
    planted = summary.get("planted")
    lines = [
        "Drift monitor" + (f": {planted['device']}'s magnet knocked at hour {planted['hour']:g}" if planted else "")
    ]
    for a in summary.get("alarms", []):
        delay = ""
        if planted and a["device"] == planted["device"] and a["cause"] == planted["cause"]:
            delay = f", detected {(a['raised_at'] - planted['hour'] * 3600) / 60:.0f} min after the knock"
        params = ", ".join(f"{k}={v:g}" for k, v in a["parameters"].items())
        lines.append(f"  ALARM {a['device']} {a['cause']} ({params}) at {a['raised_at'] / 3600:.2f} h{delay}")
        lines.append(f"        {a['evidence']}")
    if not summary.get("alarms"):
        lines.append("  no drift alarm")
    lines.append(f"  ({summary.get('offline_alarms', 0)} offline alarms: the agents ended with the run)")
    return lines


def format_summary(summary: dict) -> str:
    lines = [
        "",
        "Angle error over a -40…+85 °C cycle (degrees; noise-free signals, so it measures the coefficients)",
        "",
        f"{'device':<10} {'windows':>8} {'versions applied':<22} {'factory rms':>11} {'max':>7} "
        f"{'fleet rms':>10} {'max':>7} {'gain':>6}",
    ]
    for name, d in summary["devices"].items():
        versions = ",".join(map(str, d["coefficient_versions"])) or "-"
        if len(versions) > 22:
            versions = versions[:19] + "..."
        gain = d["rms_error_deg_factory"] / d["rms_error_deg_fleet"] if d["rms_error_deg_fleet"] > 0 else float("inf")
        lines.append(
            f"{name:<10} {d['windows']:>8} {versions:<22} {d['rms_error_deg_factory']:>11.3f} "
            f"{d['max_error_deg_factory']:>7.3f} {d['rms_error_deg_fleet']:>10.3f} "
            f"{d['max_error_deg_fleet']:>7.3f} {gain:>5.1f}x"
        )
    lines += [
        "",
        f"database: {summary['database']}",
        f"MCAP exports (open in Foxglove): {', '.join(summary['mcap'])}",
        f"plot: {summary['plot']}",
        f"service log: {summary['service_log']['path']} ({summary['service_log']['events']} events, JSON lines)",
        f"rejected messages: {summary['rejections'] or 'none'}",
        f"security: {summary.get('security', '?')}",
        "",
        *format_alarms(summary),
        "inspect: .venv/bin/encoder-fleet service --db "
        + summary["database"]
        + (
            " --insecure"
            if summary.get("security") == "insecure"
            else f" --pki {Path(summary['database']).parent / 'pki'}"
        )
        + " --http-port 8000, then http://127.0.0.1:8000/docs"
        + ("" if summary.get("security") == "insecure" else " (REST token: admin-token beside the database)"),
    ]
    return "\n".join(lines)
