// Pieces shared by the pages: fits table, events table, instrument list, live value tiles, run header.
import { SERIES } from "./charts.js";
import { dateTime, fmt, h, hms, pill } from "./util.js";

// One row per completed HPPC pulse set (GET /runs/{id}/fits).
export function fitsTable(fits) {
  const side = (d, key, scale, digits) => h("td.num", null, d ? fmt(d[key], digits, scale) : "–");
  const params = (d) => [
    side(d, "r0_ohm", 1e3, 3), side(d, "r1_ohm", 1e3, 3), side(d, "c1_f", 1, 0), side(d, "r2_ohm", 1e3, 3), side(d, "c2_f", 1, 0),
  ];
  const heads = ["R0 mΩ", "R1 mΩ", "C1 F", "R2 mΩ", "C2 F"];
  return h("div.scroll", null, h("table.fits", { id: "fits-table" },
    h("thead", null,
      h("tr", null, h("th", { colspan: 4 }), h("th", { colspan: 5 }, "discharge"), h("th", { colspan: 5 }, "charge")),
      h("tr", null, h("th.num", null, "set"), h("th.num", null, "test time"), h("th.num", null, "SOC %"), h("th.num", null, "OCV V"),
        heads.map((t) => h("th.num", null, t)), heads.map((t) => h("th.num", null, t)))),
    h("tbody", null, fits.map((f) => h("tr", null,
      h("td.num", null, f.pulse_set), h("td.num", null, hms(f.test_time_s)), h("td.num", null, fmt(f.soc, 1, 100)),
      h("td.num", null, fmt(f.ocv_v, 4)), params(f.discharge), params(f.charge))))));
}

export function eventsTable(events, { limit = 500, newestFirst = true } = {}) {
  const list = newestFirst ? [...events].reverse() : events;
  return h("div.scroll", null, h("table.events", null,
    h("thead", null, h("tr", null, ["test time", "time", "level", "kind", "step", "message"].map((t) => h("th", null, t)))),
    h("tbody", null, list.slice(0, limit).map((e) => h("tr", null,
      h("td.num", null, hms(e.test_time_s)), h("td.num.muted", null, dateTime(e.time_unix_s)),
      h("td.level-" + e.level, null, e.level), h("td", null, e.kind), h("td.num", null, e.step ?? ""),
      h("td", null, e.message))))));
}

export function instrumentList(instruments) {
  if (!instruments?.length) return h("div.empty", null, "no instruments configured");
  return h("ul", null, instruments.map((i) => h("li", null,
    h("span.name", null, i.name), h("span.muted.small", null, i.kind), pill(i.state),
    h("span.detail", null, i.address, i.detail ? h("div", null, i.detail) : null))));
}

const TILE_KEYS = ["voltage_v", "current_a", "soc", "surface_c", "t1_c", "t2_c", "heat_flux_w_per_m2", "ambient_c"];

export function liveTiles(live) {
  live = live || {};
  return h("div.tiles", null, TILE_KEYS.map((k) => {
    const s = SERIES[k];
    const v = live[k];
    return h("div.tile", { "data-key": k },
      h("div.k", null, h("i", { style: `background:${s.color}` }), s.label),
      h("div.v", null, fmt(v, s.digits, s.scale || 1), h("small", null, s.unit)));
  }));
}

// Program position: step index/count, kind, time in step; a bar for how far through the program.
export function stepBlock(run) {
  const st = run?.step;
  if (!st) return h("div.muted.small", { style: "margin-top:10px" }, run ? "no step running" : "");
  return h("div", null,
    h("dl.step", null,
      h("dt", null, "step"), h("dd", { id: "step-index" }, `${st.index} of ${st.count}`),
      h("dt", null, "kind"), h("dd", null, st.type || "–"),
      h("dt", null, "in step"), h("dd", null, hms(st.elapsed_s))),
    h("div.progress", { title: "program position (steps)" }, h("div", { style: `width:${Math.min(100, (100 * st.index) / Math.max(1, st.count)).toFixed(1)}%` })));
}
