// The fleet as the browser knows it: loaded from GET /vehicles, kept current by websocket
// messages. Views subscribe and re-render what changed.

import { api } from "./api.js";

// id -> {id, name, depot, state, last_heard, parked_since, units: Map(key -> unit)}; state is
// the API's: ok, attention, offline, parked (every bus silent: ignition off) or not_reporting.
export const vehicles = new Map();
export const commands = new Map(); // command id -> command (as the API shows it)
export const openAlerts = new Map(); // alert id -> alert (active or acknowledged)
const listeners = new Set();

export function subscribe(fn) {
  listeners.add(fn);
  return () => listeners.delete(fn);
}

function notify(kind, vehicleId, msg) {
  for (const fn of listeners) fn(kind, vehicleId, msg);
}

const SLOT_FIELDS = {
  voltages: { v12: "v12", v24: "v24", i12: "i12", i24: "i24" },
  "battery_states/1": { soh: "soh_12v" },
  "battery_states/2": { soc: "soc_12v" },
  "battery_states/3": { soh: "soh_24v" },
  "battery_states/4": { soc: "soc_24v" },
};

function newUnit(bus, sa) {
  return {
    key: `${bus}/${sa}`,
    unit: sa,
    bus,
    series: null,
    model: null,
    software_id: null,
    online: false,
    state: "online", // online, offline or parked (as the API says)
    parked_since: null,
    last_seen: null,
    latest: {},
    flags: {},
    faults: new Map(),
    diagnosis: null,
  };
}

function vehicle(id) {
  let v = vehicles.get(id);
  if (!v) {
    v = { id, name: id, depot: null, state: null, last_heard: null, parked_since: null, units: new Map() };
    vehicles.set(id, v);
  }
  return v;
}

function unitOf(v, bus, sa) {
  const key = `${bus}/${sa}`;
  let u = v.units.get(key);
  if (!u) {
    u = newUnit(bus, sa);
    v.units.set(key, u);
  }
  return u;
}

// A slot's value: whole (`fields`), or the fields that changed since the websocket last sent
// it (`changed`, protocol 2), merged into what the page holds.
function applySlot(u, slot, ts, fields, changed) {
  if (fields === undefined) fields = { ...(u.latest[slot]?.fields || {}), ...changed };
  u.latest[slot] = { ts, fields };
  const map = SLOT_FIELDS[slot];
  if (map) for (const [from, to] of Object.entries(map)) if (from in fields) u[to] = fields[from];
  if (slot === "status") u.flags = fields;
  if (ts && (!u.last_seen || ts > u.last_seen)) u.last_seen = ts;
}

/** Battery B minus battery A: (V24 - V12) - V12, the manuals' imbalance. */
export function imbalance(u) {
  if (u.v12 === null || u.v12 === undefined || u.v24 === null || u.v24 === undefined) return null;
  return u.v24 - 2 * u.v12;
}

function applyUnitRow(u, s) {
  for (const k of ["series", "model", "online", "state", "parked_since", "v12", "v24", "soc_12v", "soc_24v"]) {
    u[k] = s[k];
  }
  u.soh_12v = s.soh_12v;
  u.soh_24v = s.soh_24v;
  if (s.last_seen && (!u.last_seen || s.last_seen > u.last_seen)) u.last_seen = s.last_seen;
  u.diagnosis = s.diagnosis || null;
  const open = new Map();
  for (const f of s.faults || s.active_faults.map((fault) => ({ fault }))) {
    open.set(f.fault, { ...(u.faults.get(f.fault) || {}), ...f });
  }
  u.faults = open;
}

/** Load the fleet (names, depots, every unit's summary and diagnosis) from the REST API. */
export async function loadFleet() {
  const body = await api("/vehicles");
  const seen = new Set();
  for (const row of body.vehicles) {
    seen.add(row.id);
    const v = vehicle(row.id);
    v.name = row.name || row.id;
    v.depot = row.depot;
    applyVehicleState(v, row);
    for (const s of row.units) applyUnitRow(unitOf(v, s.bus, s.unit), s);
  }
  for (const id of [...vehicles.keys()]) if (!seen.has(id)) vehicles.delete(id);
  notify("fleet", null, body);
}

const FLEET_PAGE = 100;

/**
 * Catch up with what the websocket does not say: names and depots, vehicles and units first
 * heard since the fleet was loaded, vehicles gone. Read a page of `GET /vehicles` at a time
 * (each a small parse, the page free to draw between them); values the websocket keeps are
 * left alone. Listeners hear "vehicles" with the ids that changed.
 */
export async function refreshFleet() {
  const seen = new Set();
  const changed = new Set();
  for (let offset = 0; ; offset += FLEET_PAGE) {
    const body = await api(`/vehicles?offset=${offset}&limit=${FLEET_PAGE}`);
    for (const row of body.vehicles) {
      seen.add(row.id);
      const known = vehicles.has(row.id);
      const v = vehicle(row.id);
      const name = row.name || row.id;
      if (!known || v.name !== name || v.depot !== row.depot) changed.add(v.id);
      v.name = name;
      v.depot = row.depot;
      if (!known) applyVehicleState(v, row);
      for (const s of row.units) {
        if (v.units.has(`${s.bus}/${s.unit}`)) continue;
        applyUnitRow(unitOf(v, s.bus, s.unit), s);
        changed.add(v.id);
      }
    }
    if (offset + FLEET_PAGE >= body.total) break;
  }
  for (const id of [...vehicles.keys()]) {
    if (!seen.has(id)) {
      vehicles.delete(id);
      changed.add(id);
    }
  }
  if (changed.size) notify("vehicles", null, { changed });
}

function applyVehicleState(v, s) {
  if (!s || !s.state) return;
  v.state = s.state;
  v.last_heard = s.last_heard ?? null;
  v.parked_since = s.parked_since ?? null;
}

/** Load the open alerts (active and acknowledged) from the REST API; listeners hear
 * "alerts" with the vehicles whose alerts changed (`changed`). */
export async function loadAlerts() {
  const body = await api("/alerts?state=open&limit=1000");
  const before = new Map([...openAlerts].map(([id, a]) => [id, JSON.stringify(a)]));
  const changed = new Set();
  openAlerts.clear();
  for (const a of body.alerts) {
    openAlerts.set(a.id, a);
    if (before.get(a.id) !== JSON.stringify(a)) changed.add(a.vehicle_id);
    before.delete(a.id);
  }
  for (const id of before.keys()) changed.add(JSON.parse(before.get(id)).vehicle_id);
  notify("alerts", null, { ...body, changed });
}

/** Keep an alert as the API or the websocket last showed it. */
export function putAlert(alert) {
  if (alert.state === "cleared") openAlerts.delete(alert.id);
  else openAlerts.set(alert.id, alert);
}

const SEVERITY_RANK = { critical: 3, warning: 2, info: 1 };

/** Open alerts, worst first then newest; of one vehicle when given. */
export function sortedAlerts(vehicleId = null) {
  return [...openAlerts.values()]
    .filter((a) => vehicleId === null || a.vehicle_id === vehicleId)
    .sort(
      (a, b) =>
        (SEVERITY_RANK[b.severity] || 0) - (SEVERITY_RANK[a.severity] || 0) ||
        b.raised_at - a.raised_at,
    );
}

/** Apply one websocket message. */
export function applyMessage(msg) {
  if (msg.type === "command") {
    commands.set(msg.data.id, msg.data);
    notify("command", msg.vehicle_id, msg);
    return;
  }
  if (!msg.vehicle_id) return;
  if (msg.type.startsWith("alert_")) {
    putAlert(msg.data);
    notify(msg.type, msg.vehicle_id, msg);
    return;
  }
  const v = vehicle(msg.vehicle_id);
  if (msg.type === "snapshot") {
    applyVehicleState(v, msg.vehicle);
    for (const s of msg.units) {
      const u = unitOf(v, s.bus, s.sa);
      u.series = s.series;
      u.model = s.model;
      u.software_id = s.software_id;
      u.first_seen = s.first_seen;
      u.online = s.online;
      u.state = s.state || (s.online ? "online" : "offline");
      u.parked_since = s.parked_since ?? null;
      for (const [slot, { ts, fields }] of Object.entries(s.latest)) applySlot(u, slot, ts, fields);
      u.faults = new Map(s.faults.map((f) => [f.fault, f]));
      if (s.diagnosis) u.diagnosis = s.diagnosis;
    }
    notify("snapshot", v.id, msg);
    return;
  }
  if (msg.type === "vehicle_state") {
    applyVehicleState(v, msg.data);
    notify(msg.type, v.id, msg);
    return;
  }
  const u = unitOf(v, msg.bus, msg.unit);
  if (msg.data?.diagnosis) u.diagnosis = msg.data.diagnosis; // protocol 2: when it changed
  switch (msg.type) {
    case "live": {
      applySlot(u, msg.data.slot, msg.ts, msg.data.fields, msg.data.changed);
      const f = msg.data.fields || msg.data.changed;
      if (msg.data.slot === "unit_info" || f.series) {
        if (f.series) u.series = f.series;
        if (f.model) u.model = f.model;
        if (f.software_id) u.software_id = f.software_id;
      }
      break;
    }
    case "status_change": {
      // Protocol 2: the flags that changed ({flag: value}); 1: every flag (`flags`).
      const flags = msg.data.flags || { ...u.flags, ...msg.data.changed };
      u.flags = flags;
      u.latest.status = { ts: msg.ts, fields: flags };
      break;
    }
    case "fault_open":
    case "fault_update":
    case "fault_stale":
      u.faults.set(msg.data.fault, msg.data);
      if (msg.data.fault === "OFFLINE") {
        u.online = false;
        u.state = "offline";
        u.parked_since = null;
      }
      break;
    case "fault_close":
      u.faults.delete(msg.data.fault);
      if (msg.data.fault === "OFFLINE") {
        u.online = true;
        u.state = "online";
      }
      break;
    case "unit_online":
      u.online = true;
      u.state = "online";
      u.parked_since = null;
      break;
    case "unit_parked":
      u.online = false;
      u.state = "parked";
      u.parked_since = msg.data.parked_since;
      break;
    default:
      return;
  }
  notify(msg.type, v.id, msg);
}

// Worst first: an offline unit, then a unit about to shut down or with a failed equalizer,
// then faults, then imbalance. The numbers only order tiles; they mean nothing else.
const CONDITION_RANK = {
  shutdown_risk: 80,
  equalizer_not_functioning: 70,
  abnormal: 60,
  overload: 40,
  unknown: 10,
  normal: 0,
  standby: 0,
};
const FAULT_RANK = { EQFLT: 75, UVF: 65, OVF: 65, EQ_BATTFLT: 60, IMB: 55 };

export function unitSeverity(u) {
  if (u.state === "parked") return 0; // ignition off: nothing to look at
  if (!u.online) return 100;
  let s = CONDITION_RANK[u.diagnosis?.condition] ?? 0;
  for (const f of u.faults.keys()) s = Math.max(s, FAULT_RANK[f] ?? 50);
  const imb = imbalance(u);
  if (imb !== null && Math.abs(imb) > 0.5) s = Math.max(s, 45);
  return s;
}

/** Parked: every bus of the vehicle silent (ignition off); shown apart, greyed. */
export function isParked(v) {
  return v.state === "parked";
}

export function vehicleSeverity(v) {
  if (v.state === "not_reporting") return 95;
  if (isParked(v)) return 0;
  let s = 0;
  for (const u of v.units.values()) s = Math.max(s, unitSeverity(u));
  return v.units.size === 0 ? 90 : s;
}

/** Whether someone should look at this vehicle: offline, faulted or not equalizing right. */
export function needsAttention(v) {
  return vehicleSeverity(v) >= 40;
}

export function sortedVehicles() {
  return [...vehicles.values()].sort(
    (a, b) => vehicleSeverity(b) - vehicleSeverity(a) || a.id.localeCompare(b.id),
  );
}
