"""The layer drawing of docs/architecture.md, checked on every import statement: no arrow points up."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
# package -> the project packages it may import (besides itself)
ALLOWED = {
    "encoder_core": set(),
    "fleet_wire": {"encoder_core"},
    "edge_agent": {"encoder_core", "fleet_wire"},
    "service": {"encoder_core", "fleet_wire"},
    "encoder_fleet": {"encoder_core", "fleet_wire", "edge_agent", "service"},
}


def imported_packages(path: Path) -> set[str]:
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found |= {alias.name.split(".")[0] for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            found.add(node.module.split(".")[0])
    return found & set(ALLOWED)


@pytest.mark.parametrize("package", sorted(ALLOWED))
def test_no_package_imports_one_above_it(package):
    for path in sorted((REPO / package).rglob("*.py")):
        wrong = imported_packages(path) - ALLOWED[package] - {package}
        assert not wrong, f"{path.relative_to(REPO)} imports {sorted(wrong)}, above {package} in the layer drawing"


def test_diagnose_and_the_core_need_neither_zenoh_nor_the_wire():
    for path in (REPO / "encoder_core").rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names = {a.name.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        names |= {n.module.split(".")[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not names & {"zenoh", "jsonschema", "fastapi", "sqlite3"}, path


def test_the_diagnose_command_loads_no_zenoh_and_no_wire(tmp_path):
    import subprocess
    import sys

    rec = tmp_path / "bench.csv"
    code = (
        "import sys; from encoder_fleet.cli import main; "
        f"assert main(['simulate', '--out', {str(rec)!r}, '--plateaus', '20', '40']) == 0; "
        f"assert main(['diagnose', {str(rec)!r}]) == 0; "
        "heavy = ('zenoh', 'jsonschema', 'fleet_wire.messages', 'fleet_wire.session', 'service', 'edge_agent'); "
        "loaded = sorted(m for m in sys.modules if m.startswith(heavy)); "
        "print('LOADED', loaded)"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "LOADED []" in done.stdout
