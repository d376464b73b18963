// The fleet page: everything it shows comes from the service's own REST API, plots by Plotly.js
// (served by the service from the plotly package, so the page works without internet).
"use strict";

// REST needs a bearer token (service/auth.py): asked once, kept in this browser's sessionStorage
const TOKEN_KEY = "encoder-fleet-token";

async function getJson(path, retried = false) {
  const headers = { Accept: "application/json" };
  const token = sessionStorage.getItem(TOKEN_KEY);
  if (token) headers.Authorization = `Bearer ${token}`;
  const response = await fetch(path, { headers });
  if (response.status === 401 && !retried) {
    const given = window.prompt("REST token (encoder-fleet token create --scope read)");
    if (given) {
      sessionStorage.setItem(TOKEN_KEY, given.trim());
      return getJson(path, true);
    }
  }
  if (!response.ok) throw new Error(`${path}: ${response.status}`);
  return response.json();
}

function cell(row, text, className) {
  const td = row.insertCell();
  td.textContent = text;
  if (className) td.className = className;
  return td;
}

function deviceState(device) {
  return device.state || (device.online ? "online" : "offline");
}

async function showFleet() {
  const devices = await getJson("/devices");
  const counts = {};
  for (const d of devices) counts[deviceState(d)] = (counts[deviceState(d)] || 0) + 1;
  const chips = document.getElementById("states");
  chips.replaceChildren(
    ...Object.entries(counts).map(([state, n]) => {
      const span = document.createElement("span");
      span.className = `state-${state}`;
      span.textContent = `${state}: ${n}`;
      return span;
    }),
  );
  const body = document.querySelector("#devices tbody");
  body.replaceChildren();
  for (const d of devices) {
    const row = body.insertRow();
    row.dataset.device = d.id;
    cell(row, d.id);
    cell(row, deviceState(d), `state-${deviceState(d)}`);
    cell(row, d.windows);
    cell(row, d.current_version === null ? "–" : `v${d.current_version}`);
    cell(row, new Date(d.last_seen * 1000).toLocaleString());
    cell(row, Object.entries(d.labels || {}).map(([k, v]) => `${k}=${v}`).join(" "));  // PUT /devices/{id}/labels
    row.addEventListener("click", () => showDevice(d.id));
  }
  await showGroups(devices);
  await showOpenAlarms();
  await showRollouts();
  if (devices.length) await showDevice(devices[0].id);
}

// the fleet a value of a label a row (GET /fleet/health/by/{label}), for the label names the devices carry
async function showGroups(devices) {
  const names = [...new Set(devices.flatMap((d) => Object.keys(d.labels || {})))].sort();
  const select = document.getElementById("by-label-name");
  document.getElementById("by-label").hidden = names.length === 0;
  if (!names.length) return;
  const chosen = names.includes(select.value) ? select.value : names.includes("site") ? "site" : names[0];
  select.replaceChildren(...names.map((n) => new Option(n, n, false, n === chosen)));
  select.onchange = () => showGroups(devices).catch((error) => console.error(error));
  const { groups } = await getJson(`/fleet/health/by/${encodeURIComponent(chosen)}`);
  if (select.value !== chosen) return; // another label was chosen meanwhile: its answer is (or will be) shown
  const body = document.querySelector("#groups tbody");
  body.replaceChildren();
  for (const g of groups) {
    const row = body.insertRow();
    cell(row, g.value === null ? "(no label)" : g.value);
    cell(row, Object.values(g.devices).reduce((a, b) => a + b, 0));
    for (const state of ["ok", "watch", "alarm", "offline", "unknown", "retired"]) {
      cell(row, g.devices[state] || 0, g.devices[state] && state !== "ok" ? `state-${state}` : undefined);
    }
    cell(row, Object.values(g.open_alarms).reduce((a, b) => a + b, 0));
    cell(row, g.silent);
  }
}

// the newest open alarms, a glance's worth: the device table's states say which drives hold the rest
const OPEN_ALARMS_SHOWN = 200;

async function showOpenAlarms() {
  // a retired drive's alarms stay in its history, not on the fleet's glance
  const { alarms, truncated } = await getJson(`/alarms?open=true&in_fleet=true&limit=${OPEN_ALARMS_SHOWN}`);
  document.getElementById("no-alarms").hidden = alarms.length > 0;
  const more = document.getElementById("more-alarms");
  more.hidden = !truncated;
  more.textContent = truncated
    ? `The newest ${alarms.length} open alarms; more are open (GET /alarms?open=true pages through them all).`
    : "";
  const body = document.querySelector("#open-alarms tbody");
  body.replaceChildren();
  for (const a of alarms) {
    const row = body.insertRow();
    row.dataset.device = a.device;
    cell(row, a.device);
    cell(row, a.cause, "state-alarm");
    cell(row, (a.raised_at / 3600).toFixed(2));
    cell(row, a.evidence);
    cell(row, a.acked_by ? `${a.acked_by}: ${a.ack_note}` : "");  // POST /alarms/{id}/ack
    row.addEventListener("click", () => showDevice(a.device));
  }
}

// staged rollouts (service/rollout.py), the running and paused ones first
async function showRollouts() {
  const rollouts = await getJson("/rollouts");
  const order = { running: 0, paused: 1 };
  rollouts.sort((a, b) => (order[a.state] ?? 2) - (order[b.state] ?? 2) || b.id - a.id);
  document.getElementById("no-rollouts").hidden = rollouts.length > 0;
  const body = document.querySelector("#rollouts tbody");
  body.replaceChildren();
  for (const r of rollouts) {
    const row = body.insertRow();
    row.dataset.rollout = r.id;
    cell(row, r.id);
    cell(row, r.name);
    cell(row, r.spec.change.kind);
    cell(row, r.state, r.state === "aborted" || r.state === "paused" ? "state-alarm" : undefined);
    cell(row, `${r.wave + 1} of ${r.waves.length}`);
    cell(row, `${r.percent_done} %`);
    cell(row, Object.entries(r.by_state).map(([s, n]) => `${s} ${n}`).join(", "));
    cell(row, r.reason || "");
  }
}

// each alarm a bar on the drive's clock, one row per cause; an open one runs on to `now`
function alarmTraces(alarms, now) {
  return alarms.map((a) => {
    const end = a.cleared_at === null ? Math.max(now, a.raised_at) : a.cleared_at;
    return {
      name: `${a.cause}${a.cleared_at === null ? " (open)" : ""}`,
      x: [a.raised_at / 3600, end / 3600],
      y: [a.cause, a.cause],
      text: [a.evidence, a.cleared_at === null ? "open" : "cleared"],
      mode: "lines+markers",
      type: "scatter",
      line: { width: 8 },
    };
  });
}

async function showDevice(id) {
  const name = encodeURIComponent(id);
  const [errors, history, alarmList] = await Promise.all([
    getJson(`/devices/${name}/angle-error`),
    getJson(`/devices/${name}/coefficients`),
    getJson(`/alarms?device=${name}`),
  ]);
  document.getElementById("device").hidden = false;
  document.getElementById("device-name").textContent = id;
  const traces = ["factory", "fleet"].map((basis) => {
    const points = errors.bands.filter((b) => b.basis === basis);
    return {
      name: basis === "factory" ? "factory set" : "fleet sets",
      x: points.map((b) => b.temp_c),
      y: points.map((b) => b.angle_error_deg),
      text: points.map((b) => `${b.windows} windows`),
      mode: "lines+markers",
      type: "scatter",
    };
  });
  Plotly.react("angle-error", traces, {
    title: { text: `Angle error against temperature (${errors.metric})` },
    xaxis: { title: { text: "temperature (°C)" } },
    yaxis: { title: { text: "angle error (°)" }, rangemode: "tozero" },
    margin: { t: 40, r: 10 },
  }, { displaylogo: false, responsive: true });
  const times = alarmList.alarms.map((a) => a.cleared_at ?? a.raised_at);
  const now = times.length ? Math.max(...times) + 3600 : 0; // open alarms drawn an hour past the newest event
  Plotly.react("alarm-timeline", alarmTraces(alarmList.alarms, now), {
    title: { text: alarmList.alarms.length ? "Alarms on the drive's clock" : "No alarms" },
    xaxis: { title: { text: "drive time (h)" } },
    yaxis: { type: "category" },
    showlegend: false,
    margin: { t: 40, r: 10, l: 130 },
    height: 80 + 40 * new Set(alarmList.alarms.map((a) => a.cause)).size,
  }, { displaylogo: false, responsive: true });
  const body = document.querySelector("#coefficients tbody");
  body.replaceChildren();
  for (const set of history.sets) {
    const row = body.insertRow();
    cell(row, `v${set.version}`);
    cell(row, set.basis);
    cell(row, set.state || "–", set.state === "rolled_back" ? "state-alarm" : undefined);
    cell(row, set.created_at.toFixed(0));
    cell(row, set.published_at === null ? "no" : new Date(set.published_at * 1000).toLocaleString());
    cell(row, set.acks.map((a) => a.status).join(", ") || "–");
  }
}

showFleet().catch((error) => console.error(error));
