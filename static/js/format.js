// Numbers with units and fixed precision: V to 2 decimals, A to 1, % to 1.

const DASH = "—";

function num(value, digits) {
  if (value === null || value === undefined || Number.isNaN(value)) return null;
  return Number(value).toFixed(digits);
}

export const volts = (v) => (num(v, 2) === null ? DASH : `${num(v, 2)} V`);
export const amps = (v) => (num(v, 1) === null ? DASH : `${num(v, 1)} A`);
export const percent = (v) => (num(v, 1) === null ? DASH : `${num(v, 1)} %`);
export const celsius = (v) => (num(v, 1) === null ? DASH : `${num(v, 1)} °C`);
export const minutes = (v) => (num(v, 0) === null ? DASH : `${num(v, 0)} min`);

/** A signed voltage difference, e.g. "+0.06 V". */
export function deltaVolts(v) {
  const s = num(v, 2);
  if (s === null) return DASH;
  return `${v > 0 ? "+" : ""}${s} V`;
}

/** A value in a parameter's own unit, with the precision its resolution needs. */
export function inUnit(value, unit, resolution = 0.01) {
  if (value === null || value === undefined) return DASH;
  const digits = Math.max(0, Math.min(3, Math.ceil(-Math.log10(resolution || 1) - 1e-9)));
  return `${Number(value).toFixed(digits)}${unit ? ` ${unit}` : ""}`;
}

const pad = (n) => String(n).padStart(2, "0");

// One time format everywhere, in the browser's locale and zone, the zone always shown:
// "14:03 CET" today, "21 Nov, 14:03 CET" (as the locale writes it) on another day of this
// year, with the year before that. 24-hour clock: a depot runs round the clock.
const TIME = { hour: "2-digit", minute: "2-digit", hourCycle: "h23", timeZoneName: "short" };
const timeOnly = new Intl.DateTimeFormat(undefined, TIME);
const thisYear = new Intl.DateTimeFormat(undefined, { ...TIME, day: "numeric", month: "short" });
const otherYear = new Intl.DateTimeFormat(undefined, {
  ...TIME,
  day: "numeric",
  month: "short",
  year: "numeric",
});

/** A time in the one format of the dashboard (see above); "—" for none. */
export function clockTime(ts, now = Date.now()) {
  if (!ts) return DASH;
  const d = new Date(ts * 1000);
  const n = new Date(now);
  if (n.toDateString() === d.toDateString()) return timeOnly.format(d);
  return (n.getFullYear() === d.getFullYear() ? thisYear : otherYear).format(d);
}

/** The same format as `clockTime` (kept for the callers that name it so). */
export const dateTime = (ts) => clockTime(ts);

/** A file-name stamp, e.g. "2026-11-21-14-03-07" (local time). */
export function fileStamp(ts) {
  const d = new Date(ts * 1000);
  return (
    `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())}-` +
    `${pad(d.getHours())}-${pad(d.getMinutes())}-${pad(d.getSeconds())}`
  );
}

/** A duration in words, e.g. "3 h 04 min", "42 s". */
export function duration(seconds) {
  if (seconds === null || seconds === undefined) return DASH;
  const s = Math.max(0, Math.round(seconds));
  if (s < 60) return `${s} s`;
  if (s < 3600) return `${Math.floor(s / 60)} min ${pad(s % 60)} s`;
  if (s < 86400) return `${Math.floor(s / 3600)} h ${pad(Math.floor((s % 3600) / 60))} min`;
  return `${Math.floor(s / 86400)} d ${Math.floor((s % 86400) / 3600)} h`;
}

/** "12 s ago" style age of a timestamp. */
export function age(ts, now = Date.now() / 1000) {
  if (!ts) return DASH;
  return `${duration(now - ts)} ago`;
}

/** Escape text for HTML templates. */
export function esc(value) {
  return String(value ?? "").replace(
    /[&<>"']/g,
    (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c],
  );
}
