// Fleet overview: a summary bar (counts per group, each a jump), search as you type, sort,
// depot and "needs attention" filters, and the fleet as tiles or as dense rows.
//
// Built for 500 vehicles streaming: one DOM node per vehicle, kept for the page's life; a
// websocket message only marks its vehicle dirty, and once per animation frame each dirty
// vehicle's view model is computed and only the text that changed is written. Filtering and
// sorting move the existing nodes (the fewest moves: the longest run already in order stays).

import {
  imbalance,
  isParked,
  loadFleet,
  needsAttention,
  openAlerts,
  subscribe,
  vehicleSeverity,
  vehicles,
} from "./store.js";
import { clockTime, deltaVolts, esc, percent, volts } from "./format.js";

const FILTER_STORE = "eqgw.overview.filters";
const SUMMARY_REFRESH_MS = 10_000; // the diagnosis comes from the API, not the events
const VALUE_SORT_MS = 2000;
const PATCH_PER_FRAME = 100; // a sort by a streaming value reorders at most this often

const CONDITION_LABEL = {
  standby: "Standby",
  normal: "Equalizing",
  overload: "Overload",
  equalizer_not_functioning: "Equalizer not working",
  abnormal: "Abnormal",
  shutdown_risk: "Shutdown risk",
  unknown: "No reading yet",
};

// The summary's groups, worst first; every vehicle is in exactly one.
export const GROUPS = [
  ["critical", "Critical"],
  ["warning", "Needs attention"],
  ["offline", "Offline"],
  ["ok", "Fine"],
  ["parked", "Parked"],
];
const GROUP_RANK = Object.fromEntries(GROUPS.map(([g], i) => [g, i]));
const SEVERITY_RANK = { critical: 3, warning: 2, info: 1 };

const SORTS = {
  worst: "Worst first",
  state: "State",
  imbalance: "Imbalance (largest first)",
  voltage: "Lowest voltage",
  soc: "Lowest SOC",
  soh: "Lowest SOH",
  heard: "Last heard (oldest first)",
  id: "Vehicle id",
};
const VALUE_SORTS = new Set(["imbalance", "voltage", "soc", "soh"]);

function loadFilters() {
  // On a phone the fleet is a list (the rows, each a card) unless the user chose tiles.
  const phone = window.matchMedia("(max-width: 600px)").matches;
  const base = { depot: "", attention: false, q: "", sort: "worst", group: "", view: phone ? "rows" : "tiles" };
  try {
    return { ...base, ...JSON.parse(localStorage.getItem(FILTER_STORE)) };
  } catch {
    return base;
  }
}

// ---- the numbers behind groups and sorts ---------------------------------------------------

function alertsByVehicle() {
  const by = new Map();
  for (const a of openAlerts.values()) {
    let list = by.get(a.vehicle_id);
    if (!list) by.set(a.vehicle_id, (list = []));
    list.push(a);
  }
  for (const list of by.values()) {
    list.sort(
      (a, b) =>
        (SEVERITY_RANK[b.severity] || 0) - (SEVERITY_RANK[a.severity] || 0) ||
        b.raised_at - a.raised_at,
    );
  }
  return by;
}

function isOffline(v) {
  if (v.state === "offline" || v.state === "not_reporting") return true;
  return [...v.units.values()].some((u) => u.state !== "parked" && !u.online);
}

/** The vehicle's summary group: critical, warning, offline, ok or parked. */
export function groupOf(v, alerts = []) {
  if (isParked(v)) return "parked";
  if (isOffline(v)) return "offline";
  const sev = vehicleSeverity(v);
  if (alerts.some((a) => a.severity === "critical" && a.state === "active") || sev >= 65) {
    return "critical";
  }
  if (sev >= 40 || alerts.some((a) => a.state === "active" && a.severity === "warning")) {
    return "warning";
  }
  return "ok";
}

const finite = (x) => (x === null || x === undefined || Number.isNaN(x) ? null : Number(x));
function lowest(v, keys) {
  let best = null;
  for (const u of v.units.values()) {
    for (const k of keys) {
      const x = finite(u[k]);
      if (x !== null && (best === null || x < best)) best = x;
    }
  }
  return best;
}
function largestImbalance(v) {
  let best = null;
  for (const u of v.units.values()) {
    const x = imbalance(u);
    if (x !== null && (best === null || Math.abs(x) > best)) best = Math.abs(x);
  }
  return best;
}

// A sort key per vehicle: [number (ascending), id]; missing values last.
function sortKey(sort, v, group) {
  const missing = Number.POSITIVE_INFINITY;
  switch (sort) {
    case "state":
      return GROUP_RANK[group];
    case "imbalance": {
      const x = largestImbalance(v);
      return x === null ? missing : -x;
    }
    case "voltage":
      return lowest(v, ["v12"]) ?? missing;
    case "soc":
      return lowest(v, ["soc_12v", "soc_24v"]) ?? missing;
    case "soh":
      return lowest(v, ["soh_12v", "soh_24v"]) ?? missing;
    case "heard":
      return v.last_heard ?? Number.NEGATIVE_INFINITY;
    case "id":
      return 0;
    default:
      return -vehicleSeverity(v);
  }
}

// ---- the view model: every text a vehicle shows, by slot ---------------------------------

function unitModel(u, m, p) {
  const imb = imbalance(u);
  const parked = u.state === "parked";
  const cond = parked ? "parked" : u.online ? u.diagnosis?.condition || "unknown" : "offline";
  const label = parked ? "Parked" : u.online ? CONDITION_LABEL[cond] || cond : "Offline";
  const text = parked
    ? `: last heard ${clockTime(u.last_seen)}`
    : u.online
      ? u.diagnosis?.text
        ? `: ${u.diagnosis.text}`
        : ""
      : `: last heard ${clockTime(u.last_seen)}`;
  const faults = [...u.faults.values()].filter((f) => f.fault !== "OFFLINE");
  m.text[`${p}v12`] = volts(u.v12);
  m.text[`${p}v24`] = volts(u.v24);
  m.text[`${p}imb`] = deltaVolts(imb);
  m.attr[`${p}imb`] = imb !== null && Math.abs(imb) > 0.1 ? "warn" : "";
  m.text[`${p}socA`] = percent(u.soc_12v ?? null);
  m.text[`${p}sohA`] = percent(u.soh_12v ?? null);
  m.text[`${p}socB`] = percent(u.soc_24v ?? null);
  m.text[`${p}sohB`] = percent(u.soh_24v ?? null);
  m.html[`${p}faults`] = faults
    .map(
      (f) =>
        `<li class="fault" data-fault="${esc(f.fault)}">${esc(f.fault)}${
          f.occurrence_count ? ` <span class="count">×${f.occurrence_count}</span>` : ""
        }${f.state === "stale" ? ' <span class="count">(stale)</span>' : ""}</li>`,
    )
    .join("");
  m.html[`${p}diag`] = `<b>${esc(label)}</b>${esc(text)}`;
  m.attr[`${p}diag`] = cond;
  m.title[`${p}diag`] = `${label}${text}`;
}

function heardText(v) {
  return isParked(v) || v.state === "not_reporting" ? `last heard ${clockTime(v.last_heard)}` : "";
}

function stateBadge(v) {
  if (v.state === "parked") return ["Parked", "parked"];
  if (v.state === "not_reporting") return ["Not reporting", "off"];
  const online = [...v.units.values()].some((u) => u.online);
  return online ? ["Online", "on"] : ["Offline", "off"];
}

function alertsHtml(list) {
  return list
    .map(
      (a) => `<li class="alert-chip" data-severity="${esc(a.severity)}" data-rule="${esc(a.rule)}"
        data-state="${esc(a.state)}" title="${esc(a.message)}">${esc(a.rule.replaceAll("_", " "))}${
          a.state === "acknowledged" ? " ✓" : ""
        }${a.muted ? " (muted)" : ""}</li>`,
    )
    .join("");
}

function model(v, alerts, group) {
  const m = { text: {}, html: {}, attr: {}, title: {} };
  const units = [...v.units.values()].sort((a, b) => a.unit - b.unit);
  const [label, cls] = stateBadge(v);
  m.text.name = v.name;
  m.text.state = label;
  m.attr.state = cls;
  m.text.depot = v.depot || "no depot";
  m.text.heard = heardText(v);
  m.text.attn = needsAttention(v) ? "needs attention" : "";
  m.text.lastHeard = clockTime(v.last_heard);
  m.html.alerts = alertsHtml(alerts);
  m.severity = isParked(v) ? "parked" : needsAttention(v) ? "attention" : "ok";
  m.group = group;
  m.units = units;
  units.forEach((u, i) => unitModel(u, m, `u${i}.`));
  // What decides the markup itself; anything else is patched into it.
  m.shape = units.map((u) => `${u.key}:${u.series || ""}`).join(",");
  return m;
}

// ---- markup ---------------------------------------------------------------------------------

const slot = (k, tag = "span", cls = "", extra = "") =>
  `<${tag} data-k="${k}"${cls ? ` class="${cls}"` : ""}${extra}></${tag}>`;

function tileHtml(v, m) {
  const many = m.units.length > 1;
  const link = `#/vehicle/${encodeURIComponent(v.id)}`;
  const units = m.units.length
    ? m.units
        .map((u, i) => {
          const p = `u${i}.`;
          return `<div class="unit" data-unit="${u.unit}">
        ${many || u.series ? `<div class="unit-id">SA ${u.unit}${u.series ? ` · ${u.series}-series` : ""}</div>` : ""}
        <dl class="big">
          <div><dt>V12</dt><dd data-field="v12" data-k="${p}v12"></dd></div>
          <div><dt>V24</dt><dd data-field="v24" data-k="${p}v24"></dd></div>
          <div><dt>B − A</dt><dd data-field="imbalance" data-k="${p}imb"></dd></div>
        </dl>
        <div class="batt"><span class="k">12 V battery (A)</span><span>SOC <b data-k="${p}socA"></b></span><span>SOH <b data-k="${p}sohA"></b></span></div>
        <div class="batt"><span class="k">24 V battery (B)</span><span>SOC <b data-k="${p}socB"></b></span><span>SOH <b data-k="${p}sohB"></b></span></div>
        <ul class="faults" aria-label="Active faults" data-k="${p}faults"></ul>
        <p class="diag" data-k="${p}diag"></p>
      </div>`;
        })
        .join("")
    : '<p class="diag">No unit heard yet.</p>';
  return `
    <a class="tile-link" href="${link}">
      <h2 data-k="name"></h2>
      ${slot("state", "span", "state")}
    </a>
    <div class="tile-sub">${slot("depot")}<span class="heard-wrap"> · <span class="heard" data-k="heard"></span></span><span class="attn-wrap"> · <b class="attn" data-k="attn"></b></span></div>
    <ul class="alert-chips" aria-label="Open alerts" data-k="alerts"></ul>
    ${units}`;
}

function rowHtml(v, m) {
  const link = `#/vehicle/${encodeURIComponent(v.id)}`;
  const per = (fn) =>
    m.units.length ? m.units.map((u, i) => fn(u, `u${i}.`)).join("") : '<span class="l">—</span>';
  return `
    <div role="cell" class="c-state">${slot("state", "span", "state")}</div>
    <div role="cell" class="c-name"><a class="tile-link row-link" href="${link}"><b data-k="name"></b></a>
      <span class="muted c-depot" data-k="depot"></span></div>
    <div role="cell" class="c-unit">${per((u) => `<span class="l">SA ${u.unit}</span>`)}</div>
    <div role="cell" class="c-num" data-label="V12">${per((u, p) => `<span class="l" data-field="v12" data-k="${p}v12"></span>`)}</div>
    <div role="cell" class="c-num" data-label="V24">${per((u, p) => `<span class="l" data-field="v24" data-k="${p}v24"></span>`)}</div>
    <div role="cell" class="c-num" data-label="B − A">${per((u, p) => `<span class="l" data-field="imbalance" data-k="${p}imb"></span>`)}</div>
    <div role="cell" class="c-soc" data-label="SOC/SOH A">${per((u, p) => `<span class="l"><span data-k="${p}socA"></span> / <span data-k="${p}sohA"></span></span>`)}</div>
    <div role="cell" class="c-soc" data-label="SOC/SOH B">${per((u, p) => `<span class="l"><span data-k="${p}socB"></span> / <span data-k="${p}sohB"></span></span>`)}</div>
    <div role="cell" class="c-alerts"><ul class="alert-chips" aria-label="Open alerts" data-k="alerts"></ul></div>
    <div role="cell" class="c-faults">${per((u, p) => `<ul class="faults l" aria-label="Active faults" data-k="${p}faults"></ul>`)}</div>
    <div role="cell" class="c-heard" data-label="Last heard"><span class="heard" data-k="lastHeard"></span></div>`;
}

// ---- a vehicle's node, patched ---------------------------------------------------------

class VehicleNode {
  constructor(id, mode) {
    this.id = id;
    this.mode = mode;
    this.el = document.createElement(mode === "rows" ? "div" : "article");
    this.el.className = mode === "rows" ? "vrow" : "tile";
    if (mode === "rows") this.el.setAttribute("role", "row");
    this.el.dataset.vehicle = id;
    this.shape = null;
    this.slots = null;
    this.last = null;
  }

  update(v, m) {
    const el = this.el;
    if (this.shape !== m.shape) {
      const hadFocus = el.contains(document.activeElement);
      el.innerHTML = this.mode === "rows" ? rowHtml(v, m) : tileHtml(v, m);
      this.slots = new Map();
      for (const s of el.querySelectorAll("[data-k]")) {
        const k = s.dataset.k;
        if (!this.slots.has(k)) this.slots.set(k, []);
        this.slots.get(k).push(s);
      }
      this.shape = m.shape;
      this.last = { text: {}, html: {}, attr: {}, title: {} };
      if (hadFocus) el.querySelector(".tile-link")?.focus();
    }
    const last = this.last;
    for (const [k, val] of Object.entries(m.text)) {
      if (last.text[k] === val) continue;
      last.text[k] = val;
      for (const s of this.slots.get(k) || []) s.textContent = val;
    }
    for (const [k, val] of Object.entries(m.html)) {
      if (last.html[k] === val) continue;
      last.html[k] = val;
      for (const s of this.slots.get(k) || []) s.innerHTML = val;
    }
    for (const [k, val] of Object.entries(m.attr)) {
      if (last.attr[k] === val) continue;
      last.attr[k] = val;
      for (const s of this.slots.get(k) || []) {
        if (k === "state") s.className = `state ${val}`;
        else if (k.endsWith("diag")) s.dataset.condition = val;
        else s.classList.toggle("warn", val === "warn");
      }
    }
    for (const [k, val] of Object.entries(m.title)) {
      if (last.title[k] === val) continue;
      last.title[k] = val;
      for (const s of this.slots.get(k) || []) s.title = val;
    }
    if (el.dataset.severity !== m.severity) el.dataset.severity = m.severity;
    if (el.dataset.group !== m.group) el.dataset.group = m.group;
    if (el.dataset.state !== (v.state || "")) el.dataset.state = v.state || "";
  }
}

// Put `nodes` into `box` in this order, removing others, moving as few as possible: the
// longest run already in order stays where it is.
export function placeInOrder(box, nodes) {
  const want = new Set(nodes);
  for (const child of [...box.children]) if (!want.has(child)) child.remove();
  const index = new Map([...box.children].map((c, i) => [c, i]));
  // Longest increasing subsequence of the current positions, in the wanted order.
  const pos = nodes.map((n) => (index.has(n) ? index.get(n) : -1));
  const tails = [];
  const prev = new Array(nodes.length).fill(-1);
  const tailIdx = [];
  for (let i = 0; i < pos.length; i++) {
    if (pos[i] < 0) continue;
    let lo = 0;
    let hi = tails.length;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (tails[mid] < pos[i]) lo = mid + 1;
      else hi = mid;
    }
    tails[lo] = pos[i];
    tailIdx[lo] = i;
    prev[i] = lo > 0 ? tailIdx[lo - 1] : -1;
  }
  const stay = new Set();
  for (let i = tails.length ? tailIdx[tails.length - 1] : -1; i >= 0; i = prev[i]) {
    stay.add(nodes[i]);
  }
  let next = null;
  for (let i = nodes.length - 1; i >= 0; i--) {
    const n = nodes[i];
    if (!stay.has(n)) box.insertBefore(n, next);
    next = n;
  }
}

// ---- the page --------------------------------------------------------------------------

export function renderOverview(main) {
  const filters = loadFilters();
  if (!SORTS[filters.sort]) filters.sort = "worst";
  main.innerHTML = `
    <section class="page overview">
      <div class="page-head">
        <h1>Fleet</h1>
        <div class="summary" id="summary" role="group" aria-label="Fleet summary: show a group">
          <button type="button" class="sum" data-group="" aria-pressed="false">All <b data-count=""></b></button>
          ${GROUPS.map(
            ([g, label]) =>
              `<button type="button" class="sum" data-group="${g}" aria-pressed="false">${label} <b data-count="${g}"></b></button>`,
          ).join("")}
        </div>
      </div>
      <div class="filters" role="group" aria-label="Filters">
        <label class="search">Search
          <input type="search" id="f-q" placeholder="id, name or depot" autocomplete="off" spellcheck="false">
        </label>
        <label>Sort
          <select id="f-sort">${Object.entries(SORTS)
            .map(([k, label]) => `<option value="${k}">${label}</option>`)
            .join("")}</select>
        </label>
        <label>Depot / group
          <select id="f-depot"><option value="">All</option></select>
        </label>
        <label class="check"><input type="checkbox" id="f-attn"> Needs attention only</label>
        <div class="view-switch" role="group" aria-label="View">
          <button type="button" class="btn btn-small" data-view="tiles">Tiles</button>
          <button type="button" class="btn btn-small" data-view="rows">Rows</button>
        </div>
        <span id="f-count" class="muted" aria-live="polite"></span>
      </div>
      <div id="fleet-body"></div>
    </section>`;
  const body = main.querySelector("#fleet-body");
  const depotSel = main.querySelector("#f-depot");
  const attnBox = main.querySelector("#f-attn");
  const search = main.querySelector("#f-q");
  const sortSel = main.querySelector("#f-sort");
  const count = main.querySelector("#f-count");
  const summary = main.querySelector("#summary");
  attnBox.checked = filters.attention;
  search.value = filters.q;
  sortSel.value = filters.sort;

  let nodes = new Map(); // vehicle id -> VehicleNode (of the current view)
  let grid;
  let parkedGrid;
  let parkedSection;
  let empty;

  function layout() {
    nodes = new Map();
    const rows = filters.view === "rows";
    body.innerHTML = rows
      ? `<div class="vrows" role="table" aria-label="Fleet">
          <div class="vrow vhead" role="row">
            <span role="columnheader">State</span><span role="columnheader">Vehicle</span>
            <span role="columnheader">Unit</span><span role="columnheader" class="c-num">V12</span>
            <span role="columnheader" class="c-num">V24</span><span role="columnheader" class="c-num">B − A</span>
            <span role="columnheader">SOC / SOH A</span><span role="columnheader">SOC / SOH B</span>
            <span role="columnheader">Open alerts</span><span role="columnheader">Faults</span>
            <span role="columnheader">Last heard</span>
          </div>
          <div role="rowgroup" id="tiles" class="vrows-body"></div>
        </div>
        <p class="muted" id="fleet-empty" hidden></p>
        <section class="parked-fleet" id="parked" hidden aria-labelledby="parked-h">
          <h2 id="parked-h">Parked <span class="muted" id="parked-count"></span></h2>
          <div class="vrows" role="table" aria-labelledby="parked-h"><div role="rowgroup" id="parked-tiles" class="vrows-body"></div></div>
        </section>`
      : `<div class="tiles" id="tiles"></div>
        <p class="muted" id="fleet-empty" hidden></p>
        <section class="parked-fleet" id="parked" hidden aria-labelledby="parked-h">
          <h2 id="parked-h">Parked <span class="muted" id="parked-count"></span></h2>
          <p class="muted">Ignition off: every bus of these vehicles is silent. No alert is raised for them.</p>
          <div class="tiles" id="parked-tiles"></div>
        </section>`;
    grid = body.querySelector("#tiles");
    parkedGrid = body.querySelector("#parked-tiles");
    parkedSection = body.querySelector("#parked");
    empty = body.querySelector("#fleet-empty");
    for (const b of main.querySelectorAll("[data-view]")) {
      b.setAttribute("aria-pressed", String(b.dataset.view === filters.view));
    }
  }

  function fillDepots() {
    const depots = [...new Set([...vehicles.values()].map((v) => v.depot || ""))].sort();
    const have = new Set([...depotSel.options].map((o) => o.value));
    for (const d of depots) if (d && !have.has(d)) depotSel.add(new Option(d, d));
    const want = filters.depot && depots.includes(filters.depot) ? filters.depot : "";
    if (depotSel.value !== want) depotSel.value = want;
  }

  const matches = (v, needle) =>
    !needle ||
    v.id.toLowerCase().includes(needle) ||
    (v.name || "").toLowerCase().includes(needle) ||
    (v.depot || "").toLowerCase().includes(needle);

  // Per vehicle: the group and sort key as last computed (reused by a reorder).
  const info = new Map();
  let alertIndex = alertsByVehicle();
  let lastOrder = 0;

  function compute(v) {
    const alerts = alertIndex.get(v.id) || [];
    const group = groupOf(v, alerts);
    const m = model(v, alerts, group);
    info.set(v.id, { group, key: sortKey(filters.sort, v, group), m });
    return m;
  }

  function patch(ids) {
    for (const id of ids) {
      const v = vehicles.get(id);
      if (!v) continue;
      const m = compute(v);
      const n = nodes.get(id);
      if (n) n.update(v, m);
    }
  }

  // Which vehicles show, in which order; nodes made for those not built yet.
  function arrange() {
    fillDepots();
    for (const id of [...info.keys()]) if (!vehicles.has(id)) info.delete(id);
    const needle = filters.q.trim().toLowerCase();
    const counts = Object.fromEntries(GROUPS.map(([g]) => [g, 0]));
    const shown = [];
    let inView = 0;
    for (const v of vehicles.values()) {
      if (!info.has(v.id)) compute(v);
      const it = info.get(v.id);
      if (filters.depot && v.depot !== filters.depot) continue;
      if (!matches(v, needle)) continue;
      counts[it.group] += 1;
      inView += 1;
      if (filters.group && it.group !== filters.group) continue;
      if (filters.attention && !needsAttention(v)) continue;
      shown.push(v);
    }
    shown.sort(
      (a, b) => info.get(a.id).key - info.get(b.id).key || a.id.localeCompare(b.id),
    );
    const active = [];
    const parked = [];
    for (const v of shown) {
      let n = nodes.get(v.id);
      if (!n) {
        n = new VehicleNode(v.id, filters.view);
        nodes.set(v.id, n);
        n.update(v, info.get(v.id).m);
      }
      (isParked(v) ? parked : active).push(n.el);
    }
    placeInOrder(grid, active);
    placeInOrder(parkedGrid, parked);
    parkedSection.hidden = !parked.length;
    body.querySelector("#parked-count").textContent = parked.length ? `(${parked.length})` : "";
    const total = vehicles.size;
    count.textContent =
      shown.length === total ? `${total} vehicles` : `${shown.length} of ${total} vehicles`;
    empty.hidden = active.length > 0;
    empty.textContent = !total
      ? "No vehicles yet."
      : !shown.length
        ? "No vehicle matches the filters."
        : "Every vehicle shown is parked.";
    for (const b of summary.querySelectorAll("[data-group]")) {
      const g = b.dataset.group;
      const c = g ? counts[g] : inView;
      const el = b.querySelector("[data-count]");
      if (el.textContent !== String(c)) el.textContent = String(c);
      b.setAttribute("aria-pressed", String(g === filters.group));
      b.dataset.n = String(c);
    }
    lastOrder = performance.now();
  }

  // Live: dirty vehicles patched once per frame; the order redone when it may have moved.
  const dirty = new Set();
  let reorder = false;
  let frame = 0;
  function schedule() {
    if (!frame) frame = requestAnimationFrame(flush);
  }
  function flush() {
    frame = 0;
    if (dirty.size) {
      // At most PATCH_PER_FRAME vehicles a frame: a full refresh of 500 is spread over a few
      // frames instead of one long task.
      const batch = [...dirty].slice(0, PATCH_PER_FRAME);
      const before = new Map(batch.map((id) => [id, info.get(id)]));
      patch(batch);
      for (const [id, old] of before) {
        dirty.delete(id);
        const now = info.get(id);
        if (!old || !now || old.group !== now.group || old.key !== now.key) reorder = true;
      }
      if (dirty.size) {
        schedule();
        return;
      }
    }
    if (reorder) {
      // A sort by a streaming value would move rows under the reader's eyes at every frame.
      const wait = VALUE_SORTS.has(filters.sort) ? VALUE_SORT_MS - (performance.now() - lastOrder) : 0;
      if (wait > 0) {
        setTimeout(schedule, wait);
        return;
      }
      reorder = false;
      arrange();
    }
  }
  function markAll() {
    for (const id of vehicles.keys()) dirty.add(id);
    reorder = true;
    schedule();
  }

  let refresh = null;
  function refreshSoon() {
    // Status and fault changes move the diagnosis: fetch the summary again, at most every 2 s.
    if (refresh) return;
    refresh = setTimeout(async () => {
      refresh = null;
      try {
        await loadFleet();
      } catch {
        /* the banner shows connection trouble */
      }
    }, 2000);
  }

  const save = () => localStorage.setItem(FILTER_STORE, JSON.stringify(filters));
  // Filters and sorts answer at once (not on the next frame): the nodes exist, they move.
  const resort = () => {
    for (const v of vehicles.values()) {
      const it = info.get(v.id);
      if (it) it.key = sortKey(filters.sort, v, it.group);
    }
    arrange();
  };
  depotSel.addEventListener("change", () => {
    filters.depot = depotSel.value;
    save();
    arrange();
  });
  attnBox.addEventListener("change", () => {
    filters.attention = attnBox.checked;
    save();
    arrange();
  });
  search.addEventListener("input", () => {
    filters.q = search.value;
    save();
    arrange();
  });
  sortSel.addEventListener("change", () => {
    filters.sort = sortSel.value;
    save();
    resort();
  });
  summary.addEventListener("click", (ev) => {
    const b = ev.target.closest("[data-group]");
    if (!b) return;
    filters.group = filters.group === b.dataset.group ? "" : b.dataset.group;
    save();
    arrange();
    grid.scrollIntoView?.({ block: "nearest" });
  });
  main.querySelector(".view-switch").addEventListener("click", (ev) => {
    const b = ev.target.closest("[data-view]");
    if (!b || b.dataset.view === filters.view) return;
    filters.view = b.dataset.view;
    save();
    layout();
    arrange();
  });

  const unsub = subscribe((kind, vehicleId) => {
    if (
      kind.startsWith("fault_") ||
      kind === "status_change" ||
      kind === "unit_online" ||
      kind === "unit_parked" ||
      kind === "vehicle_state"
    ) {
      refreshSoon();
    }
    if (kind === "command") return;
    if (kind === "alerts" || kind.startsWith("alert_")) alertIndex = alertsByVehicle();
    if (kind === "fleet" || kind === "alerts" || !vehicleId) {
      markAll();
      return;
    }
    if (kind.startsWith("alert_") || !info.has(vehicleId)) reorder = true;
    dirty.add(vehicleId);
    schedule();
  });
  const periodic = setInterval(refreshSoon, SUMMARY_REFRESH_MS);
  layout();
  arrange();
  return () => {
    unsub();
    clearInterval(periodic);
    clearTimeout(refresh);
    cancelAnimationFrame(frame);
  };
}
