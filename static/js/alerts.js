// Alerts page: the open alerts (worst first, live over the websocket), acknowledge with a
// comment (operators and admins), and the history filtered by state, severity and vehicle.

import { api } from "./api.js";
import { age, dateTime, duration, esc } from "./format.js";
import { putAlert, sortedAlerts, subscribe, vehicles } from "./store.js";

const FILTER_STORE = "eqgw.alerts.filters";
const ack = document.getElementById("ack-dialog");

function loadFilters() {
  try {
    return { state: "", severity: "", vehicle: "", ...JSON.parse(localStorage.getItem(FILTER_STORE)) };
  } catch {
    return { state: "", severity: "", vehicle: "" };
  }
}

const RANK = { viewer: 1, operator: 2, admin: 3 };

/**
 * The strongest role the signed-in key or person holds over one vehicle. A key has one role
 * over its whole scope; a single sign-on person may hold several (an operator of one depot and
 * a viewer of another): the grant whose scope holds the vehicle counts, as the server decides
 * (a scope is null for the whole fleet, else depots by name and vehicles by id).
 */
export function roleFor(me, vehicleId) {
  if (!me) return null;
  if (!me.grants) return me.role;
  const depot = vehicles.get(vehicleId)?.depot ?? null;
  let best = null;
  for (const g of me.grants) {
    const s = g.scope;
    const holds = s === null || s.vehicles.includes(vehicleId) || (depot !== null && s.groups.includes(depot));
    if (holds && (best === null || RANK[g.role] > RANK[best])) best = g.role;
  }
  return best;
}

/** Whether the session may act (acknowledge, command) on a vehicle, or on any vehicle. */
export function canAcknowledge(session, vehicleId) {
  const role = vehicleId === undefined ? session.me?.role : roleFor(session.me, vehicleId);
  return role === "operator" || role === "admin";
}

function sevHtml(a) {
  return `<span class="sev" data-severity="${esc(a.severity)}">${esc(a.severity)}</span>`;
}

function vehicleHtml(a) {
  return `<a href="#/vehicle/${encodeURIComponent(a.vehicle_id)}">${esc(a.vehicle_name)}</a>`;
}

function stateHtml(a) {
  const muted = a.muted ? ' <span class="badge-muted">(muted)</span>' : "";
  if (a.state === "acknowledged") {
    const note = a.ack_comment ? `: “${esc(a.ack_comment)}”` : "";
    return `acknowledged by <b>${esc(a.acknowledged_by)}</b>${note}${muted}`;
  }
  return `<b>${esc(a.state)}</b>${muted}`;
}

function openHtml(list, session) {
  if (!list.length) return '<p class="muted" id="no-open">No open alerts.</p>';
  const canAck = canAcknowledge(session);
  return `<div class="table-wrap"><table class="alerts" id="open-table">
    <thead><tr><th>Severity</th><th>Vehicle</th><th>Unit</th><th>Rule</th><th>What</th>
      <th>Raised</th><th>State</th>${canAck ? "<th><span class=\"sr\">Action</span></th>" : ""}</tr></thead>
    <tbody>${list
      .map(
        (a) => `<tr data-alert="${a.id}" data-rule="${esc(a.rule)}" data-vehicle="${esc(a.vehicle_id)}"
          data-state="${esc(a.state)}">
        <td data-label="Severity">${sevHtml(a)}</td><td data-label="Vehicle">${vehicleHtml(a)}</td><td class="nowrap" data-label="Unit">SA ${a.sa}</td>
        <td data-label="Rule">${esc(a.rule)}</td><td class="msg" data-label="What">${esc(a.message)}</td>
        <td data-label="Raised" title="${esc(age(a.raised_at))}">${esc(dateTime(a.raised_at))}</td>
        <td data-label="State">${stateHtml(a)}</td>
        ${
          canAck
            ? `<td>${
                a.state === "active" && canAcknowledge(session, a.vehicle_id)
                  ? `<button type="button" class="btn btn-small" data-ack="${a.id}">Acknowledge</button>`
                  : ""
              }</td>`
            : ""
        }
      </tr>`,
      )
      .join("")}</tbody></table></div>`;
}

function historyHtml(list) {
  if (!list.length) return '<p class="muted">No alerts match.</p>';
  return `<div class="table-wrap"><table class="alerts" id="history-table">
    <thead><tr><th>Raised</th><th>Severity</th><th>Vehicle</th><th>Rule</th><th>What</th>
      <th>State</th><th>Cleared</th><th>Lasted</th></tr></thead>
    <tbody>${list
      .map(
        (a) => `<tr data-alert="${a.id}" data-state="${esc(a.state)}">
        <td data-label="Raised">${esc(dateTime(a.raised_at))}</td><td data-label="Severity">${sevHtml(a)}</td><td data-label="Vehicle">${vehicleHtml(a)}</td>
        <td data-label="Rule">${esc(a.rule)}</td><td class="msg" data-label="What">${esc(a.message)}</td><td data-label="State">${stateHtml(a)}</td>
        <td data-label="Cleared">${a.cleared_at ? esc(dateTime(a.cleared_at)) : "—"}${
          a.cleared_by && a.cleared_by !== "condition" ? ` (${esc(a.cleared_by.replace("_", " "))})` : ""
        }</td>
        <td data-label="Lasted">${a.cleared_at ? esc(duration(a.cleared_at - a.raised_at)) : "—"}</td>
      </tr>`,
      )
      .join("")}</tbody></table></div>`;
}

/** Ask for an optional comment; resolves with it, or null when cancelled. */
export function askComment(a) {
  ack.querySelector("#ack-text").textContent =
    `${a.rule} on ${a.vehicle_name} (SA ${a.sa}): ${a.message}`;
  const box = ack.querySelector("#ack-comment");
  box.value = "";
  ack.returnValue = "cancel";
  ack.showModal();
  box.focus();
  return new Promise((resolve) => {
    ack.addEventListener("close", () => resolve(ack.returnValue === "ok" ? box.value.trim() : null), {
      once: true,
    });
  });
}

export function renderAlerts(main, session) {
  const filters = loadFilters();
  main.innerHTML = `
    <section class="page alerts-page">
      <div class="page-head"><h1>Alerts</h1></div>
      <div class="panel">
        <h2>Open <span class="muted" id="open-count"></span></h2>
        <p class="error" id="ack-error" role="alert"></p>
        <div id="open-alerts"><p class="muted">Loading…</p></div>
      </div>
      <section class="block">
        <div class="page-head">
          <h2>History</h2>
          <div class="filters" role="group" aria-label="History filters">
            <label>State <select id="h-state"><option value="">All</option>
              <option value="open">Open</option><option value="active">Active</option>
              <option value="acknowledged">Acknowledged</option><option value="cleared">Cleared</option>
            </select></label>
            <label>Severity <select id="h-severity"><option value="">All</option>
              <option value="critical">Critical</option><option value="warning">Warning</option>
              <option value="info">Info</option></select></label>
            <label>Vehicle <select id="h-vehicle"><option value="">All</option></select></label>
          </div>
        </div>
        <div class="panel" id="alert-history"><p class="muted">Loading…</p></div>
      </section>
    </section>`;
  const $ = (sel) => main.querySelector(sel);
  const selects = { state: $("#h-state"), severity: $("#h-severity"), vehicle: $("#h-vehicle") };
  for (const v of [...vehicles.values()].sort((a, b) => a.id.localeCompare(b.id))) {
    selects.vehicle.add(new Option(v.name, v.id));
  }
  for (const [k, sel] of Object.entries(selects)) {
    sel.value = filters[k];
    if (sel.value !== filters[k]) filters[k] = sel.value = "";
  }

  function drawOpen() {
    const list = sortedAlerts();
    const hadFocus = $("#open-alerts").contains(document.activeElement);
    $("#open-alerts").innerHTML = openHtml(list, session);
    $("#open-count").textContent = `(${list.length})`;
    if (hadFocus) $("#open-alerts button")?.focus();
  }

  let seq = 0;
  async function loadHistory() {
    const mine = ++seq;
    const q = new URLSearchParams({ limit: "200" });
    for (const k of ["state", "severity", "vehicle"]) if (filters[k]) q.set(k, filters[k]);
    try {
      const body = await api(`/alerts?${q}`);
      if (mine === seq) $("#alert-history").innerHTML = historyHtml(body.alerts);
    } catch (err) {
      if (mine === seq) {
        $("#alert-history").innerHTML = `<p class="error">Cannot load alerts: ${esc(err.message)}</p>`;
      }
    }
  }

  let historyTimer = null;
  function historySoon() {
    if (historyTimer) return;
    historyTimer = setTimeout(() => {
      historyTimer = null;
      loadHistory();
    }, 1000);
  }

  for (const [k, sel] of Object.entries(selects)) {
    sel.addEventListener("change", () => {
      filters[k] = sel.value;
      localStorage.setItem(FILTER_STORE, JSON.stringify(filters));
      loadHistory();
    });
  }

  $("#open-alerts").addEventListener("click", async (ev) => {
    const btn = ev.target.closest("[data-ack]");
    if (!btn) return;
    const a = sortedAlerts().find((x) => String(x.id) === btn.dataset.ack);
    if (!a) return;
    const comment = await askComment(a);
    if (comment === null) return;
    $("#ack-error").textContent = "";
    try {
      const done = await api(`/alerts/${a.id}/acknowledge`, {
        method: "POST",
        body: { comment: comment || null },
      });
      putAlert(done);
      drawOpen();
      historySoon();
    } catch (err) {
      $("#ack-error").textContent = `Not acknowledged: ${err.message}`;
    }
  });

  const unsub = subscribe((kind) => {
    if (kind === "alerts" || kind.startsWith("alert_")) {
      drawOpen();
      historySoon();
    }
  });
  const ages = setInterval(drawOpen, 15_000); // "raised ... ago"
  drawOpen();
  loadHistory();
  return () => {
    unsub();
    clearInterval(ages);
    clearTimeout(historyTimer);
  };
}
