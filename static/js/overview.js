// Fleet overview: a summary bar (counts per group, each a jump), search as you type, sort,
// depot and "needs attention" filters, and the fleet as tiles or as dense rows.
//
// Built for 500 vehicles streaming:
// - One DOM node per vehicle, kept for the page's life. Its head (name, state, depot) is
//   always there, so search, sort, counts and the keyboard's Tab order cover every vehicle;
//   its values (units, alerts, faults, diagnosis) are drawn only while it is within a screen
//   and a half of the viewport, and dropped again when it leaves (an off-screen node keeps
//   its last size: `content-visibility: auto`).
// - A websocket message only marks its vehicle dirty; once per animation frame, within a
//   time budget, each dirty vehicle's group and sort keys (every sort's, so a new sort
//   computes nothing) are redone and only the text that changed is written.
// - Filtering and sorting move the existing nodes (the fewest moves: the longest run already
//   in order stays; `moveBefore` keeps the focus where the browser has it).

import {
  imbalance,
  isParked,
  openAlerts,
  refreshFleet,
  subscribe,
  vehicleSeverity,
  vehicles,
} from "./store.js";
import { clockTime, deltaVolts, esc, percent, volts } from "./format.js";

const FILTER_STORE = "eqgw.overview.filters";
// What the websocket does not say (names, depots, vehicles first heard) is read again this
// often, a page of vehicles at a time.
const FLEET_REFRESH_MS = 60_000;
const VALUE_SORT_MS = 2000; // a sort by a streaming value reorders at most this often
const FRAME_BUDGET_MS = 6; // live patches per frame; the rest waits for the next
const NEAR = 1.5; // values drawn within this many viewport heights above and below

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
  for (const u of v.units.values()) if (u.state !== "parked" && !u.online) return true;
  return false;
}

/** The vehicle's summary group: critical, warning, offline, ok or parked. */
export function groupOf(v, alerts = [], sev = vehicleSeverity(v)) {
  if (isParked(v)) return "parked";
  if (isOffline(v)) return "offline";
  if (alerts.some((a) => a.severity === "critical" && a.state === "active") || sev >= 65) {
    return "critical";
  }
  if (sev >= 40 || alerts.some((a) => a.state === "active" && a.severity === "warning")) {
    return "warning";
  }
  return "ok";
}

const finite = (x) => (x === null || x === undefined || Number.isNaN(x) ? null : Number(x));
const MISSING = Number.POSITIVE_INFINITY;

// Every sort's key of a vehicle (ascending, missing values last; ties by id), computed when
// its values change: choosing another sort computes nothing.
function sortKeys(v, group, sev) {
  let imb = null;
  let v12 = null;
  let soc = null;
  let soh = null;
  const low = (best, x) => (x !== null && (best === null || x < best) ? x : best);
  for (const u of v.units.values()) {
    const x = imbalance(u);
    if (x !== null && (imb === null || Math.abs(x) > imb)) imb = Math.abs(x);
    v12 = low(v12, finite(u.v12));
    soc = low(low(soc, finite(u.soc_12v)), finite(u.soc_24v));
    soh = low(low(soh, finite(u.soh_12v)), finite(u.soh_24v));
  }
  return {
    worst: -sev,
    state: GROUP_RANK[group],
    imbalance: imb === null ? MISSING : -imb,
    voltage: v12 ?? MISSING,
    soc: soc ?? MISSING,
    soh: soh ?? MISSING,
    heard: v.last_heard ?? Number.NEGATIVE_INFINITY,
    id: 0,
  };
}

// ---- what a vehicle shows ---------------------------------------------------------------

function stateBadge(v) {
  if (v.state === "parked") return ["Parked", "parked"];
  if (v.state === "not_reporting") return ["Not reporting", "off"];
  for (const u of v.units.values()) if (u.online) return ["Online", "on"];
  return ["Offline", "off"];
}

// The head: what every node shows, drawn or not.
function headModel(v) {
  const [label, cls] = stateBadge(v);
  const quiet = isParked(v) || v.state === "not_reporting";
  return {
    name: v.name,
    state: label,
    stateClass: cls,
    depot: v.depot || "no depot",
    heard: quiet ? `last heard ${clockTime(v.last_heard)}` : "",
  };
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

function faultsHtml(u) {
  let out = "";
  for (const f of u.faults.values()) {
    if (f.fault === "OFFLINE") continue;
    out += `<li class="fault" data-fault="${esc(f.fault)}">${esc(f.fault)}${
      f.occurrence_count ? ` <span class="count">×${f.occurrence_count}</span>` : ""
    }${f.state === "stale" ? ' <span class="count">(stale)</span>' : ""}</li>`;
  }
  return out;
}

// The values: every text by slot (`text`), markup (`html`), a class or data attribute
// (`attr`) and a title; `shape` decides the markup itself.
function bodyModel(v, alerts) {
  const m = { text: {}, html: {}, attr: {}, title: {} };
  const units = [...v.units.values()].sort((a, b) => a.unit - b.unit);
  m.units = units;
  m.shape = units.map((u) => `${u.key}:${u.series || ""}`).join(",");
  m.html.alerts = alertsHtml(alerts);
  m.text.lastHeard = clockTime(v.last_heard);
  units.forEach((u, i) => {
    const p = `u${i}.`;
    const imb = imbalance(u);
    const parked = u.state === "parked";
    const cond = parked ? "parked" : u.online ? u.diagnosis?.condition || "unknown" : "offline";
    const label = parked ? "Parked" : u.online ? CONDITION_LABEL[cond] || cond : "Offline";
    const text =
      parked || !u.online
        ? `: last heard ${clockTime(u.last_seen)}`
        : u.diagnosis?.text
          ? `: ${u.diagnosis.text}`
          : "";
    const socA = percent(u.soc_12v ?? null);
    const sohA = percent(u.soh_12v ?? null);
    const socB = percent(u.soc_24v ?? null);
    const sohB = percent(u.soh_24v ?? null);
    m.text[`${p}v12`] = volts(u.v12);
    m.text[`${p}v24`] = volts(u.v24);
    m.text[`${p}imb`] = deltaVolts(imb);
    m.attr[`${p}imb`] = imb !== null && Math.abs(imb) > 0.1 ? "warn" : "";
    m.text[`${p}socA`] = socA;
    m.text[`${p}sohA`] = sohA;
    m.text[`${p}socB`] = socB;
    m.text[`${p}sohB`] = sohB;
    m.text[`${p}battA`] = `${socA} / ${sohA}`; // a row's SOC/SOH cells
    m.text[`${p}battB`] = `${socB} / ${sohB}`;
    m.html[`${p}faults`] = faultsHtml(u);
    m.html[`${p}diag`] = `<b>${esc(label)}</b>${esc(text)}`;
    m.attr[`${p}diag`] = cond;
    m.title[`${p}diag`] = `${label}${text}`;
  });
  return m;
}

// ---- markup ---------------------------------------------------------------------------------

const link = (id) => `#/vehicle/${encodeURIComponent(id)}`;

function tileHeadHtml(id) {
  return `<a class="tile-link" href="${link(id)}"><h2 data-k="name"></h2><span class="state" data-k="state"></span></a>
    <p class="tile-sub"><span data-k="depot"></span><span class="heard" data-k="heard"></span></p>`;
}

function tileBodyHtml(m) {
  const many = m.units.length > 1;
  const units = m.units.length
    ? m.units
        .map((u, i) => {
          const p = `u${i}.`;
          return `<div class="unit" data-unit="${u.unit}">${
            many || u.series ? `<p class="unit-id">SA ${u.unit}${u.series ? ` · ${esc(u.series)}-series` : ""}</p>` : ""
          }<dl class="big"><dt>V12</dt><dd data-field="v12" data-k="${p}v12"></dd><dt>V24</dt><dd data-field="v24" data-k="${p}v24"></dd><dt>B − A</dt><dd data-field="imbalance" data-k="${p}imb"></dd></dl>
        <div class="batt"><span class="k">12 V <span class="wide">battery </span>(A)</span><span>SOC <b data-k="${p}socA"></b></span><span>SOH <b data-k="${p}sohA"></b></span></div>
        <div class="batt"><span class="k">24 V <span class="wide">battery </span>(B)</span><span>SOC <b data-k="${p}socB"></b></span><span>SOH <b data-k="${p}sohB"></b></span></div>
        <ul class="faults" aria-label="Active faults" data-k="${p}faults"></ul>
        <p class="diag" data-k="${p}diag"></p></div>`;
        })
        .join("")
    : '<p class="diag">No unit heard yet.</p>';
  return `<ul class="alert-chips" aria-label="Open alerts" data-k="alerts"></ul>${units}`;
}

function rowHeadHtml(id) {
  return `<div role="cell" class="c-state"><span class="state" data-k="state"></span></div>
    <div role="cell" class="c-name"><a class="tile-link row-link" href="${link(id)}"><b data-k="name"></b></a><span class="muted c-depot" data-k="depot"></span></div>`;
}

function rowBodyHtml(m) {
  const per = (fn) =>
    m.units.length ? m.units.map((u, i) => fn(u, `u${i}.`)).join("") : '<span class="l">—</span>';
  return `<div role="cell" class="c-unit">${per((u) => `<span class="l">SA ${u.unit}</span>`)}</div>
    <div role="cell" class="c-num" data-label="V12">${per((u, p) => `<span class="l" data-field="v12" data-k="${p}v12"></span>`)}</div>
    <div role="cell" class="c-num" data-label="V24">${per((u, p) => `<span class="l" data-field="v24" data-k="${p}v24"></span>`)}</div>
    <div role="cell" class="c-num" data-label="B − A">${per((u, p) => `<span class="l" data-field="imbalance" data-k="${p}imb"></span>`)}</div>
    <div role="cell" class="c-soc" data-label="SOC/SOH A">${per((u, p) => `<span class="l" data-k="${p}battA"></span>`)}</div>
    <div role="cell" class="c-soc" data-label="SOC/SOH B">${per((u, p) => `<span class="l" data-k="${p}battB"></span>`)}</div>
    <div role="cell" class="c-alerts"><ul class="alert-chips" aria-label="Open alerts" data-k="alerts"></ul></div>
    <div role="cell" class="c-faults">${per((u, p) => `<ul class="faults l" aria-label="Active faults" data-k="${p}faults"></ul>`)}</div>
    <div role="cell" class="c-heard heard" data-label="Last heard" data-k="lastHeard"></div>`;
}

// ---- a vehicle's node ---------------------------------------------------------------------

function slotsOf(el, into = new Map()) {
  for (const s of el.querySelectorAll("[data-k]")) {
    const k = s.dataset.k;
    if (!into.has(k)) into.set(k, []);
    into.get(k).push(s);
  }
  return into;
}

class VehicleNode {
  constructor(id, mode) {
    this.id = id;
    this.rows = mode === "rows";
    const el = document.createElement(this.rows ? "div" : "article");
    el.className = this.rows ? "vrow" : "tile";
    if (this.rows) el.setAttribute("role", "row");
    el.dataset.vehicle = id;
    el.innerHTML = this.rows ? rowHeadHtml(id) : tileHeadHtml(id);
    this.el = el;
    this.headEnd = el.lastElementChild; // the values come after it
    this.head = slotsOf(el);
    this.lastHead = {};
    this.near = false; // within NEAR viewports (the intersection observer says)
    this.drawn = false; // its values are in the DOM (kept current while they are)
    this.shape = null;
    this.slots = null;
    this.last = null;
  }

  setHead(h) {
    const last = this.lastHead;
    for (const k of ["name", "state", "depot", "heard"]) {
      if (last[k] === h[k]) continue;
      last[k] = h[k];
      for (const s of this.head.get(k) || []) s.textContent = h[k];
    }
    if (last.stateClass !== h.stateClass) {
      last.stateClass = h.stateClass;
      for (const s of this.head.get("state")) s.className = `state ${h.stateClass}`;
    }
  }

  /** Draw (or bring up to date) the values. */
  draw(m) {
    const el = this.el;
    if (!this.drawn || this.shape !== m.shape) {
      this.clear();
      el.insertAdjacentHTML("beforeend", this.rows ? rowBodyHtml(m) : tileBodyHtml(m));
      this.slots = new Map();
      for (let n = this.headEnd.nextElementSibling; n; n = n.nextElementSibling) {
        if (n.dataset.k) this.slots.set(n.dataset.k, [n]);
        slotsOf(n, this.slots);
      }
      this.shape = m.shape;
      this.last = { text: {}, html: {}, attr: {}, title: {} };
      this.drawn = true;
    }
    const { last, slots } = this;
    for (const [k, val] of Object.entries(m.text)) {
      if (last.text[k] === val) continue;
      last.text[k] = val;
      for (const s of slots.get(k) || []) s.textContent = val;
    }
    for (const [k, val] of Object.entries(m.html)) {
      if (last.html[k] === val) continue;
      last.html[k] = val;
      for (const s of slots.get(k) || []) s.innerHTML = val;
    }
    for (const [k, val] of Object.entries(m.attr)) {
      if (last.attr[k] === val) continue;
      last.attr[k] = val;
      for (const s of slots.get(k) || []) {
        if (k.endsWith("diag")) s.dataset.condition = val;
        else s.classList.toggle("warn", val === "warn");
      }
    }
    for (const [k, val] of Object.entries(m.title)) {
      if (last.title[k] === val) continue;
      last.title[k] = val;
      for (const s of slots.get(k) || []) s.title = val;
    }
  }

  /** Drop the values (far off-screen: the node keeps its last size). */
  clear() {
    const el = this.el;
    while (el.lastElementChild && el.lastElementChild !== this.headEnd) el.lastElementChild.remove();
    this.drawn = false;
    this.slots = null;
  }
}

// Put `nodes` into `box` in this order, removing others, moving as few as possible: the
// longest run already in order stays where it is. Returns how many were removed, moved or
// added (0: the box is as it was).
export function placeInOrder(box, nodes) {
  const want = new Set(nodes);
  let moved = 0;
  for (const child of [...box.children]) {
    if (!want.has(child)) {
      child.remove();
      moved += 1;
    }
  }
  const index = new Map();
  let i = 0;
  for (const c of box.children) index.set(c, i++);
  // Longest increasing subsequence of the current positions, in the wanted order.
  const tails = [];
  const prev = new Array(nodes.length).fill(-1);
  const tailIdx = [];
  for (let j = 0; j < nodes.length; j++) {
    const pos = index.get(nodes[j]);
    if (pos === undefined) continue;
    let lo = 0;
    let hi = tails.length;
    while (lo < hi) {
      const mid = (lo + hi) >> 1;
      if (tails[mid] < pos) lo = mid + 1;
      else hi = mid;
    }
    tails[lo] = pos;
    tailIdx[lo] = j;
    prev[j] = lo > 0 ? tailIdx[lo - 1] : -1;
  }
  const stay = new Set();
  for (let j = tails.length ? tailIdx[tails.length - 1] : -1; j >= 0; j = prev[j]) stay.add(nodes[j]);
  let next = null;
  for (let j = nodes.length - 1; j >= 0; j--) {
    const n = nodes[j];
    if (!stay.has(n)) {
      // moveBefore keeps a focused link focused; a node not in the page yet is inserted.
      if (n.isConnected && box.moveBefore) box.moveBefore(n, next);
      else box.insertBefore(n, next);
      moved += 1;
    }
    next = n;
  }
  return moved;
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
  const sumButtons = [...summary.querySelectorAll("[data-group]")].map((b) => ({
    b,
    g: b.dataset.group,
    n: b.querySelector("[data-count]"),
  }));
  attnBox.checked = filters.attention;
  search.value = filters.q;
  sortSel.value = filters.sort;

  // Per vehicle: what groups, filters and sorts it (redone when its values change).
  const info = new Map();
  let alertIndex = alertsByVehicle();
  let nodes = new Map(); // vehicle id -> VehicleNode (of the current view)
  let drawn = new Set(); // the VehicleNodes whose values are drawn
  let byEl = new WeakMap(); // node element -> VehicleNode
  let observer = null;
  let grid;
  let parkedGrid;
  let parkedSection;
  let parkedCount;
  let empty;
  let lastOrder = 0;

  function refresh(v) {
    const alerts = alertIndex.get(v.id) || [];
    const sev = vehicleSeverity(v);
    const group = groupOf(v, alerts, sev);
    const it = {
      id: v.id,
      group,
      keys: sortKeys(v, group, sev),
      attention: sev >= 40,
      parked: isParked(v),
      depot: v.depot,
      hay: `${v.id}\n${v.name || ""}\n${v.depot || ""}`.toLowerCase(),
    };
    info.set(v.id, it);
    const n = nodes.get(v.id);
    if (n) {
      n.setHead(headModel(v));
      const el = n.el;
      const severity = it.parked ? "parked" : it.attention ? "attention" : "ok";
      if (el.dataset.severity !== severity) el.dataset.severity = severity;
      if (el.dataset.group !== group) el.dataset.group = group;
      if (el.dataset.state !== (v.state || "")) el.dataset.state = v.state || "";
      // Drawn values are kept current; a node far away is redrawn when it comes near.
      if (n.drawn) n.draw(bodyModel(v, alerts));
    }
    return it;
  }

  // Draw a node's values (it came near, or was placed in view), or drop them.
  function drawNode(n) {
    const v = vehicles.get(n.id);
    if (!v || n.drawn) return;
    n.draw(bodyModel(v, alertIndex.get(v.id) || []));
    drawn.add(n);
  }
  function clearNode(n) {
    n.clear();
    drawn.delete(n);
  }

  function onIntersect(entries) {
    for (const e of entries) {
      const n = byEl.get(e.target);
      if (!n) continue;
      n.near = e.isIntersecting;
      if (n.near) drawNode(n);
      // A node a filter took out keeps its values (kept current): the filter undone puts it
      // back drawn. One put back far from the viewport drops them then (drawInView).
      else if (n.drawn && n.el.isConnected) clearNode(n);
    }
  }

  function nodeOf(v) {
    let n = nodes.get(v.id);
    if (!n) {
      n = new VehicleNode(v.id, filters.view);
      nodes.set(v.id, n);
      byEl.set(n.el, n);
      observer.observe(n.el);
      refresh(v);
    }
    return n;
  }

  function layout() {
    if (observer) observer.disconnect();
    observer = new IntersectionObserver(onIntersect, { rootMargin: `${NEAR * 100}% 0px` });
    nodes = new Map();
    drawn = new Set();
    byEl = new WeakMap();
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
    parkedCount = body.querySelector("#parked-count");
    empty = body.querySelector("#fleet-empty");
    for (const b of main.querySelectorAll("[data-view]")) {
      b.setAttribute("aria-pressed", String(b.dataset.view === filters.view));
    }
  }

  // The nodes placed in the viewport get their values before the frame is drawn: the
  // observer would only say so after it, showing bare heads for a frame. Those placed near it
  // (within NEAR) are left to the observer, a task later; drawn ones placed beyond drop their
  // values. Every position is read first, then the values written (one layout, not one a
  // node).
  function drawInView() {
    const margin = innerHeight * NEAR;
    const seen = [];
    const near = new Set();
    for (const box of parkedSection.hidden ? [grid] : [grid, parkedGrid]) {
      for (const el of box.children) {
        const r = el.getBoundingClientRect();
        if (r.bottom < -margin) continue;
        if (r.top > innerHeight + margin) break;
        near.add(el);
        if (r.bottom >= 0 && r.top <= innerHeight) seen.push(el);
      }
    }
    for (const el of seen) {
      const n = byEl.get(el);
      if (n && !n.drawn) drawNode(n);
    }
    for (const n of drawn) if (!n.near && n.el.isConnected && !near.has(n.el)) clearNode(n);
  }

  let depotsKnown = -1;
  function fillDepots() {
    if (depotsKnown === vehicles.size) return;
    depotsKnown = vehicles.size;
    const depots = [...new Set([...vehicles.values()].map((v) => v.depot || ""))].sort();
    const have = new Set([...depotSel.options].map((o) => o.value));
    for (const d of depots) if (d && !have.has(d)) depotSel.add(new Option(d, d));
    const want = filters.depot && depots.includes(filters.depot) ? filters.depot : "";
    if (depotSel.value !== want) depotSel.value = want;
  }

  // Which vehicles show, in which order; nodes made for those not built yet.
  function arrange() {
    fillDepots();
    const needle = filters.q.trim().toLowerCase();
    const counts = Object.fromEntries(GROUPS.map(([g]) => [g, 0]));
    const active = [];
    const parked = [];
    let inView = 0;
    for (const v of vehicles.values()) {
      const it = info.get(v.id) || refresh(v);
      if (filters.depot && it.depot !== filters.depot) continue;
      if (needle && !it.hay.includes(needle)) continue;
      counts[it.group] += 1;
      inView += 1;
      if (filters.group && it.group !== filters.group) continue;
      if (filters.attention && !it.attention) continue;
      (it.parked ? parked : active).push(it);
    }
    const k = filters.sort;
    const order = (a, b) => a.keys[k] - b.keys[k] || (a.id < b.id ? -1 : a.id > b.id ? 1 : 0);
    active.sort(order);
    parked.sort(order);
    const els = (list) => list.map((it) => nodeOf(vehicles.get(it.id)).el);
    const moved = placeInOrder(grid, els(active)) + placeInOrder(parkedGrid, els(parked));
    parkedSection.hidden = !parked.length;
    const shown = active.length + parked.length;
    parkedCount.textContent = parked.length ? `(${parked.length})` : "";
    const total = vehicles.size;
    count.textContent = shown === total ? `${total} vehicles` : `${shown} of ${total} vehicles`;
    empty.hidden = active.length > 0;
    empty.textContent = !total
      ? "No vehicles yet."
      : !shown
        ? "No vehicle matches the filters."
        : "Every vehicle shown is parked.";
    for (const { b, g, n } of sumButtons) {
      const c = String(g ? counts[g] : inView);
      if (n.textContent !== c) n.textContent = c;
      const pressed = String(g === filters.group);
      if (b.getAttribute("aria-pressed") !== pressed) b.setAttribute("aria-pressed", pressed);
      if (b.dataset.n !== c) b.dataset.n = c;
    }
    if (moved) drawInView();
    lastOrder = performance.now();
  }

  // Live: dirty vehicles redone once per frame within a budget; the order redone when it may
  // have moved.
  const dirty = new Set();
  let reorder = false;
  let frame = 0;
  let reorderTimer = null;
  function schedule() {
    if (!frame) frame = requestAnimationFrame(flush);
  }
  function flush() {
    frame = 0;
    const t0 = performance.now();
    const k = filters.sort;
    for (const id of dirty) {
      dirty.delete(id);
      const v = vehicles.get(id);
      const old = info.get(id);
      if (!v) {
        info.delete(id);
        const n = nodes.get(id);
        if (n) {
          n.el.remove();
          observer.unobserve(n.el);
          drawn.delete(n);
        }
        nodes.delete(id);
        reorder = true;
        continue;
      }
      const now = refresh(v);
      if (
        !old ||
        old.group !== now.group ||
        old.keys[k] !== now.keys[k] ||
        old.attention !== now.attention ||
        old.parked !== now.parked ||
        old.hay !== now.hay
      ) {
        reorder = true;
      }
      if (performance.now() - t0 > FRAME_BUDGET_MS) break;
    }
    if (dirty.size) {
      schedule();
      return;
    }
    if (reorder && !reorderTimer) {
      // A sort by a streaming value would move rows under the reader's eyes at every frame.
      const wait = VALUE_SORTS.has(k) ? VALUE_SORT_MS - (performance.now() - lastOrder) : 0;
      if (wait > 0) {
        reorderTimer = setTimeout(() => {
          reorderTimer = null;
          schedule();
        }, wait);
        return;
      }
      reorder = false;
      arrange();
    }
  }
  function markAll() {
    for (const id of vehicles.keys()) dirty.add(id);
    for (const id of info.keys()) if (!vehicles.has(id)) dirty.add(id);
    reorder = true;
    schedule();
  }

  const save = () => localStorage.setItem(FILTER_STORE, JSON.stringify(filters));
  // Filters and sorts answer at once (not on the next frame): the nodes exist, they move.
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
    arrange();
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

  const unsub = subscribe((kind, vehicleId, msg) => {
    if (kind === "command") return;
    if (kind === "alerts" || kind.startsWith("alert_")) alertIndex = alertsByVehicle();
    if (kind === "fleet") {
      depotsKnown = -1;
      markAll();
      return;
    }
    if (kind === "vehicles" || kind === "alerts") {
      // Only the vehicles whose alerts, names or depots changed.
      if (kind === "vehicles") depotsKnown = -1;
      if (!msg?.changed) return markAll();
      for (const id of msg.changed) dirty.add(id);
      if (msg.changed.size) schedule();
      return;
    }
    if (!vehicleId) return;
    if (!info.has(vehicleId)) depotsKnown = -1;
    dirty.add(vehicleId);
    schedule();
  });
  let refreshing = false;
  const periodic = setInterval(async () => {
    if (refreshing) return;
    refreshing = true;
    try {
      await refreshFleet();
    } catch {
      /* the banner shows connection trouble */
    } finally {
      refreshing = false;
    }
  }, FLEET_REFRESH_MS);
  layout();
  arrange();
  return () => {
    unsub();
    clearInterval(periodic);
    clearTimeout(reorderTimer);
    cancelAnimationFrame(frame);
    observer?.disconnect();
  };
}
