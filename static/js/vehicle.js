// Vehicle page: live values per unit, charts over a chosen range, the status-flag timeline,
// the fault history, identity, CSV export, and the operator controls.

import { api } from "./api.js";
import { ALL_FIELDS, ChartSet, rowsFromHistory, toCsv } from "./charts.js";
import { controlPanel } from "./controls.js";
import {
  amps,
  celsius,
  clockTime,
  dateTime,
  deltaVolts,
  duration,
  esc,
  fileStamp,
  minutes,
  percent,
  volts,
} from "./format.js";
import { askComment, canAcknowledge } from "./alerts.js";
import { imbalance, putAlert, sortedAlerts, subscribe, vehicles } from "./store.js";

const RANGES = { hour: 3600, day: 86400, week: 7 * 86400 };
const FAULT_FLAGS = new Set(["ex24f", "ex12f", "exgnf", "ovf", "uvf", "imb", "eqflt", "io_in_sdn", "vcfl", "vcfh", "eq_battflt"]);
const FLAG_LABEL = {
  state_can_jso: "Jump-start override",
  state_onoff_en: "CAN on/off enabled",
  ex24f: "EX24F 24 V input",
  ex12f: "EX12F 12 V output",
  exgnf: "EXGNF ground",
  ovf: "OVF overvoltage",
  uvf: "UVF undervoltage",
  imb: "IMB imbalance",
  eqrn: "Equalizer running",
  eqflt: "EQFLT equalizer fault",
  io_in_sdn: "Shutdown input",
  vcfl: "VCFL",
  vcfh: "VCFH",
  can_ss_msg_on: "Smart Sensor msgs",
  eq_state_onoff: "Equalizer on (CAN)",
  eq_battflt: "Battery fault",
};
const flagLabel = (f) => FLAG_LABEL[f] || f;

// Every reading (3 s apart) up to two hours, about 2400 points, which uPlot draws at once; the
// API's rollups (1m, 15m, 1h, 1d, picked by span) beyond that.
const RAW_UP_TO_S = 2 * 3600;
const bucketFor = (span) => (span <= RAW_UP_TO_S ? "raw" : "auto");

/** A chart row from a live frame (voltages, or a battery-states frame with SOC or SOH). */
function liveRow(slot, ts, f) {
  if (slot === "voltages") return { ts, v12: f.v12, v24: f.v24, i12: f.i12 ?? null, i24: f.i24 ?? null };
  const battery = { "battery_states/1": "soh_12v", "battery_states/3": "soh_24v" }[slot];
  if (battery) return { ts, [battery]: f.soh };
  const soc = { "battery_states/2": "soc_12v", "battery_states/4": "soc_24v" }[slot];
  if (soc) return { ts, [soc]: f.soc };
  return null;
}

function toLocalInput(ts) {
  const d = new Date(ts * 1000 - new Date().getTimezoneOffset() * 60000);
  return d.toISOString().slice(0, 16);
}

function liveValuesHtml(u, diag) {
  const f = (slot, key) => u.latest[slot]?.fields?.[key] ?? null;
  const temp = f("battery_states/5", "temperature_c");
  const cell = (label, value, field) => `<div><dt>${label}</dt><dd${field ? ` data-field="${field}"` : ""}>${value}</dd></div>`;
  const flags = Object.entries(u.flags || {});
  const faults = [...u.faults.values()];
  const imb = imbalance(u);
  return `
    <dl class="values">
      ${cell("V12 battery A", volts(u.v12), "v12")}
      ${cell("V24 system", volts(u.v24), "v24")}
      ${cell("Battery B", volts(u.v24 == null || u.v12 == null ? null : u.v24 - u.v12))}
      ${cell("B − A", `<span class="${imb !== null && Math.abs(imb) > 0.1 ? "warn" : ""}">${deltaVolts(imb)}</span>`, "imbalance")}
      ${u.latest.voltages?.fields?.i12 != null ? cell("I12", amps(u.i12)) + cell("I24", amps(u.i24)) : ""}
      ${u.soc_12v != null ? cell("SOC A", percent(u.soc_12v)) + cell("SOC B", percent(u.soc_24v)) : ""}
      ${u.soh_12v != null ? cell("SOH A", percent(u.soh_12v)) + cell("SOH B", percent(u.soh_24v)) : ""}
      ${f("battery_states/2", "dod") != null ? cell("DOD A", percent(f("battery_states/2", "dod"))) + cell("DOD B", percent(f("battery_states/4", "dod"))) : ""}
      ${f("battery_states/1", "runtime_min") != null ? cell("Run time A", minutes(f("battery_states/1", "runtime_min"))) + cell("Run time B", minutes(f("battery_states/3", "runtime_min"))) : ""}
      ${temp != null ? cell("Temperature", celsius(temp)) : ""}
    </dl>
    ${
      u.state === "parked"
        ? `<p class="diag" data-condition="parked"><b>Parked</b>: ${esc(`ignition off, last heard ${clockTime(u.last_seen)}; the values are from then`)}</p>`
        : `<p class="diag" data-condition="${u.online ? diag?.condition || "unknown" : "offline"}"><b>${u.online ? "Diagnosis" : "Offline"}</b>: ${esc(u.online ? diag?.text || "—" : `last heard ${dateTime(u.last_seen)}`)}</p>`
    }
    <ul class="faults" aria-label="Active faults">${faults
      .map((x) => `<li class="fault" data-fault="${esc(x.fault)}">${esc(x.fault)}${x.occurrence_count ? ` <span class="count">×${x.occurrence_count}</span>` : ""} <span class="count">since ${esc(clockTime(x.started_at))}</span></li>`)
      .join("")}</ul>
    <ul class="flags" aria-label="Status flags">${flags
      .map(([k, v]) => `<li class="flag ${v === "active" ? "on" : ""} ${FAULT_FLAGS.has(k) ? "faulty" : ""}" title="${esc(k)}: ${esc(v)}">${esc(flagLabel(k))}${v !== "active" && v !== "inactive" ? ` (${esc(v.replaceAll("_", " "))})` : ""}</li>`)
      .join("")}</ul>`;
}

function identityHtml(u) {
  return `<div class="identity">
    <span>SA <b>${u.unit}</b></span>
    <span>Series <b>${u.series ? `${u.series}` : "—"}</b></span>
    <span>Model <b>${esc(u.model || "—")}</b></span>
    <span>Software <b>${esc(u.software_id || "—")}</b></span>
    <span>Last heard <b data-field="last_seen">${dateTime(u.last_seen)}</b></span>
  </div>`;
}

function timelineHtml(changes, from, to, initial) {
  // Each flag's active periods from the stored changes (the flags after each change).
  const span = to - from;
  const periods = new Map();
  let state = initial || {};
  let at = from;
  const close = (flags, until) => {
    for (const [k, v] of Object.entries(flags)) {
      if (!periods.has(k)) periods.set(k, []);
      if (v === "active") periods.get(k).push([at, until]);
    }
  };
  for (const c of changes) {
    close(state, c.ts);
    state = c.flags;
    at = c.ts;
  }
  close(state, to);
  const active = [...periods.entries()].filter(([, p]) => p.length);
  const never = [...periods.keys()].filter((k) => !periods.get(k).length);
  if (!periods.size) return '<p class="muted">No status frames stored in this range.</p>';
  const pct = (t) => (((Math.min(Math.max(t, from), to) - from) / span) * 100).toFixed(3);
  return `
    <div class="timeline">
      ${active
        .map(
          ([k, ps]) => `<div>${esc(flagLabel(k))}</div><div class="lane" role="img" aria-label="${esc(flagLabel(k))} active ${ps.length} time(s)">${ps
            .map(([a, b]) => `<span class="seg ${FAULT_FLAGS.has(k) ? "faulty" : ""}" data-left="${pct(a)}" data-width="${(pct(b) - pct(a)).toFixed(3)}" title="${dateTime(a)} – ${dateTime(b)}"></span>`)
            .join("")}</div>`,
        )
        .join("")}
      <div></div><div class="axis"><span>${dateTime(from)}</span><span>${dateTime(to)}</span></div>
    </div>
    ${never.length ? `<p class="muted">Never active in this range: ${never.map((k) => esc(flagLabel(k))).join(", ")}.</p>` : ""}`;
}

function faultsHtml(body, units) {
  const rows = body.episodes;
  if (!rows.length) return '<p class="muted">No fault in this range.</p>';
  const many = units > 1;
  return `<div class="table-wrap"><table>
    <thead><tr><th>Fault</th>${many ? "<th>Unit</th>" : ""}<th>State</th><th>Start</th><th>End</th><th>Duration</th><th>Occurrences</th><th>Ended by</th></tr></thead>
    <tbody>${rows
      .map((e) => {
        const end = e.ended_at;
        const dur = (end ?? Date.now() / 1000) - e.started_at;
        return `<tr data-fault="${esc(e.fault)}"><td><b>${esc(e.fault)}</b></td>${many ? `<td>SA ${e.sa}</td>` : ""}<td>${esc(e.state)}</td><td>${dateTime(e.started_at)}</td><td>${end ? dateTime(end) : "ongoing"}</td><td>${duration(dur)}${end ? "" : " so far"}</td><td>${e.occurrence_count ?? "—"}</td><td>${esc(e.ended_by || "")}</td></tr>`;
      })
      .join("")}</tbody></table></div>`;
}

export function renderVehicle(main, vehicleId, session) {
  // A person's groups may make them an operator of one depot and a viewer of another: the
  // vehicle's own role decides (its depot is known once the fleet has loaded).
  const canOperate = () => canAcknowledge(session, vehicleId);
  const view = { range: "hour", from: 0, to: 0, unit: null, diag: new Map(), panels: new Map() };
  main.innerHTML = `
    <section class="page vehicle">
      <a class="back" href="#/">← Fleet</a>
      <div class="page-head"><h1 id="v-title">${esc(vehicleId)}</h1><span id="v-sub" class="muted"></span></div>
      <section class="block v-alerts" aria-labelledby="h-valerts" id="v-alerts">
        <h2 id="h-valerts">Open alerts <span class="muted" id="v-alert-count"></span></h2>
        <p class="error" id="ack-error" role="alert"></p>
        <ul class="alert-cards" id="v-alert-list"></ul>
      </section>
      <div class="units" id="units"><p class="muted">Loading…</p></div>
      <section class="block" aria-labelledby="h-charts">
        <h2 id="h-charts">History</h2>
        <div class="toolbar" role="group" aria-label="Chart range">
          <label id="unit-pick" hidden>Unit <select id="unit-select"></select></label>
          <button type="button" class="btn btn-small" data-range="hour">Last hour</button>
          <button type="button" class="btn btn-small" data-range="day">Last day</button>
          <button type="button" class="btn btn-small" data-range="week">Last week</button>
          <span class="sep"></span>
          <label>From <input type="datetime-local" id="c-from"></label>
          <label>To <input type="datetime-local" id="c-to"></label>
          <button type="button" class="btn btn-small" id="c-apply">Show</button>
          <span class="sep"></span>
          <button type="button" class="btn btn-small" id="zoom-reset" disabled>Reset zoom</button>
          <button type="button" class="btn btn-small" id="csv">Export CSV</button>
          <span class="muted" id="bucket"></span>
        </div>
        <p class="muted">Drag across a chart to zoom; double-click or “Reset zoom” to go back.</p>
        <div class="charts" id="charts"></div>
      </section>
      <section class="block" aria-labelledby="h-flags">
        <h2 id="h-flags">Status flags</h2>
        <div id="timeline" class="panel"><p class="muted">Loading…</p></div>
      </section>
      <section class="block" aria-labelledby="h-faults">
        <h2 id="h-faults">Fault history</h2>
        <div id="fault-summary"></div>
        <div id="fault-table" class="panel"><p class="muted">Loading…</p></div>
      </section>
    </section>`;
  const $ = (sel) => main.querySelector(sel);
  const unitsEl = $("#units");
  const charts = new ChartSet($("#charts"), {
    onZoom: (zoomed) => {
      $("#zoom-reset").disabled = !zoomed;
    },
  });
  let disposed = false;

  function vehicle() {
    return vehicles.get(vehicleId);
  }
  function units() {
    return [...(vehicle()?.units.values() || [])].sort((a, b) => a.unit - b.unit);
  }

  function drawUnits() {
    const v = vehicle();
    if (!v) {
      unitsEl.innerHTML = `<p class="error">No vehicle ${esc(vehicleId)}.</p>`;
      return;
    }
    $("#v-title").textContent = v.name;
    const online = units().some((u) => u.online);
    // Parked and offline say since when (the bus fell silent; the unit was last heard).
    const silentSince = Math.max(0, ...units().filter((u) => !u.online).map((u) => u.last_seen || 0));
    const badge =
      v.state === "parked"
        ? `<span class="state parked">Parked</span> <span class="since">since ${esc(clockTime(v.parked_since || v.last_heard))}</span>`
        : v.state === "not_reporting"
          ? `<span class="state off">Not reporting</span> <span class="since">since ${esc(clockTime(v.last_heard))}</span>`
          : online
            ? '<span class="state on">Online</span>'
            : `<span class="state off">Offline</span> <span class="since">since ${esc(clockTime(silentSince || v.last_heard))}</span>`;
    $("#v-sub").innerHTML = `${esc(v.depot || "no depot")} · ${badge}`;
    if (!units().length) {
      unitsEl.innerHTML = '<p class="muted">No unit heard yet.</p>';
      return;
    }
    unitsEl.querySelector(":scope > p")?.remove();
    for (const u of units()) {
      let panel = view.panels.get(u.key);
      if (!panel) {
        const el = document.createElement("article");
        el.className = "panel unit-panel";
        el.dataset.unit = u.unit;
        el.innerHTML = `<h2>Unit SA ${u.unit}</h2><div class="ident"></div><div class="live"></div>`;
        panel = { el, controls: null };
        unitsEl.append(el);
        view.panels.set(u.key, panel);
      }
      if (!panel.controls && canOperate()) {
        // Control and parameter frames are broadcasts: every unit on the bus acts on them.
        panel.controls = controlPanel(vehicleId, u, () => units().filter((x) => x.bus === u.bus));
        panel.el.append(panel.controls.el);
      }
      panel.el.querySelector(".ident").innerHTML = identityHtml(u);
      panel.el.querySelector(".live").innerHTML = liveValuesHtml(u, view.diag.get(u.key));
      panel.controls?.update(u);
    }
    const sel = $("#unit-select");
    if (sel.options.length !== units().length) {
      sel.innerHTML = units().map((u) => `<option value="${u.unit}">SA ${u.unit}</option>`).join("");
      if (view.unit !== null) sel.value = view.unit;
    }
    $("#unit-pick").hidden = units().length < 2;
  }

  $("#v-alerts").hidden = !session.features?.alerts;
  function drawAlerts() {
    const list = sortedAlerts(vehicleId);
    $("#v-alert-count").textContent = `(${list.length})`;
    const box = $("#v-alert-list");
    const hadFocus = box.contains(document.activeElement);
    box.innerHTML = list.length
      ? list
          .map(
            (a) => `<li class="alert-card" data-alert="${a.id}" data-rule="${esc(a.rule)}" data-state="${esc(a.state)}" data-severity="${esc(a.severity)}">
          <div class="ac-head"><span class="sev" data-severity="${esc(a.severity)}">${esc(a.severity)}</span>
            <b>${esc(a.rule.replaceAll("_", " "))}</b><span class="muted">SA ${a.sa}</span>
            <span class="muted">raised ${esc(clockTime(a.raised_at))}</span></div>
          <p class="ac-msg">${esc(a.message)}</p>
          <div class="ac-foot">${
            a.state === "acknowledged"
              ? `<span>acknowledged by <b>${esc(a.acknowledged_by)}</b>${a.ack_comment ? `: “${esc(a.ack_comment)}”` : ""}</span>`
              : `<span><b>active</b>${a.muted ? " (muted)" : ""}</span>`
          }${
            canAcknowledge(session, vehicleId) && a.state === "active"
              ? `<button type="button" class="btn btn-small" data-ack="${a.id}">Acknowledge</button>`
              : ""
          }</div></li>`,
          )
          .join("")
      : '<li class="muted">No open alert.</li>';
    if (hadFocus) box.querySelector("button")?.focus();
  }
  $("#v-alert-list").addEventListener("click", async (ev) => {
    const btn = ev.target.closest("[data-ack]");
    if (!btn) return;
    const a = sortedAlerts(vehicleId).find((x) => String(x.id) === btn.dataset.ack);
    if (!a) return;
    const comment = await askComment(a);
    if (comment === null) return;
    $("#ack-error").textContent = "";
    try {
      putAlert(await api(`/alerts/${a.id}/acknowledge`, { method: "POST", body: { comment: comment || null } }));
      if (!disposed) drawAlerts();
    } catch (err) {
      $("#ack-error").textContent = `Not acknowledged: ${err.message}`;
    }
  });

  async function loadLive() {
    try {
      const body = await api(`/vehicles/${encodeURIComponent(vehicleId)}/live`);
      for (const s of body.units) view.diag.set(`${s.bus}/${s.unit}`, s.diagnosis);
      if (!disposed) drawUnits();
    } catch (err) {
      if (err.status === 404) unitsEl.innerHTML = `<p class="error">No vehicle ${esc(vehicleId)}.</p>`;
    }
  }

  function setRangeButtons() {
    for (const b of main.querySelectorAll("[data-range]")) b.setAttribute("aria-pressed", String(b.dataset.range === view.range));
  }

  async function loadHistory() {
    const now = Date.now() / 1000;
    if (view.range !== "custom") {
      view.to = now;
      view.from = now - RANGES[view.range];
      $("#c-from").value = toLocalInput(view.from);
      $("#c-to").value = toLocalInput(view.to);
    }
    setRangeButtons();
    const q = new URLSearchParams({ from: view.from.toFixed(3), to: view.to.toFixed(3) });
    if (view.unit !== null) q.set("unit", view.unit);
    const base = `/vehicles/${encodeURIComponent(vehicleId)}`;
    const [hist, status, faults] = await Promise.allSettled([
      api(`${base}/history?${q}&fields=${ALL_FIELDS.join(",")}&bucket=${bucketFor(view.to - view.from)}`),
      api(`${base}/status?${q}`),
      api(`${base}/faults?${new URLSearchParams({ from: view.from.toFixed(3), to: view.to.toFixed(3) })}`),
    ]);
    if (disposed) return;
    if (hist.status === "fulfilled") {
      view.bucket = hist.value.bucket;
      if (view.unit === null) view.unit = hist.value.unit;
      $("#bucket").textContent = hist.value.bucket === "raw" ? "every reading" : `${hist.value.bucket} averages`;
      charts.setRows(rowsFromHistory(hist.value.series), view.from, view.to);
    } else {
      charts.setRows([], view.from, view.to);
      $("#bucket").textContent = hist.reason.status === 404 ? "no stored data yet" : hist.reason.message;
    }
    if (status.status === "fulfilled") {
      const first = status.value.changes[0];
      $("#timeline").innerHTML = timelineHtml(status.value.changes, view.from, view.to, first ? null : currentFlags());
      // Positions set through the DOM: the page's policy refuses inline style attributes.
      for (const seg of $("#timeline").querySelectorAll(".seg[data-left]")) {
        seg.style.left = `${seg.dataset.left}%`;
        seg.style.width = `${seg.dataset.width}%`;
      }
    } else {
      $("#timeline").innerHTML = `<p class="muted">${esc(status.reason.message)}</p>`;
    }
    if (faults.status === "fulfilled") showFaults(faults.value);
  }

  function showFaults(body) {
    const counts = Object.entries(body.counts || {});
    $("#fault-summary").innerHTML = counts.length
      ? `<p>${counts.map(([k, c]) => `<b>${esc(k)}</b>: ${c.episodes} episode${c.episodes === 1 ? "" : "s"}${c.occurrence_count ? `, occurrence count ${c.occurrence_count}` : ""}${c.active ? " (active)" : ""}`).join(" · ")}</p>`
      : "";
    $("#fault-table").innerHTML = faultsHtml(body, units().length);
  }

  // A fault opened or closed: the fault history again (to now when the range follows it).
  async function loadFaults() {
    const to = view.range === "custom" ? view.to : Date.now() / 1000;
    try {
      const q = new URLSearchParams({ from: view.from.toFixed(3), to: to.toFixed(3) });
      const body = await api(`/vehicles/${encodeURIComponent(vehicleId)}/faults?${q}`);
      if (!disposed) showFaults(body);
    } catch {
      /* the banner shows connection trouble */
    }
  }

  function currentFlags() {
    const u = units().find((x) => x.unit === view.unit) || units()[0];
    return u?.flags;
  }

  // Live: values re-render; voltage frames of the charted unit extend the charts.
  let pending = false;
  let diagTimer = null;
  const unsub = subscribe((kind, vid, msg) => {
    if (disposed) return;
    if (kind === "alerts" || (kind.startsWith("alert_") && vid === vehicleId)) {
      drawAlerts();
      return;
    }
    if (vid !== vehicleId) return;
    if (kind === "live" && msg.unit === view.unit && view.range !== "custom") {
      // The slot as the store holds it (a message may carry only the fields that changed).
      const u = vehicles.get(vid)?.units.get(`${msg.bus}/${msg.unit}`);
      const row = liveRow(msg.data.slot, msg.ts, u?.latest[msg.data.slot]?.fields || {});
      if (row) charts.extend(row, Date.now() / 1000 - RANGES[view.range]);
    }
    if (kind.startsWith("fault_") || kind === "status_change") {
      clearTimeout(diagTimer);
      diagTimer = setTimeout(() => {
        loadLive();
        loadFaults();
      }, 1000);
    }
    if (kind === "command") return;
    if (!pending) {
      pending = true;
      requestAnimationFrame(() => {
        pending = false;
        if (!disposed) drawUnits();
      });
    }
  });
  const periodic = setInterval(() => {
    loadLive();
    loadFaults();
  }, 10_000);

  for (const b of main.querySelectorAll("[data-range]")) {
    b.addEventListener("click", () => {
      view.range = b.dataset.range;
      loadHistory();
    });
  }
  $("#c-apply").addEventListener("click", () => {
    const from = new Date($("#c-from").value).getTime() / 1000;
    const to = new Date($("#c-to").value).getTime() / 1000;
    if (!(to > from)) {
      $("#bucket").textContent = "“From” must be before “To”.";
      return;
    }
    view.range = "custom";
    view.from = from;
    view.to = to;
    loadHistory();
  });
  $("#unit-select").addEventListener("change", (ev) => {
    view.unit = Number(ev.target.value);
    loadHistory();
  });
  $("#zoom-reset").addEventListener("click", () => charts.resetZoom());
  $("#csv").addEventListener("click", () => {
    const blob = new Blob([toCsv(charts.visibleRows())], { type: "text/csv" });
    const a = document.createElement("a");
    const stamp = fileStamp(Date.now() / 1000);
    a.href = URL.createObjectURL(blob);
    a.download = `${vehicleId}-SA${view.unit ?? ""}-${stamp}.csv`;
    document.body.append(a);
    a.click();
    a.remove();
    setTimeout(() => URL.revokeObjectURL(a.href), 1000);
  });

  drawUnits();
  drawAlerts();
  loadLive();
  loadHistory();
  return () => {
    disposed = true;
    unsub();
    clearInterval(periodic);
    clearTimeout(diagTimer);
    charts.destroy();
    for (const p of view.panels.values()) p.controls?.destroy();
  };
}
