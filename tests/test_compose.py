"""docker-compose.yml: a zenohd router, the service and three agents, whose commands the CLI accepts."""

from pathlib import Path

import yaml

from encoder_fleet.cli import build_parser

ROOT = Path(__file__).resolve().parents[1]


def test_compose_services_use_commands_that_exist():
    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    services = compose["services"]
    assert services["zenohd"]["image"].startswith("eclipse/zenoh")
    ours = {name: s for name, s in services.items() if s.get("image") == "encoder-fleet" and "profiles" not in s}
    assert {"service", "agent-1", "agent-2", "agent-3"} <= set(ours)
    parser = build_parser()
    for name, svc in ours.items():
        if name == "pki":  # the one-shot job that makes the PKI, zenohd's config and Prometheus' token
            script = svc["command"][0]
            assert "pki init /pki" in script and "pki router-config /pki --name zenohd" in script
            for line in script.splitlines():
                if line.strip().startswith("encoder-fleet "):
                    words = line.strip().rstrip("\\").split()[1:]
                    parser.parse_args([w.replace('"$$d"', "drive-001") for w in words])
            continue
        args = parser.parse_args(svc["command"])  # exits (SystemExit) on an unknown command or flag
        assert args.command in ("service", "agent"), name
        assert args.pki == "/pki" and not args.insecure  # TLS with client certificates, signed sets
        if args.command == "agent":
            assert args.connect == ["tls/zenohd:7447"] and args.source == "sim"
        else:
            assert args.connect == ["tls/zenohd:7447"] and args.http_port == 8000
    devices = [parser.parse_args(s["command"]).device for s in ours.values() if s["command"][0] == "agent"]
    assert len(set(devices)) == 3
    assert services["zenohd"]["command"][:2] == ["-c", "/pki/zenohd.json5"]


def test_the_scale_profile_runs_three_members_on_postgresql_behind_two_meshed_routers(pki):
    from encoder_fleet.pki import issue, router_config
    from fleet_wire.security import ROLE_ROUTER

    compose = yaml.safe_load((ROOT / "docker-compose.yml").read_text())
    scale = {name: s for name, s in compose["services"].items() if "scale" in s.get("profiles", [])}
    parser = build_parser()
    assert scale["postgres"]["image"].startswith("postgres:15")
    routers = {n: s for n, s in scale.items() if s["image"].startswith("eclipse/zenoh")}
    assert sorted(routers) == ["zenohd-a", "zenohd-b"]
    ours = {n: parser.parse_args(s["command"]) for n, s in scale.items() if s["image"] == "encoder-fleet"}
    members = [a for a in ours.values() if a.command == "service"]
    assert len(members) == 3 and len({a.member for a in members}) == 3
    for args in members:
        assert args.db.startswith("postgresql://fleet@postgres:") and args.pki == "/pki" and not args.insecure
    assert {a.connect[0] for a in members} == {"tls/zenohd-a:7447", "tls/zenohd-b:7447"}
    agents = [a for a in ours.values() if a.command == "agent"]
    assert {a.connect[0] for a in agents} == {"tls/zenohd-a:7447", "tls/zenohd-b:7447"}
    # the routers' configs as the pki job writes them (its router-config lines), on a PKI of our own
    script = compose["services"]["pki"]["command"][0].replace("\\\n", " ")
    confs = {}
    for line in script.splitlines():
        if "router-config /pki --name zenohd-" in line:
            args = parser.parse_args(line.split()[1:])
            issue(pki, args.name, ROLE_ROUTER, force=True)
            confs[args.name] = router_config(
                pki, args.name, listen=["tls/0.0.0.0:7447"], connect=args.connect or [], peers=args.peer or []
            )
    assert confs["zenohd-b"]["connect"]["endpoints"] == ["tls/zenohd-a:7447"]  # meshed
    for name, other in (("zenohd-a", "zenohd-b"), ("zenohd-b", "zenohd-a")):
        trusted = confs[name]["access_control"]["subjects"][0]["cert_common_names"]
        assert other in trusted  # each trusts the other's link as it trusts the service
    for name, svc in scale.items():
        assert svc["restart"] == "on-failure", name
        assert all(p.startswith("127.0.0.1:") for p in svc.get("ports", [])), name
        for needed, condition in svc.get("depends_on", {}).items():
            assert needed == "pki" or (condition == {"condition": "service_healthy"} and "healthcheck" in scale[needed])


def test_image_builds_from_the_project_files():
    dockerfile = (ROOT / "Dockerfile").read_text()
    for line in dockerfile.splitlines():
        if line.startswith("COPY "):
            for src in line.split()[1:-1]:
                assert (ROOT / src).exists(), src
    assert 'ENTRYPOINT ["encoder-fleet"]' in dockerfile


def test_compose_waits_for_health_restarts_on_failure_and_binds_loopback():
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    assert {"zenohd", "service", "prometheus", "grafana"} <= set(services)
    for name, svc in services.items():
        assert svc.get("restart") == "on-failure", name
        for port in svc.get("ports", []):
            assert port.startswith("127.0.0.1:"), (name, port)  # nothing published beyond the host
        for needed in svc.get("depends_on", {}):
            if needed == "pki":  # a one-shot job: done, not healthy
                assert svc["depends_on"][needed] == {"condition": "service_completed_successfully"}, name
                continue
            assert svc["depends_on"][needed] == {"condition": "service_healthy"}, name
            assert "healthcheck" in services[needed], needed
    assert services["service"]["depends_on"] == {"zenohd": {"condition": "service_healthy"}}
    assert "/healthz" in " ".join(services["service"]["healthcheck"]["test"])
    for mount in services["prometheus"]["volumes"] + services["grafana"]["volumes"]:
        if mount.startswith("./"):  # bind mounts; named volumes (secrets) are compose's
            assert (ROOT / mount.split(":")[0]).exists(), mount


def scraped_metrics(tmp_path) -> str:
    """The real service's /metrics text, with a sample in every family (a rejection counted, an alarm open)."""
    from fastapi.testclient import TestClient

    from fleet_wire.session import loopback_endpoint
    from service.api import create_app
    from service.runtime import FleetService, open_session
    from service.store import Store

    store = Store.open(tmp_path / "f.sqlite")
    session = open_session(listen=[loopback_endpoint()])
    service = FleetService(store, session, refit_interval_s=0).start()
    try:
        service.counters.count("schema")  # so every family has a sample
        service.counters.count("device_retired")  # a retired drive's agent still sending (an alert leaves it out)
        step = {"kind": "raise", "cause": "offset_step", "at": 1.0, "parameters": {}, "evidence": "planted"}
        store.save_monitor("drive-001", {}, 0, [step])
        return TestClient(create_app(store, service)).get("/metrics").text
    finally:
        service.stop()
        session.close()
        store.close()


def test_prometheus_scrapes_the_service_and_the_dashboard_draws_metrics_it_exports(tmp_path):
    import json
    import re

    from prometheus_client.parser import text_string_to_metric_families

    scrape = yaml.safe_load((ROOT / "ops" / "prometheus.yml").read_text())["scrape_configs"][0]
    assert scrape["metrics_path"] == "/metrics" and scrape["static_configs"][0]["targets"] == ["service:8000"]
    assert scrape["authorization"] == {"type": "Bearer", "credentials_file": "/secrets/prometheus-token"}
    text = scraped_metrics(tmp_path)
    exported = {s.name for f in text_string_to_metric_families(text) for s in f.samples}
    dashboard = json.loads((ROOT / "ops" / "grafana" / "dashboards" / "encoder-fleet.json").read_text())
    drawn = {n for p in dashboard["panels"] for t in p["targets"] for n in re.findall(r"encoder_fleet_\w+", t["expr"])}
    assert drawn and drawn <= exported, drawn - exported
    # and the README's "ops/grafana draws every family": each family /metrics exports is in some panel
    families = {f.name for f in text_string_to_metric_families(text) if not f.name.endswith("_created")}
    drawn_families = {re.sub(r"_(total|bucket|count|sum)$", "", n) for n in drawn}
    assert families <= drawn_families, families - drawn_families


def selectors(node) -> list:
    """Every vector selector in a parsed PromQL expression (promql_parser's tree)."""
    import promql_parser

    if isinstance(node, promql_parser.VectorSelector):
        return [node]
    found = []
    for attr in ("lhs", "rhs", "expr", "param", "vector_selector"):
        child = getattr(node, attr, None)
        if child is not None and not isinstance(child, (str, int, float)):
            found += selectors(child)
    for arg in getattr(node, "args", None) or []:
        found += selectors(arg)
    return found


def test_the_alerting_rules_parse_and_read_only_metrics_and_labels_the_service_exports(tmp_path):
    """ops/alerts.yml: every expression is PromQL Prometheus parses, every metric it reads is one /metrics exports
    (or Prometheus's own `up` of this job), and every label value it matches exists: a rule on a misspelt metric
    or cause would never fire, and nobody would know."""
    import re

    import promql_parser
    from prometheus_client.parser import text_string_to_metric_families

    from encoder_core.monitor_causes import CAUSES

    config = yaml.safe_load((ROOT / "ops" / "prometheus.yml").read_text())
    assert config["rule_files"] == ["/etc/prometheus/alerts.yml"]
    mounts = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]["prometheus"]["volumes"]
    assert "./ops/alerts.yml:/etc/prometheus/alerts.yml:ro" in mounts
    samples = [s for f in text_string_to_metric_families(scraped_metrics(tmp_path)) for s in f.samples]
    labels: dict[tuple[str, str], set[str]] = {}
    for s in samples:
        for k, v in s.labels.items():
            labels.setdefault((s.name, k), set()).add(v)
    for family in ("encoder_fleet_open_alarms", "encoder_fleet_unacknowledged_alarms"):  # one planted; any may be open
        labels[(family, "cause")] |= set(CAUSES)
    rules = [r for g in yaml.safe_load((ROOT / "ops" / "alerts.yml").read_text())["groups"] for r in g["rules"]]
    assert len({r["alert"] for r in rules}) == len(rules) >= 8
    for rule in rules:
        assert rule["labels"]["severity"] in ("critical", "warning", "info"), rule["alert"]
        assert rule["annotations"]["summary"] and rule["annotations"]["description"], rule["alert"]
        read = selectors(promql_parser.parse(rule["expr"]))
        assert read, rule["alert"]
        for vs in read:
            if vs.name == "up":
                assert [(m.name, m.value) for m in vs.matchers.matchers] == [
                    ("job", config["scrape_configs"][0]["job_name"])
                ]
                continue
            assert any(s.name == vs.name for s in samples), (rule["alert"], vs.name)
            for m in vs.matchers.matchers:
                known = labels.get((vs.name, m.name), set())
                values = str(m.value).split("|") if "Re" in str(m.op) else [str(m.value)]
                missing = [v for v in values if v not in known]
                assert known and not missing, (rule["alert"], vs.name, m.name, missing)
        for text in rule["annotations"].values():  # templates name only what the expression keeps
            for label in re.findall(r"\$labels\.(\w+)", text):
                assert f"by ({label})" in rule["expr"], (rule["alert"], label)


def test_the_image_installs_the_extras_its_compose_commands_need(monkeypatch):
    """The scale profile's members run on PostgreSQL: an image built with `.[service]` alone lacked psycopg, so each
    member ended in a ModuleNotFoundError traceback at start, restarted for ever, and its drives never started."""
    import re
    import sys

    import pytest

    from service.store import Store, StoreError

    extras = re.search(r"pip install [^\n]*'\.\[([\w,]+)\]'", (ROOT / "Dockerfile").read_text()).group(1).split(",")
    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    parser = build_parser()
    commands = [
        parser.parse_args(s["command"])
        for s in services.values()
        if s.get("image") == "encoder-fleet" and s["command"][0] in ("service", "agent")
    ]
    if any(a.command == "service" for a in commands):
        assert "service" in extras
    if any(a.command == "service" and a.db.startswith("postgresql://") for a in commands):
        assert "postgres" in extras, extras
    # and where the extra is missing, the service says so in one line instead of a traceback
    monkeypatch.setitem(sys.modules, "psycopg", None)
    with pytest.raises(StoreError, match=r"encoder-fleet\[postgres\]"):
        Store.open("postgresql://fleet@127.0.0.1:1/fleet")


def test_the_compose_operator_gets_an_admin_token_and_prometheus_a_read_token(tmp_path):
    """The pki job made Prometheus' read token in the service's database before the service first started; the
    service writes its first admin token only into an empty token table, so /secrets/admin-token never appeared
    and nobody could create tokens or stage a rollout. The job's token lines, then what the service does at start."""
    import shlex

    from encoder_fleet.cli import main
    from service.auth import TokenAuth
    from service.store import Store

    services = yaml.safe_load((ROOT / "docker-compose.yml").read_text())["services"]
    script = services["pki"]["command"][0].replace("\\\n", " ")

    def here(path):
        return str(tmp_path / path.lstrip("/"))

    for line in script.splitlines():
        if line.strip().startswith("encoder-fleet token create"):
            words = shlex.split(line)[1:]
            assert main([here(w) if w.startswith(("/data/", "/secrets/")) else w for w in words]) == 0
    service = build_parser().parse_args(services["service"]["command"])
    store = Store.open(here(service.db))
    try:
        auth = TokenAuth(store)
        auth.first_admin_token(here(service.admin_token_file))  # the service at first start (runtime.run_service)
        admin = Path(here(service.admin_token_file))
        assert admin.is_file(), "no admin token for the operator"
        assert auth.scope_of(admin.read_text().strip()) == "admin"
        credentials = yaml.safe_load((ROOT / "ops" / "prometheus.yml").read_text())["scrape_configs"][0]
        scraper = Path(here(credentials["authorization"]["credentials_file"]))
        assert auth.scope_of(scraper.read_text().strip()) == "read"
    finally:
        store.close()
    # the scale members share one database: only the first to start writes a token, so they name one file
    parser = build_parser()
    members = [parser.parse_args(s["command"]) for s in services.values() if "--member" in s.get("command", [])]
    assert len(members) == 3 and len({m.admin_token_file for m in members}) == 1


def test_every_alarm_cause_is_watched_by_an_alerting_rule():
    """Each cause the drift monitor raises is watched by a rule on the unacknowledged alarms, but `offline` (which
    EncoderFleetManyOffline watches fleet-wide): the `outliers` cause (a sensor dropping reads, samples off the
    circle) was in none, so an open outliers alarm paged nobody, while the README said sensor alarms alert."""
    import promql_parser

    from encoder_core.monitor_causes import CAUSES

    rules = [r for g in yaml.safe_load((ROOT / "ops" / "alerts.yml").read_text())["groups"] for r in g["rules"]]
    watched = set()
    for rule in rules:
        for vs in selectors(promql_parser.parse(rule["expr"])):
            if vs.name == "encoder_fleet_unacknowledged_alarms":
                watched |= {v for m in vs.matchers.matchers if m.name == "cause" for v in str(m.value).split("|")}
    assert watched == set(CAUSES) - {"offline"}, set(CAUSES) - {"offline"} - watched
    offline = [r for r in rules if r["alert"] == "EncoderFleetManyOffline"]
    assert offline and 'encoder_fleet_devices{state="offline"}' in offline[0]["expr"]


def test_a_retired_drive_still_sending_does_not_fire_the_rejections_alert():
    """A retired drive's agent, still running (moved to a test bench), resends up to 500 windows of its outbox with
    every window, each refused as device_retired: in a fleet of fewer than ~9,500 drives that alone was more than 5 %
    of the messages, and EncoderFleetRejectionsHigh fired for as long as the drive stayed retired."""
    import promql_parser

    rules = {
        r["alert"]: r for g in yaml.safe_load((ROOT / "ops" / "alerts.yml").read_text())["groups"] for r in g["rules"]
    }
    read = selectors(promql_parser.parse(rules["EncoderFleetRejectionsHigh"]["expr"]))
    rejections = [vs for vs in read if vs.name == "encoder_fleet_ingest_rejections_total"]
    assert len(rejections) == 2
    for vs in rejections:
        assert [(m.name, str(m.op), m.value) for m in vs.matchers.matchers] == [
            ("reason", str(promql_parser.MatchOp.NotEqual), "device_retired")
        ]
