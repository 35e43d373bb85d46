// uPlot charts: a group of time charts (one per quantity) sharing cursor and zoom, and the fit-vs-SOC plots.
import uPlot from "uplot";
import "uplot/dist/uPlot.min.css";
import { h, hms } from "./util.js";

export const SERIES = {
  voltage_v: { label: "Voltage", unit: "V", color: "#1f6feb", digits: 4 },
  current_a: { label: "Current", unit: "A", color: "#d92d20", digits: 3 },
  soc: { label: "SOC", unit: "%", color: "#0e9384", digits: 1, scale: 100 },
  surface_c: { label: "Surface", unit: "°C", color: "#f79009", digits: 2 },
  t1_c: { label: "T1 (+)", unit: "°C", color: "#7a5af8", digits: 2 },
  t2_c: { label: "T2 (−)", unit: "°C", color: "#ee46bc", digits: 2 },
  ambient_c: { label: "Chamber", unit: "°C", color: "#475467", digits: 2 },
  heat_flux_w_per_m2: { label: "Heat flux", unit: "W/m²", color: "#12b76a", digits: 1 },
};

export const PANELS = [
  { title: "Voltage", unit: "V", keys: ["voltage_v"] },
  { title: "Current", unit: "A", keys: ["current_a"] },
  { title: "Temperatures: surface, terminals T1 (+) and T2 (−), chamber", unit: "°C", keys: ["surface_c", "t1_c", "t2_c", "ambient_c"] },
  { title: "Heat flux", unit: "W/m²", keys: ["heat_flux_w_per_m2"] },
];

// A samples response (GET /runs/{id}/samples) as uPlot columns [x, y1, y2, ...]. Decimated responses carry
// min and max per bucket: both are plotted (min at the bucket start, max half a bucket later), so a
// one-sample spike stays visible however far out the plot is zoomed.
export function toColumns(resp, keys) {
  const t = resp.time_s || [];
  const series = resp.series || {};
  if (!resp.decimated) {
    return [t, ...keys.map((k) => (series[k] ? series[k].map((v) => scaled(k, v)) : new Array(t.length).fill(null)))];
  }
  const half = (resp.bucket_s || 0) / 2, n = t.length;
  const x = new Array(2 * n);
  for (let i = 0; i < n; i++) { x[2 * i] = t[i]; x[2 * i + 1] = t[i] + half; }
  const ys = keys.map((k) => {
    const y = new Array(2 * n).fill(null), s = series[k];
    if (s) for (let i = 0; i < n; i++) { y[2 * i] = scaled(k, s.min[i]); y[2 * i + 1] = scaled(k, s.max[i]); }
    return y;
  });
  return [x, ...ys];
}
// Y tick labels that fit the axis: 12000 -> "12k", 0.00314 -> "0.00314" (uPlot's own precision otherwise).
export function compactTicks(u, splits) {
  const span = Math.max(...splits.map(Math.abs));
  if (span >= 1e4) return splits.map((v) => (v == null ? "" : +(v / 1e3).toPrecision(4) + "k"));
  return splits.map((v) => (v == null ? "" : String(+v.toPrecision(6))));
}
const scaled = (k, v) => (v == null ? null : SERIES[k]?.scale ? v * SERIES[k].scale : v);

let groupSerial = 0;

// Stacked time charts with one cursor and one x zoom. Drag to zoom (every chart follows), double-click to
// go back; onZoom(true|false) tells the page (a live page stops following the newest data while zoomed).
export class ChartGroup {
  constructor(container, panels = PANELS, { height = 210, onZoom } = {}) {
    this.panels = panels;
    this.onZoom = onZoom;
    this.zoom = null;  // [min, max] while the user has zoomed
    this.window = null;  // [min, max] the page asks for (null = the data's extent)
    this.points = 0;
    this.lastTime = null;
    const key = "cb" + ++groupSerial;
    this.root = h("div.grid2");
    container.append(this.root);
    this.plots = panels.map((p) => {
      const el = h("div.card.chart");
      this.root.append(el);
      const opts = {
        title: `${p.title} (${p.unit})`,
        width: Math.max(300, el.clientWidth - 32),
        height,
        cursor: {
          sync: { key },
          drag: { x: true, y: false, setScale: false },
          bind: { dblclick: () => () => { this.resetZoom(); return null; } },
        },
        scales: { x: { time: false } },
        legend: { live: true },
        series: [
          { label: "test time", value: (u, v) => hms(v, true) },
          ...p.keys.map((k) => ({
            label: SERIES[k].label,
            stroke: SERIES[k].color,
            width: 1.5,
            spanGaps: true,
            points: { show: false },
            value: (u, v) => (v == null ? "–" : v.toFixed(SERIES[k].digits) + " " + SERIES[k].unit),
          })),
        ],
        axes: [
          { label: "Test time (h:mm:ss)", labelSize: 18, values: (u, splits) => splits.map((v) => hms(v)), grid: { stroke: "#eef1f5" }, ticks: { stroke: "#e3e7ee" } },
          { label: `${p.title.split(/[:,]/)[0]} / ${p.unit}`, labelSize: 18, size: 64, values: compactTicks, grid: { stroke: "#eef1f5" }, ticks: { stroke: "#e3e7ee" } },
        ],
        hooks: {
          setSelect: [(u) => {
            if (u.select.width < 4) return;
            const lo = u.posToVal(u.select.left, "x"), hi = u.posToVal(u.select.left + u.select.width, "x");
            u.setSelect({ left: 0, top: 0, width: 0, height: 0 }, false);
            this.setZoom([lo, hi]);
          }],
        },
      };
      const plot = new uPlot(opts, [[], ...p.keys.map(() => [])], el);
      return { el, plot, keys: p.keys };
    });
    this.resize = new ResizeObserver(() => {
      for (const { el, plot } of this.plots) {
        const w = Math.max(300, el.clientWidth - 32);
        if (Math.abs(plot.width - w) > 2) plot.setSize({ width: w, height });
      }
    });
    this.plots.forEach(({ el }) => this.resize.observe(el));
  }

  // New data for every chart (a samples response), keeping the zoom if any.
  setData(resp) {
    for (const p of this.plots) p.plot.setData(toColumns(resp, p.keys), true);
    const t = resp.time_s || [];
    this.points = resp.decimated ? 2 * t.length : t.length;
    this.lastTime = t.length ? t[t.length - 1] : null;
    this.applyX();
  }

  // The x range to show when not zoomed (e.g. the last 10 minutes, fixed even while data is still coming).
  setWindow(range) { this.window = range; this.applyX(); }

  setZoom(range) {
    this.zoom = range;
    this.applyX();
    this.onZoom?.(true);
  }
  resetZoom() {
    this.zoom = null;
    this.applyX();
    this.onZoom?.(false);
  }
  applyX() {
    const r = this.zoom || this.window;
    for (const { plot } of this.plots) {
      const xs = plot.data[0];
      if (r && r[1] > r[0]) plot.setScale("x", { min: r[0], max: r[1] });
      else if (xs && xs.length > 1) plot.setScale("x", { min: xs[0], max: xs[xs.length - 1] });
    }
  }

  destroy() {
    this.resize.disconnect();
    this.plots.forEach(({ plot }) => plot.destroy());
    this.root.remove();
  }
}

// The flags of one fitted value of a direction of GET /runs/{id}/fits ([] when it is fine).
export function fitFlags(direction, key) {
  const f = direction?.flags?.[key];
  return Array.isArray(f) ? f : [];
}

// GET /runs/{id}/fits as six small plots against SOC: R0, R1, C1, R2, C2 (discharge and charge) and OCV.
export const FIT_PARAMS = [
  { key: "r0_ohm", title: "R0", unit: "mΩ", scale: 1e3, digits: 3 },
  { key: "r1_ohm", title: "R1", unit: "mΩ", scale: 1e3, digits: 3 },
  { key: "c1_f", title: "C1", unit: "F", scale: 1, digits: 0 },
  { key: "r2_ohm", title: "R2", unit: "mΩ", scale: 1e3, digits: 3 },
  { key: "c2_f", title: "C2", unit: "F", scale: 1, digits: 0 },
  { key: "ocv_v", title: "OCV", unit: "V", scale: 1, digits: 4 },
];

export class FitCharts {
  constructor(container) {
    this.root = h("div.fitcharts");
    container.append(this.root);
    this.plots = FIT_PARAMS.map((p) => {
      const el = h("div.chart");
      this.root.append(el);
      const isOcv = p.key === "ocv_v";
      // A value the fit flagged (implausible, uncertain, at a bound: GET /runs/{id}/fits "flags") is never drawn on
      // the curve of the values that are fine: it goes to its own series, hollow markers and no line.
      const series = isOcv
        ? [{ label: "OCV", stroke: "#0e9384" }]
        : [{ label: "discharge", stroke: "#d92d20" }, { label: "charge", stroke: "#1f6feb" },
           { label: "discharge, flagged", stroke: "#d92d20", flagged: true },
           { label: "charge, flagged", stroke: "#1f6feb", flagged: true }];
      const plot = new uPlot({
        title: `${p.title} (${p.unit}) vs SOC`,
        width: 300, height: 170,
        // SOC is always 0..100 %; a single pulse set must not stretch the axis to 200 %.
        scales: { x: { time: false, range: [0, 100] },
                  y: { range: (u, lo, hi) => (lo == null ? [0, 1] : uPlot.rangeNum(lo, hi, 0.1, true)) } },
        cursor: { drag: { x: false, y: false } },
        series: [
          { label: "SOC", value: (u, v) => (v == null ? "–" : v.toFixed(1) + " %") },
          ...series.map((s) => ({ label: s.label, stroke: s.stroke, width: 1.5, spanGaps: !s.flagged,
                                 ...(s.flagged ? { paths: () => null, dash: [4, 3] } : {}),
                                 points: { show: true, size: s.flagged ? 9 : 6, fill: s.flagged ? "#ffffff" : s.stroke, stroke: s.stroke, width: s.flagged ? 2 : 1 },
                                 value: (u, v) => (v == null ? "–" : v.toFixed(p.digits) + (s.flagged ? " ?" : "")) })),
        ],
        axes: [
          { label: "SOC / %", labelSize: 18, values: (u, splits) => splits.map((v) => v + " %"), grid: { stroke: "#eef1f5" } },
          { label: `${p.title} / ${p.unit}`, labelSize: 18, size: 60, values: compactTicks, grid: { stroke: "#eef1f5" } },
        ],
      }, [[], ...series.map(() => [])], el);
      return { el, plot, p, isOcv };
    });
    this.resize = new ResizeObserver(() => {
      for (const { el, plot } of this.plots) {
        const w = Math.max(240, el.clientWidth);
        if (Math.abs(plot.width - w) > 2) plot.setSize({ width: w, height: 170 });
      }
    });
    this.plots.forEach(({ el }) => this.resize.observe(el));
  }

  setFits(fits) {
    const sorted = [...fits].filter((f) => f.soc != null).sort((a, b) => a.soc - b.soc);
    const x = sorted.map((f) => +(f.soc * 100).toFixed(2));
    for (const { plot, p, isOcv } of this.plots) {
      const val = (v) => (v == null || !Number.isFinite(v) ? null : v * p.scale);
      const fine = (d) => (d ? val(fitFlags(d, p.key).length ? null : d[p.key]) : null);
      const flagged = (d) => (d && fitFlags(d, p.key).length ? val(d[p.key]) : null);
      const cols = isOcv
        ? [x, sorted.map((f) => val(f.ocv_v))]
        : [x, sorted.map((f) => fine(f.discharge)), sorted.map((f) => fine(f.charge)),
           sorted.map((f) => flagged(f.discharge)), sorted.map((f) => flagged(f.charge))];
      plot.setData(cols);
    }
  }

  destroy() {
    this.resize.disconnect();
    this.plots.forEach(({ plot }) => plot.destroy());
    this.root.remove();
  }
}

// Time charts of given series on one x (test time), sharing cursor and drag-to-zoom (double-click returns):
// the Diagnosis page's traces. panels: [{title, unit, digits, series: [{label, color, data, dash?}]}].
export class TraceCharts {
  constructor(container, time, panels, { height = 220 } = {}) {
    const key = "tr" + ++groupSerial;
    this.root = h("div.grid2");
    container.append(this.root);
    this.plots = panels.map((p) => {
      const el = h("div.card.chart");
      this.root.append(el);
      const plot = new uPlot({
        title: `${p.title} (${p.unit})`,
        width: Math.max(300, el.clientWidth - 32),
        height,
        cursor: { sync: { key }, drag: { x: true, y: false, setScale: false } },
        scales: { x: { time: false } },
        legend: { live: true },
        series: [
          { label: "test time", value: (u, v) => hms(v, true) },
          ...p.series.map((s) => ({
            label: s.label, stroke: s.color, width: s.width ?? 1.25, dash: s.dash, spanGaps: true, points: { show: false },
            value: (u, v) => (v == null ? "–" : v.toFixed(p.digits ?? 4) + " " + p.unit),
          })),
        ],
        axes: [
          { label: "Test time (h:mm:ss)", labelSize: 18, values: (u, splits) => splits.map((v) => hms(v)), grid: { stroke: "#eef1f5" }, ticks: { stroke: "#e3e7ee" } },
          { label: `${p.title.split(/[:,]/)[0]} / ${p.unit}`, labelSize: 18, size: 64, values: compactTicks, grid: { stroke: "#eef1f5" }, ticks: { stroke: "#e3e7ee" } },
        ],
        hooks: { setSelect: [(u) => {
          if (u.select.width < 4) return;
          const lo = u.posToVal(u.select.left, "x"), hi = u.posToVal(u.select.left + u.select.width, "x");
          u.setSelect({ left: 0, top: 0, width: 0, height: 0 }, false);
          this.plots.forEach(({ plot }) => plot.setScale("x", { min: lo, max: hi }));
        }] },
      }, [time, ...p.series.map((s) => s.data)], el);
      el.addEventListener("dblclick", () => this.plots.forEach(({ plot }) =>
        plot.setScale("x", { min: time[0], max: time[time.length - 1] })));
      return { el, plot };
    });
    this.resize = new ResizeObserver(() => {
      for (const { el, plot } of this.plots) {
        const w = Math.max(300, el.clientWidth - 32);
        if (Math.abs(plot.width - w) > 2) plot.setSize({ width: w, height });
      }
    });
    this.plots.forEach(({ el }) => this.resize.observe(el));
  }

  destroy() {
    this.resize.disconnect();
    this.plots.forEach(({ plot }) => plot.destroy());
    this.root.remove();
  }
}
