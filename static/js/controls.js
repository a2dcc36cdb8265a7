// Operator controls of one unit: control flags, parameter writes, requests. Every action asks
// for confirmation, then shows the command's life as the websocket reports it. Control and
// parameter frames are broadcasts: the dialog lists every unit on the bus they reach, and the
// write says it knows (`all_units`) when there are several.

import { api } from "./api.js";
import { confirmAction } from "./dialog.js";
import { dateTime, esc, inUnit } from "./format.js";
import { commands, subscribe } from "./store.js";

const FINAL = new Set(["confirmed", "sent", "unconfirmed", "refused", "failed", "expired", "cancelled"]);

// field -> the status flag that shows its state, and how to say it.
export const CONTROLS = [
  { field: "jump_start_override", flag: "state_can_jso", label: "Jump-start override" },
  { field: "can_onoff_enable", flag: "state_onoff_en", label: "CAN on/off enable" },
  { field: "equalizer_on", flag: "eq_state_onoff", label: "Equalizer on/off" },
  {
    field: "smart_sensor_messages",
    flag: "can_ss_msg_on",
    label: "Smart Sensor messages",
    series: 70,
  },
];

const REQUESTS = [
  { what: "dm1", label: "Request DM1" },
  { what: "component_id", label: "Request component ID" },
  { what: "software_id", label: "Request software ID" },
];

let catalogue = null;
async function parameters() {
  if (!catalogue) catalogue = api("/parameters").then((b) => b.parameters);
  return catalogue;
}

function describe(cmd) {
  const req = cmd.request || {};
  if (cmd.kind === "request") return `request ${req.what}`;
  const parts = Object.entries(req)
    .filter(([k]) => k !== "unit" && k !== "expires_in_s" && k !== "all_units")
    .map(([k, v]) => `${k.replaceAll("_", " ")} ${v === true ? "on" : v === false ? "off" : v}`);
  return parts.join(", ") || cmd.kind;
}

/**
 * The control panel of a unit; returns {el, update(unit), destroy()}. `busUnits()` gives the
 * units known on the unit's bus (the ones a control or parameter write reaches).
 */
export function controlPanel(vehicleId, unit, busUnits = () => [unit]) {
  const el = document.createElement("div");
  el.className = "controls";
  el.dataset.unit = unit.unit;
  const mine = []; // commands started here, newest first
  el.innerHTML = `
    <h3>Controls <span class="muted">(operator)</span></h3>
    <div class="control-rows">
      ${CONTROLS.map(
        (c) => `
        <div class="control-row" data-control="${c.field}">
          <span>${c.label}${c.series ? ` <span class="muted">(${c.series}-series)</span>` : ""}:
            <span class="now" data-now>—</span></span>
          <span>
            <button type="button" class="btn btn-small" data-set="true">Turn on</button>
            <button type="button" class="btn btn-small" data-set="false">Turn off</button>
          </span>
        </div>`,
      ).join("")}
    </div>
    <h3>Parameter write</h3>
    <form class="param-form" novalidate>
      <label>Parameter <select name="name" required></select></label>
      <label>Value <input name="value" type="number" inputmode="decimal" required></label>
      <button class="btn" type="submit">Write…</button>
      <p class="param-hint" aria-live="polite"></p>
    </form>
    <h3>Requests</h3>
    <div class="requests">
      ${REQUESTS.map((r) => `<button type="button" class="btn btn-small" data-request="${r.what}">${r.label}</button>`).join(" ")}
    </div>
    <h3>Commands</h3>
    <ul class="cmds" aria-live="polite"></ul>`;

  const list = el.querySelector(".cmds");
  function drawCommands() {
    list.innerHTML = mine.length
      ? mine
          .slice(0, 8)
          .map((m) => {
            const cmd = commands.get(m.id) || m.cmd;
            const state = m.refused ? "refused" : cmd?.state || "queued";
            const reason = m.refused || cmd?.reason;
            return `<li class="cmd" data-command="${esc(m.id)}">
              <span class="cmd-state" data-state="${state}"${state === "unconfirmed" ? ' title="sent, not confirmed: it may still take effect"' : ""}>${state}</span>
              <span>${esc(m.what)}</span>
              <span class="muted">${dateTime(cmd?.updated_at || m.at)}${cmd?.sends ? ` · ${cmd.sends} sends` : ""}</span>
              ${reason ? `<span class="${m.refused || state === "failed" || state === "refused" || state === "unconfirmed" ? "warn" : "muted"}">${esc(reason)}</span>` : ""}
            </li>`;
          })
          .join("")
      : '<li class="muted">None sent from this page yet.</li>';
  }
  drawCommands();

  // Every unit a broadcast reaches, as the dialog lists it and the API will name it.
  function reach() {
    const all = busUnits();
    const units = (all.length ? all : [unit]).slice().sort((a, b) => a.unit - b.unit);
    const bus = unit.bus ? ` on bus ${unit.bus}` : "";
    return {
      count: units.length,
      text:
        units.length > 1
          ? `This write reaches every equalizer${bus} (${units.length} units), not only SA ${unit.unit}:`
          : `This write reaches the one equalizer${bus}:`,
      units: units.map((u) => ({
        sa: u.unit,
        label: `SA ${u.unit}${u.series ? ` · ${u.series}-series` : " · series not known yet"}${u.online === false ? " · offline" : ""}`,
      })),
    };
  }

  async function submit(path, body, what) {
    const entry = { id: `local-${Date.now()}`, what, at: Date.now() / 1000 };
    mine.unshift(entry);
    drawCommands();
    try {
      const cmd = await api(`/vehicles/${encodeURIComponent(vehicleId)}/${path}`, {
        method: "POST",
        body: { unit: unit.unit, ...body },
      });
      entry.id = cmd.id;
      entry.cmd = cmd;
      // The websocket may already have told a later state; keep the newest.
      if (!commands.has(cmd.id)) commands.set(cmd.id, cmd);
      poll(entry);
    } catch (err) {
      entry.refused = `refused (${err.status}): ${err.message}`;
    }
    drawCommands();
  }

  // Websocket events drive the states; a slow poll covers a dropped connection.
  function poll(entry) {
    const timer = setInterval(async () => {
      const known = commands.get(entry.id);
      if (!el.isConnected || (known && FINAL.has(known.state))) {
        clearInterval(timer);
        return;
      }
      try {
        const cmd = await api(`/commands/${encodeURIComponent(entry.id)}`);
        const now = commands.get(entry.id);
        if (!now || cmd.updated_at >= now.updated_at) commands.set(cmd.id, cmd);
        drawCommands();
      } catch {
        /* next round */
      }
    }, 3000);
  }

  for (const row of el.querySelectorAll("[data-control]")) {
    const def = CONTROLS.find((c) => c.field === row.dataset.control);
    for (const btn of row.querySelectorAll("[data-set]")) {
      btn.addEventListener("click", async () => {
        const on = btn.dataset.set === "true";
        const body = { [def.field]: on };
        let text = `${on ? "Turn on" : "Turn off"} ${def.label.toLowerCase()} on ${vehicleId}?`;
        if (def.field === "equalizer_on" && unit.flags.state_onoff_en !== "active") {
          // The unit obeys on/off only while CAN on/off is enabled: enable it in the same command.
          body.can_onoff_enable = true;
          text += " CAN on/off is not enabled: this also enables it.";
        }
        const r = reach();
        if (r.count > 1) body.all_units = true; // the dialog listed every unit it reaches
        if (await confirmAction(def.label, text, "Send", r)) await submit("commands", body, `${def.label} ${on ? "on" : "off"}`);
      });
    }
  }

  for (const btn of el.querySelectorAll("[data-request]")) {
    btn.addEventListener("click", async () => {
      const r = REQUESTS.find((x) => x.what === btn.dataset.request);
      if (await confirmAction(r.label, `${r.label} from ${vehicleId}, unit SA ${unit.unit}?`)) {
        await submit("requests", { what: r.what }, r.label);
      }
    });
  }

  const form = el.querySelector(".param-form");
  const select = form.elements.name;
  const input = form.elements.value;
  const hint = form.querySelector(".param-hint");
  let specs = [];
  function spec() {
    return specs.find((p) => p.name === select.value);
  }
  let shownSeries;
  function fillParams() {
    shownSeries = unit.series;
    // A unit whose series is unknown only gets what both series accept (as the API enforces).
    const fits = (p) => (unit.series ? p.series.includes(unit.series) : p.series.includes(70) && p.series.includes(80));
    const chosen = select.value;
    select.innerHTML = specs
      .filter(fits)
      .map((p) => `<option value="${esc(p.name)}">${esc(p.name.replaceAll("_", " "))}</option>`)
      .join("");
    if (chosen && [...select.options].some((o) => o.value === chosen)) select.value = chosen;
    showRange();
  }
  function showRange() {
    const p = spec();
    if (!p) return;
    input.min = p.minimum;
    input.max = p.maximum;
    input.step = p.resolution;
    hint.textContent = `Range ${inUnit(p.minimum, p.unit, p.resolution)} to ${inUnit(p.maximum, p.unit, p.resolution)}, step ${p.resolution}${p.unit ? ` ${p.unit}` : ""}. ${p.description}`;
    hint.classList.remove("warn");
  }
  select.addEventListener("change", showRange);
  parameters().then((all) => {
    specs = all;
    fillParams();
  });
  form.addEventListener("submit", async (ev) => {
    ev.preventDefault();
    const p = spec();
    const value = Number(input.value);
    if (!p || input.value.trim() === "" || Number.isNaN(value)) {
      hint.textContent = "Enter a number.";
      hint.classList.add("warn");
      input.focus();
      return;
    }
    if (value < p.minimum || value > p.maximum) {
      hint.textContent = `${inUnit(value, p.unit, p.resolution)} is outside the manuals' range ${inUnit(p.minimum, p.unit, p.resolution)} to ${inUnit(p.maximum, p.unit, p.resolution)}: not sent.`;
      hint.classList.add("warn");
      input.focus();
      return;
    }
    const steps = (value - p.minimum) / p.resolution;
    if (Math.abs(steps - Math.round(steps)) > 1e-6) {
      hint.textContent = `The unit takes steps of ${p.resolution}${p.unit ? ` ${p.unit}` : ""}: not sent.`;
      hint.classList.add("warn");
      input.focus();
      return;
    }
    showRange();
    const label = `${p.name.replaceAll("_", " ")} = ${inUnit(value, p.unit, p.resolution)}`;
    const r = reach();
    const body = { [p.name]: value };
    if (r.count > 1) body.all_units = true; // the dialog listed every unit it reaches
    if (await confirmAction("Parameter write", `Write ${label} to ${vehicleId}? Parameter writes cannot be read back: the result is "sent", not confirmed.`, "Write", r)) {
      await submit("parameters", body, label);
    }
  });

  const unsub = subscribe((kind) => {
    if (kind === "command") drawCommands();
  });

  function update(u) {
    unit = u;
    for (const row of el.querySelectorAll("[data-control]")) {
      const def = CONTROLS.find((c) => c.field === row.dataset.control);
      const flag = u.flags?.[def.flag];
      row.querySelector("[data-now]").textContent =
        flag === "active" ? "on" : flag === "inactive" ? "off" : flag ? flag.replaceAll("_", " ") : "—";
      row.hidden = Boolean(def.series && u.series && u.series !== def.series);
    }
    if (specs.length && u.series !== shownSeries) fillParams();
  }
  update(unit);
  return { el, update, destroy: unsub };
}
