// Fleet overview: one tile per vehicle, worst first, filtered by depot and "needs attention",
// updated from the store as websocket messages arrive.

import {
  loadFleet,
  imbalance,
  isParked,
  needsAttention,
  sortedAlerts,
  sortedVehicles,
  subscribe,
  vehicles,
} from "./store.js";
import { age, clockTime, deltaVolts, esc, percent, volts } from "./format.js";

const FILTER_STORE = "eqgw.overview.filters";
const SUMMARY_REFRESH_MS = 10_000; // the diagnosis comes from the API, not the events

const CONDITION_LABEL = {
  standby: "Standby",
  normal: "Equalizing",
  overload: "Overload",
  equalizer_not_functioning: "Equalizer not working",
  abnormal: "Abnormal",
  shutdown_risk: "Shutdown risk",
  unknown: "No reading yet",
};

function loadFilters() {
  try {
    return { depot: "", attention: false, ...JSON.parse(localStorage.getItem(FILTER_STORE)) };
  } catch {
    return { depot: "", attention: false };
  }
}

function unitHtml(u, many) {
  const imb = imbalance(u);
  const faults = [...u.faults.values()].filter((f) => f.fault !== "OFFLINE");
  const parked = u.state === "parked";
  const cond = parked ? "parked" : u.online ? u.diagnosis?.condition || "unknown" : "offline";
  const label = parked ? "Parked" : u.online ? esc(CONDITION_LABEL[cond] || cond) : "Offline";
  const text = parked
    ? `: last heard ${esc(clockTime(u.last_seen))}`
    : u.online
      ? u.diagnosis?.text
        ? `: ${esc(u.diagnosis.text)}`
        : ""
      : `: last heard ${age(u.last_seen)}`;
  const batt = (label, soc, soh) =>
    soc === null && soh === null
      ? ""
      : `<div class="batt"><span class="k">${label}</span>
         <span>SOC <b>${percent(soc)}</b></span><span>SOH <b>${percent(soh)}</b></span></div>`;
  return `
    <div class="unit" data-unit="${u.unit}">
      ${many || u.series ? `<div class="unit-id">SA ${u.unit}${u.series ? ` · ${u.series}-series` : ""}</div>` : ""}
      <dl class="big">
        <div><dt>V12</dt><dd data-field="v12">${volts(u.v12)}</dd></div>
        <div><dt>V24</dt><dd data-field="v24">${volts(u.v24)}</dd></div>
        <div><dt>B − A</dt><dd data-field="imbalance" class="${imb !== null && Math.abs(imb) > 0.1 ? "warn" : ""}">${deltaVolts(imb)}</dd></div>
      </dl>
      ${batt("12 V battery (A)", u.soc_12v ?? null, u.soh_12v ?? null)}
      ${batt("24 V battery (B)", u.soc_24v ?? null, u.soh_24v ?? null)}
      <ul class="faults" aria-label="Active faults">
        ${faults
          .map(
            (f) => `<li class="fault" data-fault="${esc(f.fault)}">${esc(f.fault)}${
              f.occurrence_count ? ` <span class="count">×${f.occurrence_count}</span>` : ""
            }${f.state === "stale" ? " <span class=\"count\">(stale)</span>" : ""}</li>`,
          )
          .join("")}
      </ul>
      <p class="diag" data-condition="${cond}"><b>${label}</b>${text}</p>
    </div>`;
}

function alertsHtml(v) {
  const open = sortedAlerts(v.id);
  if (!open.length) return "";
  return `<ul class="alert-chips" aria-label="Open alerts">${open
    .map(
      (a) => `<li class="alert-chip" data-severity="${esc(a.severity)}" data-rule="${esc(a.rule)}"
        data-state="${esc(a.state)}" title="${esc(a.message)}">${esc(a.rule.replaceAll("_", " "))}${
          a.state === "acknowledged" ? " ✓" : ""
        }${a.muted ? " (muted)" : ""}</li>`,
    )
    .join("")}</ul>`;
}

// The vehicle's state badge: the API's state when known, else from its units.
function stateBadge(v, units) {
  if (v.state === "parked") return '<span class="state parked">Parked</span>';
  if (v.state === "not_reporting") return '<span class="state off">Not reporting</span>';
  const online = units.some((u) => u.online);
  return `<span class="state ${online ? "on" : "off"}">${online ? "Online" : "Offline"}</span>`;
}

function tileHtml(v) {
  const units = [...v.units.values()].sort((a, b) => a.unit - b.unit);
  const attention = needsAttention(v);
  const heard =
    isParked(v) || v.state === "not_reporting"
      ? ` · <span class="heard">last heard ${esc(clockTime(v.last_heard))}</span>`
      : "";
  return `
    <a class="tile-link" href="#/vehicle/${encodeURIComponent(v.id)}">
      <h2>${esc(v.name)}</h2>
      ${stateBadge(v, units)}
    </a>
    <div class="tile-sub">${esc(v.depot || "no depot")}${heard}${attention ? ' · <b class="attn">needs attention</b>' : ""}</div>
    ${alertsHtml(v)}
    ${units.length ? units.map((u) => unitHtml(u, units.length > 1)).join("") : '<p class="diag">No unit heard yet.</p>'}`;
}

export function renderOverview(main) {
  const filters = loadFilters();
  main.innerHTML = `
    <section class="page overview">
      <div class="page-head">
        <h1>Fleet</h1>
        <div class="filters" role="group" aria-label="Filters">
          <label>Depot / group
            <select id="f-depot"><option value="">All</option></select>
          </label>
          <label class="check"><input type="checkbox" id="f-attn"> Needs attention only</label>
          <span id="f-count" class="muted" aria-live="polite"></span>
        </div>
      </div>
      <div class="tiles" id="tiles"></div>
      <section class="parked-fleet" id="parked" hidden aria-labelledby="parked-h">
        <h2 id="parked-h">Parked <span class="muted" id="parked-count"></span></h2>
        <p class="muted">Ignition off: every bus of these vehicles is silent. No alert is raised for them.</p>
        <div class="tiles" id="parked-tiles"></div>
      </section>
    </section>`;
  const grid = main.querySelector("#tiles");
  const parkedGrid = main.querySelector("#parked-tiles");
  const parkedSection = main.querySelector("#parked");
  const depotSel = main.querySelector("#f-depot");
  const attnBox = main.querySelector("#f-attn");
  const count = main.querySelector("#f-count");
  attnBox.checked = filters.attention;
  const tiles = new Map();

  function fillDepots() {
    const depots = [...new Set([...vehicles.values()].map((v) => v.depot || ""))].sort();
    const have = [...depotSel.options].map((o) => o.value);
    for (const d of depots) {
      if (d && !have.includes(d)) depotSel.add(new Option(d, d));
    }
    depotSel.value = filters.depot && depots.includes(filters.depot) ? filters.depot : "";
  }

  function draw() {
    fillDepots();
    const shown = sortedVehicles().filter(
      (v) =>
        (!filters.depot || v.depot === filters.depot) && (!filters.attention || needsAttention(v)),
    );
    const keep = new Set(shown.map((v) => v.id));
    for (const [id, el] of tiles) {
      if (!keep.has(id)) {
        el.remove();
        tiles.delete(id);
      }
    }
    const active = shown.filter((v) => !isParked(v));
    const parked = shown.filter(isParked);
    const place = (v, i, into) => {
      let el = tiles.get(v.id);
      const html = tileHtml(v);
      if (!el) {
        el = document.createElement("article");
        el.className = "tile";
        el.dataset.vehicle = v.id;
        tiles.set(v.id, el);
      }
      if (el.dataset.html !== html) {
        const hadFocus = el.contains(document.activeElement);
        el.innerHTML = html;
        el.dataset.html = html;
        if (hadFocus) el.querySelector(".tile-link").focus();
      }
      el.dataset.severity = isParked(v) ? "parked" : needsAttention(v) ? "attention" : "ok";
      el.dataset.state = v.state || "";
      if (into.children[i] !== el) into.insertBefore(el, into.children[i] || null);
    };
    active.forEach((v, i) => place(v, i, grid));
    parked.forEach((v, i) => place(v, i, parkedGrid));
    parkedSection.hidden = !parked.length;
    main.querySelector("#parked-count").textContent = parked.length ? `(${parked.length})` : "";
    const total = vehicles.size;
    count.textContent =
      shown.length === total ? `${total} vehicles` : `${shown.length} of ${total} vehicles`;
    if (!shown.length) {
      grid.innerHTML = `<p class="muted">${total ? "No vehicle matches the filters." : "No vehicles yet."}</p>`;
      tiles.clear();
    } else if (!active.length) {
      if (!grid.querySelector(":scope > p")) {
        grid.innerHTML = '<p class="muted">Every vehicle shown is parked.</p>';
      }
    } else {
      grid.querySelector(":scope > p")?.remove();
    }
  }

  let pending = false;
  function schedule() {
    if (pending) return;
    pending = true;
    requestAnimationFrame(() => {
      pending = false;
      draw();
    });
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
  depotSel.addEventListener("change", () => {
    filters.depot = depotSel.value;
    save();
    draw();
  });
  attnBox.addEventListener("change", () => {
    filters.attention = attnBox.checked;
    save();
    draw();
  });
  const unsub = subscribe((kind) => {
    if (
      kind.startsWith("fault_") ||
      kind === "status_change" ||
      kind === "unit_online" ||
      kind === "unit_parked" ||
      kind === "vehicle_state"
    ) {
      refreshSoon();
    }
    if (kind !== "command") schedule();
  });
  const periodic = setInterval(refreshSoon, SUMMARY_REFRESH_MS);
  const ages = setInterval(schedule, 5000); // "last heard ... ago" of offline units
  draw();
  return () => {
    unsub();
    clearInterval(periodic);
    clearInterval(ages);
    clearTimeout(refresh);
  };
}
