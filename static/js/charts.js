// Time-series charts on uPlot: history from the API (downsampled by range), extended live,
// drag to zoom (all charts together), double-click or "Reset zoom" to go back.

/* global uPlot */

const COLORS = ["#0047b3", "#c2410c", "#0a6b2d", "#7e22ce"];
const SYNC_KEY = "eqgw-vehicle";

/** The chart definitions: which fields, how to derive the plotted series, the unit. */
export const CHARTS = [
  {
    id: "voltages",
    title: "Voltages",
    fields: ["v12", "v24"],
    series: [
      { label: "V12 (battery A)", unit: "V", digits: 2, scale: "v12", get: (r) => r.v12 },
      { label: "V24 (system)", unit: "V", digits: 2, scale: "v24", get: (r) => r.v24 },
    ],
  },
  {
    id: "imbalance",
    title: "Imbalance B − A",
    fields: ["v12", "v24"],
    series: [
      {
        label: "B − A",
        unit: "V",
        digits: 2,
        axisDigits: 3, // ticks 5 mV apart would print the same at 2 decimals
        scale: "V",
        get: (r) => (r.v12 == null || r.v24 == null ? null : r.v24 - 2 * r.v12),
      },
    ],
  },
  {
    id: "currents",
    title: "Currents",
    fields: ["i12", "i24"],
    series: [
      { label: "I12 (battery A)", unit: "A", digits: 1, scale: "A", get: (r) => r.i12 },
      { label: "I24 (battery B)", unit: "A", digits: 1, scale: "A", get: (r) => r.i24 },
    ],
  },
  {
    id: "battery",
    title: "State of charge and health",
    fields: ["soc_12v", "soc_24v", "soh_12v", "soh_24v"],
    series: [
      { label: "SOC 12 V (A)", unit: "%", digits: 1, scale: "%", get: (r) => r.soc_12v },
      { label: "SOC 24 V (B)", unit: "%", digits: 1, scale: "%", get: (r) => r.soc_24v },
      { label: "SOH 12 V (A)", unit: "%", digits: 1, scale: "%", get: (r) => r.soh_12v },
      { label: "SOH 24 V (B)", unit: "%", digits: 1, scale: "%", get: (r) => r.soh_24v },
    ],
  },
];

export const ALL_FIELDS = [...new Set(CHARTS.flatMap((c) => c.fields))];

/** Rows {ts, field: value, ...} from the API's series (raw values or bucket averages). */
export function rowsFromHistory(series) {
  const byTs = new Map();
  for (const [field, points] of Object.entries(series)) {
    for (const p of points) {
      const ts = Math.round(p.ts * 1000) / 1000;
      let row = byTs.get(ts);
      if (!row) {
        row = { ts };
        byTs.set(ts, row);
      }
      row[field] = p.value ?? p.avg;
    }
  }
  return [...byTs.values()].sort((a, b) => a.ts - b.ts);
}

// The smallest y span shown, so a steady 12.46 V reads as steady, not as noise or 0..50 V.
const MIN_SPAN = { V: 0.2, A: 2, "%": 2 };

function paddedRange(minSpan = 1) {
  return (u, min, max) => {
    if (min == null || max == null) return [0, 1];
    const pad = Math.max((max - min) * 0.1, (minSpan - (max - min)) / 2, 0);
    return [min - pad, max + pad];
  };
}

function seriesOpts(def, i) {
  return {
    label: def.label,
    scale: def.scale,
    stroke: COLORS[i % COLORS.length],
    width: 2,
    spanGaps: true,
    points: { show: false },
    value: (u, v) => (v == null ? "—" : `${v.toFixed(def.digits)} ${def.unit}`),
  };
}

function axisOpts(def, side) {
  return {
    scale: def.scale,
    side,
    stroke: "#0b0d12",
    grid: { stroke: "#d5d9e0", width: 1 },
    ticks: { stroke: "#9aa1ad" },
    size: 84,
    font: "14px system-ui, sans-serif",
    values: (u, vals) => vals.map((v) => `${v.toFixed(def.axisDigits ?? def.digits)} ${def.unit}`),
  };
}

/** A set of charts that zoom together. */
export class ChartSet {
  constructor(container, { onZoom }) {
    this.container = container;
    this.onZoom = onZoom;
    this.plots = new Map();
    this.rows = [];
    this.syncing = false;
    this.zoomed = false;
    this.range = null;
    this.resizeObserver = new ResizeObserver(() => this.resize());
    this.resizeObserver.observe(container);
  }

  destroy() {
    this.resizeObserver.disconnect();
    for (const p of this.plots.values()) p.plot?.destroy();
    this.plots.clear();
  }

  /** Replace the data (history for [from, to]). */
  setRows(rows, from, to) {
    this.rows = rows;
    this.range = { from, to };
    this.zoomed = false;
    this.draw();
  }

  /** Add live rows at the end; the window slides when `slideFrom` is given. */
  extend(row, slideFrom) {
    // Frames of different kinds arrive a little out of order: merge by time, keep sorted.
    let i = this.rows.length;
    while (i > 0 && this.rows[i - 1].ts > row.ts) i -= 1;
    if (i > 0 && this.rows[i - 1].ts === row.ts) Object.assign(this.rows[i - 1], row);
    else this.rows.splice(i, 0, row);
    if (slideFrom !== undefined) {
      while (this.rows.length && this.rows[0].ts < slideFrom) this.rows.shift();
      this.range = { from: slideFrom, to: row.ts };
    }
    if (!this.zoomed) this.update();
  }

  /** The rows inside the shown x range (what a CSV export should hold). */
  visibleRows() {
    const first = [...this.plots.values()].find((p) => p.plot)?.plot;
    if (!first) return this.rows;
    const { min, max } = first.scales.x;
    return this.rows.filter((r) => r.ts >= min && r.ts <= max);
  }

  resetZoom() {
    this.zoomed = false;
    this.update();
    this.onZoom(false);
  }

  width() {
    const any = this.container.querySelector(".chart");
    return Math.max(280, (any?.clientWidth || this.container.clientWidth) - 20);
  }

  resize() {
    const w = this.width();
    for (const p of this.plots.values()) if (p.plot && p.plot.width !== w) p.plot.setSize({ width: w, height: 240 });
  }

  data(def) {
    const xs = [];
    const ys = def.series.map(() => []);
    for (const r of this.rows) {
      const vals = def.series.map((s) => s.get(r));
      if (vals.every((v) => v == null)) continue;
      xs.push(r.ts);
      vals.forEach((v, i) => ys[i].push(v ?? null));
    }
    return [xs, ...ys];
  }

  update() {
    for (const def of CHARTS) {
      const entry = this.plots.get(def.id);
      const data = this.data(def);
      if (!entry?.plot || !data[0].length) {
        this.draw();
        return;
      }
      entry.plot.setData(data, false);
      entry.plot.root.closest(".chart").dataset.points = data[0].length;
      this.syncing = true;
      entry.plot.setScale("x", { min: this.range.from, max: this.range.to });
      this.syncing = false;
    }
  }

  draw() {
    for (const p of this.plots.values()) p.plot?.destroy();
    this.plots.clear();
    this.container.innerHTML = CHARTS.map(
      (def) => `<figure class="chart" data-chart="${def.id}"><h3>${def.title}</h3><div class="plot"></div></figure>`,
    ).join("");
    const width = this.width();
    for (const def of CHARTS) {
      const el = this.container.querySelector(`[data-chart="${def.id}"] .plot`);
      const data = this.data(def);
      if (!data[0].length) {
        el.innerHTML = '<p class="empty">No data in this range.</p>';
        el.closest(".chart").dataset.points = 0;
        this.plots.set(def.id, { plot: null });
        continue;
      }
      const scales = [...new Set(def.series.map((s) => s.scale))];
      const opts = {
        width,
        height: 240,
        cursor: {
          sync: { key: SYNC_KEY },
          drag: { x: true, y: false },
          // Double-click goes back to the chosen range, not just to the data's extent.
          bind: { dblclick: () => () => (this.resetZoom(), null) },
        },
        scales: Object.fromEntries([
          ["x", { time: true }],
          ...scales.map((sc) => [sc, { range: paddedRange(MIN_SPAN[def.series.find((s) => s.scale === sc).unit]) }]),
        ]),
        series: [{ label: "Time", value: "{YYYY}-{MM}-{DD} {HH}:{mm}:{ss}" }, ...def.series.map(seriesOpts)],
        axes: [
          { stroke: "#0b0d12", grid: { stroke: "#d5d9e0" }, font: "14px system-ui, sans-serif" },
          ...scales.map((sc, i) => axisOpts(def.series.find((s) => s.scale === sc), i === 0 ? 3 : 1)),
        ],
        hooks: {
          setScale: [
            (u, key) => {
              if (key !== "x" || this.syncing) return;
              const { min, max } = u.scales.x;
              const full = this.range && min <= this.range.from + 1 && max >= this.range.to - 1;
              this.zoomed = !full;
              this.onZoom(this.zoomed);
              this.syncing = true;
              for (const other of this.plots.values()) {
                if (other.plot && other.plot !== u) other.plot.setScale("x", { min, max });
              }
              this.syncing = false;
            },
          ],
        },
      };
      const plot = new uPlot(opts, data, el);
      el.closest(".chart").dataset.points = data[0].length;
      this.syncing = true;
      plot.setScale("x", { min: this.range.from, max: this.range.to });
      this.syncing = false;
      this.plots.set(def.id, { plot });
    }
  }
}

/** CSV of rows: one column per field, times in ISO 8601 (UTC). */
export function toCsv(rows) {
  const head = ["time_utc", "ts", ...ALL_FIELDS, "imbalance_v"];
  const lines = [head.join(",")];
  for (const r of rows) {
    const imb = r.v12 == null || r.v24 == null ? "" : (r.v24 - 2 * r.v12).toFixed(3);
    lines.push(
      [new Date(r.ts * 1000).toISOString(), r.ts, ...ALL_FIELDS.map((f) => r[f] ?? ""), imb].join(","),
    );
  }
  return `${lines.join("\n")}\n`;
}
