"""docker-compose.yml: a zenohd router, the service and three agents, whose commands the CLI accepts."""

from pathlib import Path

import yaml

from encoder_fleet.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def test_compose_services_use_commands_that_exist():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert services["zenohd"]["image"].startswith("eclipse/zenoh")
    ours = {name: s for name, s in services.items() if s.get("image") == "encoder-fleet"}
    assert {"service", "agent-1", "agent-2", "agent-3"} <= set(ours)
    parser = build_parser()
    for name, svc in ours.items():
        args = parser.parse_args(svc["command"])  # exits (SystemExit) on an unknown command or flag
        assert args.command in ("service", "agent"), name
        if args.command == "agent":
            assert args.connect == ["tcp/zenohd:7447"] and args.source == "sim"
        else:
            assert args.connect == ["tcp/zenohd:7447"] and args.http_port == 8000
    devices = [parser.parse_args(s["command"]).device for s in ours.values() if s["command"][0] == "agent"]
    assert len(set(devices)) == 3


def test_image_builds_from_the_project_files():
    dockerfile = (ROOT / "Dockerfile").read_text()
    for line in dockerfile.splitlines():
        if line.startswith("COPY "):
            for src in line.split()[1:-1]:
                assert (ROOT / src).exists(), src
    assert 'ENTRYPOINT ["encoder-fleet"]' in dockerfile
