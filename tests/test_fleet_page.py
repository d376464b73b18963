"""The fleet page in a real headless browser (Debian's chromium driven by playwright) against the real
service: it loads with no console error and no failed request, and shows the drives and their plots."""

from __future__ import annotations

import shutil

import pytest
from wire_samples import ack, coefficients, window

from fleet_wire.session import free_port
from service.rollout import Rollouts, RolloutSpec
from service.runtime import HttpServer
from service.store import Store

CHROMIUM = shutil.which("chromium")
playwright = pytest.importorskip("playwright.sync_api", reason="playwright is installed by make (dev extra)")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no chromium: `make test` installs Debian's as root")
# as the machine's own probe runs it: no sandbox as root, nothing that phones out
CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run"]
CHROMIUM_ARGS += ["--disable-background-networking", "--disable-component-update", "--disable-sync"]


@pytest.fixture
def served(tmp_path):
    store = Store.open(tmp_path / "fleet.sqlite")
    for device in ("drive-001", "drive-002"):
        for seq in range(1, 9):
            version = 0 if seq <= 4 else 1
            store.insert_window(window(device, seq=seq, version=version, temp_c=-10.0 + 10 * seq))
        store.insert_coefficient_set(coefficients(device, version=1, created_at=200.0))
        store.mark_published(device, 1)
        store.insert_ack(ack(device, version=1, at=210.0))
    # a planted alarm: what the drift monitor writes when drive-002's offsets jump
    step = {"kind": "raise", "cause": "offset_step", "at": 7200.0, "parameters": {"delta_d": 0.02, "delta_q": 0.0}}
    planted = [{**step, "evidence": "the offsets jumped (planted by the test)"}]
    (alarm,) = store.save_monitor("drive-002", {}, 8, planted, device_state="alarm")
    store.ack_alarm(alarm["id"], by="token 2 (ops desk)", note="magnet re-glued at the next stop")
    store.set_labels("drive-001", {"site": "plant-3"})
    store.set_labels("drive-002", {"site": "plant-7", "line": "1"})
    spec = {"change": {"kind": "reset_to_factory"}, "base_per_minute": 1, "soak_windows": 30}
    Rollouts(store).create(RolloutSpec(name="back to the bench", **spec))  # a rollout in progress
    port = free_port()
    http = HttpServer(store, port).start()
    yield f"http://127.0.0.1:{port}"
    http.stop()
    store.close()


def test_fleet_page_shows_the_drives_and_their_plots_without_errors(served):
    problems = []
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page()
        page.on("console", lambda m: problems.append(f"console {m.type}: {m.text}") if m.type == "error" else None)
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
        page.on("response", lambda r: problems.append(f"{r.status} {r.url}") if r.status >= 400 else None)
        page.goto(served + "/")
        page.wait_for_selector("#devices tbody tr[data-device='drive-002']")
        rows = page.locator("#devices tbody tr").all_inner_texts()
        assert [r.split("\t")[0] for r in rows] == ["drive-001", "drive-002"]
        # the monitor's state, not the token's: the page showed "offline" for both (GET /devices sent no state)
        assert [r.split("\t")[1] for r in rows] == ["unknown", "alarm"]
        assert page.locator("#states span").all_inner_texts() == ["unknown: 1", "alarm: 1"]
        page.wait_for_selector("#angle-error .main-svg")  # Plotly drew the first drive
        assert page.locator("#device-name").inner_text() == "drive-001"
        page.click("#devices tbody tr[data-device='drive-002']")
        page.wait_for_function("document.getElementById('device-name').textContent === 'drive-002'")
        traces = page.evaluate("document.getElementById('angle-error').data.map(t => [t.name, t.x.length])")
        assert traces == [["factory set", 4], ["fleet sets", 4]]
        history = page.locator("#coefficients tbody tr").all_inner_texts()
        assert history[0].startswith("v1\t") and "applied" in history[0]
        # the planted alarm: listed among the open ones, and on drive-002's timeline
        open_alarms = page.locator("#open-alarms tbody tr").all_inner_texts()
        assert [a.split("\t")[:3] for a in open_alarms] == [["drive-002", "offset_step", "2.00"]]
        assert open_alarms[0].split("\t")[4] == "token 2 (ops desk): magnet re-glued at the next stop"
        assert page.locator("#more-alarms").is_hidden()  # all of them listed
        timeline = page.evaluate("document.getElementById('alarm-timeline').data.map(t => [t.name, t.x])")
        assert timeline == [["offset_step (open)", [2.0, 3.0]]]
        assert [r.split("\t")[5] for r in rows] == ["site=plant-3", "line=1 site=plant-7"]
        # the fleet a site a row (GET /fleet/health/by/site), and a line a row once the label is chosen
        groups = page.locator("#groups tbody tr").all_inner_texts()
        assert [g.split("\t")[:2] for g in groups] == [["plant-3", "1"], ["plant-7", "1"]]
        assert groups[1].split("\t")[4] == "1" and groups[1].split("\t")[8] == "1"  # in alarm, one open alarm
        page.select_option("#by-label-name", "line")
        page.wait_for_function("document.querySelector('#groups tbody tr').cells[0].textContent === '1'")
        groups = page.locator("#groups tbody tr").all_inner_texts()
        assert [g.split("\t")[:2] for g in groups] == [["1", "1"], ["(no label)", "1"]]
        rollouts = page.locator("#rollouts tbody tr").all_inner_texts()
        assert [r.split("\t")[:6] for r in rollouts] == [
            ["1", "back to the bench", "reset_to_factory", "running", "1 of 2", "0 %"]
        ]
        browser.close()
    assert problems == []


def test_fleet_page_says_when_more_alarms_are_open_than_it_lists(tmp_path):
    """A fleet with more open alarms than the page lists (its first 200, GET /alarms being paged): the page says
    that more are open; it had listed the first page as if it were all."""
    store = Store.open(tmp_path / "fleet.sqlite")
    causes = ("offset_step", "gain_step", "offline")
    for i in range(67):  # 201 open alarms
        device = f"drive-{i:03d}"
        store.insert_window(window(device, seq=1))
        raised = [
            {"kind": "raise", "cause": c, "at": 60.0 * (i * 3 + k), "parameters": {}, "evidence": "planted"}
            for k, c in enumerate(causes)
        ]
        store.save_monitor(device, {}, 1, raised, device_state="alarm")
    port = free_port()
    http = HttpServer(store, port).start()
    problems = []
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page()
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            page.goto(f"http://127.0.0.1:{port}/")
            page.wait_for_selector("#more-alarms:not([hidden])")
            assert page.locator("#open-alarms tbody tr").count() == 200
            assert "more are open" in page.locator("#more-alarms").inner_text()
            newest = page.locator("#open-alarms tbody tr").first.inner_text().split("\t")[:2]
            assert newest == ["drive-066", "offline"]
            browser.close()
    finally:
        http.stop()
        store.close()
    assert problems == []


def test_fleet_page_asks_once_for_a_token_when_rest_needs_one(tmp_path):
    """With REST tokens on (service/auth.py): the page's shell and code load without one, its first data call
    gets 401, the page asks for a token once and keeps it for the session."""
    from service.auth import TokenAuth

    store = Store.open(tmp_path / "fleet.sqlite")
    for seq in range(1, 5):
        store.insert_window(window("drive-001", seq=seq))
    auth = TokenAuth(store)
    _, token = auth.create("read", "page")
    port = free_port()
    http = HttpServer(store, port, auth=auth).start()
    asked, unauthorized, problems = [], [], []
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
            page = browser.new_page()
            page.on("dialog", lambda d: (asked.append(d.message), d.accept(token)))
            page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
            page.on("requestfailed", lambda r: problems.append(f"request failed: {r.url}"))
            page.on(
                "response",
                lambda r: (unauthorized if r.status == 401 else problems).append(r.url) if r.status >= 400 else None,
            )
            page.goto(f"http://127.0.0.1:{port}/")
            page.wait_for_selector("#devices tbody tr[data-device='drive-001']")
            page.wait_for_selector("#angle-error .main-svg")
            browser.close()
    finally:
        http.stop()
        store.close()
    assert len(asked) == 1 and "token" in asked[0]
    assert [u.rsplit("/", 1)[-1] for u in unauthorized] == ["devices"] and problems == []


def test_the_by_label_table_shows_the_label_chosen_last_whichever_answer_comes_last(served):
    """Two labels chosen one after the other: the table showed the answer that came last, not the label chosen
    last (the select said site, the rows were the lines'). The first answer is held until the second is shown."""
    held, problems = [], []
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page()
        page.on("pageerror", lambda e: problems.append(f"page error: {e}"))
        page.goto(served + "/")
        page.wait_for_selector("#groups tbody tr")
        page.route(
            "**/fleet/health/by/line", lambda route: held.append(route)
        )  # answered only once the page asks for /release

        def release(route):
            route.fulfill(status=204)
            held.pop().continue_()

        page.route("**/release", release)
        shown = page.evaluate(
            """async () => {
              const devices = await getJson("/devices");
              const select = document.getElementById("by-label-name");
              select.value = "line";
              const first = showGroups(devices);
              select.value = "site";
              await showGroups(devices);
              await fetch("/release");
              await first;
              const rows = [...document.querySelectorAll("#groups tbody tr")];
              return [select.value, rows.map((r) => r.cells[0].textContent)];
            }"""
        )
        browser.close()
    assert shown == ["site", ["plant-3", "plant-7"]] and held == [] and problems == []
