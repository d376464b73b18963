"""The package as a user installs it: a wheel in a fresh venv, run from outside the repository; and the
one-line errors of a service that cannot start."""

from __future__ import annotations

import shutil
import socket
import sqlite3
import subprocess
import sys
import sysconfig
import time
import zipfile
from email.parser import Parser
from pathlib import Path

import pytest

from fleet_wire.session import free_port

REPO = Path(__file__).resolve().parent.parent
SERVICE_ONLY = ("fastapi", "uvicorn", "mcap", "matplotlib")


@pytest.fixture(scope="module")
def wheel(tmp_path_factory) -> Path:
    # built from a copy of the sources, so no build/ folder of an earlier build can leak into it
    src = tmp_path_factory.mktemp("src") / "encoder-fleet"
    shutil.copytree(
        REPO, src, symlinks=True, ignore=shutil.ignore_patterns(".git", ".venv", "out", "build", "*.egg-info")
    )
    out = tmp_path_factory.mktemp("wheel")
    subprocess.run(
        [sys.executable, "-m", "pip", "wheel", "--no-deps", "--quiet", "-w", str(out), str(src)],
        check=True,
        capture_output=True,
    )
    (found,) = out.glob("encoder_fleet-*.whl")
    return found


@pytest.fixture(scope="module")
def fresh_venv(tmp_path_factory, wheel) -> Path:
    """A new venv holding only the wheel; its dependencies are borrowed from this test run's site-packages
    through a .pth line (a .pth inside that folder is not processed, so this checkout stays invisible)."""
    venv = tmp_path_factory.mktemp("venv")
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    py = venv / "bin" / "python"
    subprocess.run(
        [str(py), "-m", "pip", "install", "--quiet", "--no-deps", "--no-index", str(wheel)],
        check=True,
        capture_output=True,
    )
    site = subprocess.run(
        [str(py), "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout.strip()
    (Path(site) / "borrowed_deps.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    return venv


def run(venv: Path, *args, cwd: Path, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run(
        [str(venv / "bin" / "encoder-fleet"), *args], cwd=cwd, capture_output=True, text=True, timeout=timeout
    )


def test_wheel_ships_schemas_and_migrations_and_an_agent_needs_no_service_packages(wheel):
    with zipfile.ZipFile(wheel) as whl:
        names = set(whl.namelist())
        meta = Parser().parsestr(whl.read(next(n for n in names if n.endswith(".dist-info/METADATA"))).decode())
    schemas = {p.name for p in (REPO / "schemas").glob("*.schema.json")}
    migrations = {p.name for p in (REPO / "migrations").glob("*.sql")}
    assert {f"fleet_wire/schemas/{n}" for n in schemas} <= names
    for package in ("encoder_core", "fleet_wire", "edge_agent", "service", "encoder_fleet"):
        for source in (REPO / package).rglob("*.py"):  # every module of the checkout is in the wheel
            assert str(source.relative_to(REPO)) in names, source
    assert {f"service/migrations/{n}" for n in migrations} <= names
    base = [r.split(";")[0].split("=")[0].strip() for r in meta.get_all("Requires-Dist") if "extra ==" not in r]
    assert "eclipse-zenoh" in base and "numpy" in base
    assert not set(base) & set(SERVICE_ONLY)


def test_installed_wheel_runs_help_diagnose_and_a_service_from_outside_the_repo(fresh_venv, tmp_path):
    where = subprocess.run(
        [str(fresh_venv / "bin" / "python"), "-c", "import fleet_wire; print(fleet_wire.__file__)"],
        cwd=tmp_path,
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert str(REPO) not in where and str(fresh_venv) in where  # the wheel's copy, not this checkout

    assert run(fresh_venv, "--help", cwd=tmp_path).returncode == 0
    rec = tmp_path / "bench.csv"
    assert run(fresh_venv, "simulate", "--out", str(rec), "--plateaus", "20", "40", cwd=tmp_path).returncode == 0
    diag = run(fresh_venv, "diagnose", str(rec), "--json", str(tmp_path / "d.json"), cwd=tmp_path)
    assert diag.returncode == 0, diag.stderr
    assert (tmp_path / "d.json").stat().st_size > 0

    db = tmp_path / "fleet.sqlite"
    zenoh_port, http_port = free_port(), free_port()
    service = subprocess.Popen(
        [str(fresh_venv / "bin" / "encoder-fleet"), "service", "--db", str(db)]
        + ["--insecure", "--listen", f"tcp/127.0.0.1:{zenoh_port}", "--http-port", str(http_port)],
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert service.stdout.readline().startswith("service: zenoh router on")
        with socket.create_connection(("127.0.0.1", http_port), timeout=5):
            pass
    finally:
        service.terminate()
        out, err = service.communicate(timeout=30)
    assert service.returncode == 0, err
    tables = {r[0] for r in sqlite3.connect(db).execute("SELECT name FROM sqlite_master WHERE type = 'table'")}
    assert {"devices", "windows", "coefficient_sets", "schema_migrations"} <= tables


def test_agent_modules_import_without_the_service_packages(fresh_venv, tmp_path):
    block = "; ".join(f"sys.modules[{m!r}] = None" for m in SERVICE_ONLY)  # any import of them now fails
    code = f"import sys; {block}; import edge_agent.agent, edge_agent.sources; from encoder_fleet.cli import main; "
    code += "sys.exit(main(['agent', '--help']))"
    done = subprocess.run([str(fresh_venv / "bin" / "python"), "-c", code], cwd=tmp_path, capture_output=True)
    assert done.returncode == 0, done.stderr.decode()


def cli(*args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "encoder_fleet.cli", *args], cwd=cwd, capture_output=True, text=True, timeout=60
    )


def assert_one_line_error(done: subprocess.CompletedProcess, *words: str) -> None:
    assert done.returncode == 2, (done.returncode, done.stderr)
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in done.stderr, done.stderr
    for word in words:
        assert word in lines[0], lines[0]


def test_service_on_a_taken_port_says_so_in_one_line(tmp_path):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        zenoh_taken = cli("service", "--db", str(tmp_path / "a.sqlite"), "--http-port", "0",
                          "--insecure", "--listen", f"tcp/127.0.0.1:{port}", cwd=tmp_path)  # fmt: skip
        http_taken = cli("service", "--db", str(tmp_path / "b.sqlite"), "--http-port", str(port),
                         "--insecure", "--listen", f"tcp/127.0.0.1:{free_port()}", cwd=tmp_path)  # fmt: skip
    assert_one_line_error(zenoh_taken, f"127.0.0.1:{port}")
    assert_one_line_error(http_taken, f"127.0.0.1:{port}", "REST")
    assert not (tmp_path / "a.sqlite").exists() and not (tmp_path / "b.sqlite").exists()  # a start that failed


def test_a_database_that_cannot_be_opened_is_one_line_not_a_traceback(tmp_path):
    garbage = tmp_path / "garbage.sqlite"
    garbage.write_bytes(b"this is not a database at all" * 200)
    started = time.monotonic()
    for db in (garbage, tmp_path):  # a file of junk; a directory
        done = cli("service", "--db", str(db), "--http-port", "0", "--insecure",
                   "--listen", f"tcp/127.0.0.1:{free_port()}", cwd=tmp_path)  # fmt: skip
        assert_one_line_error(done, str(db))
    assert time.monotonic() - started < 60  # and it exits, it does not hang
    assert_one_line_error(cli("export", "--db", str(garbage), "--device", "d", "--out", "x.mcap", cwd=tmp_path),
                          str(garbage))  # fmt: skip
    assert not (tmp_path / "x.mcap").exists()


def test_service_refuses_a_database_corrupt_mid_file_in_one_line(tmp_path):
    from wire_samples import window

    from service.store import Store

    path = tmp_path / "mid.sqlite"
    with Store.open(path) as s:
        for seq in range(1, 200):
            s.insert_window(window(seq=seq))
        s._rows("PRAGMA wal_checkpoint(TRUNCATE)")
    data = bytearray(path.read_bytes())
    data[5 * 4096 : 5 * 4096 + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    done = cli("service", "--db", str(path), "--http-port", "0", "--insecure",
               "--listen", f"tcp/127.0.0.1:{free_port()}", cwd=tmp_path)  # fmt: skip
    assert_one_line_error(done, str(path), "corrupt")
