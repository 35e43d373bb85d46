// Pieces shared by the pages: fits table, events table, instrument list, live value tiles, run header.
import { SERIES, fitFlags } from "./charts.js";
import { dateTime, fmt, h, hms, pill, stepWords } from "./util.js";

// One row per completed HPPC pulse set (GET /runs/{id}/fits).
export function fitsTable(fits) {
  // A flagged value is marked and says why (hover), never shown as fine.
  const side = (d, key, scale, digits) => {
    if (!d) return h("td.num", null, "–");
    const flags = fitFlags(d, key);
    const sd = d[key + "_sd"];
    const title = [sd != null ? `± ${fmt(sd, digits, scale)} (1σ)` : "", flags.join(", ")].filter(Boolean).join("; ");
    return flags.length
      ? h("td.num.flagged", { title }, fmt(d[key], digits, scale) + " ?")
      : h("td.num", title ? { title } : null, fmt(d[key], digits, scale));
  };
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

// One sample of a Prometheus text exposition: value of `family{labels...}` whose labels include `want`.
export function metricValue(text, family, want = {}) {
  for (const line of (text || "").split("\n")) {
    if (!line.startsWith(family)) continue;
    const m = line.match(/^([a-z_:]+)(\{([^}]*)\})?\s+(\S+)$/i);
    if (!m || m[1] !== family) continue;
    const labels = Object.fromEntries([...(m[3] || "").matchAll(/(\w+)="([^"]*)"/g)].map((x) => [x[1], x[2]]));
    if (Object.entries(want).every(([k, v]) => labels[k] === v)) return Number(m[4]);
  }
  return null;
}

const SOURCE = { neware: "cycler", dewe: "daq", chamber: "chamber" };

// Instrument health: state, how old the newest reading is, samples per second (during a run), faults,
// reconnects and lost frames since cellbenchd started (from /metrics), and the chamber's set point against
// the air it measures.
export function instrumentList(instruments, live = {}, metrics = "") {
  if (!instruments?.length) return h("div.empty", null, "no instruments configured");
  const age = live?.time_unix_s != null ? Math.max(0, Date.now() / 1000 - live.time_unix_s) : null;
  const num = (v, d = 0) => (v == null ? "–" : fmt(v, d));
  return h("div.scroll", null, h("table.health", { id: "instrument-health" },
    h("thead", null, h("tr", null, ["instrument", "state", "data age", "samples/s", "faults", "reconnects", "lost frames", ""].map((t, i) =>
      h(i >= 2 && i <= 6 ? "th.num" : "th", null, t)))),
    h("tbody", null, instruments.map((i) => {
      const m = (f) => metricValue(metrics, f, { instrument: i.name });
      const rate = metricValue(metrics, "cellbench_samples_ingested_per_second", { source: SOURCE[i.name] || i.kind });
      let extra = i.detail || "";
      if (i.kind === "chamber" && live?.setpoint_c != null)
        extra = `set point ${fmt(live.setpoint_c, 1)} °C, air ${fmt(live.ambient_c, 2)} °C` + (extra ? ` · ${extra}` : "");
      if (i.kind === "cycler" && live?.voltage_v != null)
        extra = `${fmt(live.voltage_v, 4)} V, ${fmt(live.current_a, 3)} A` + (extra ? ` · ${extra}` : "");
      // The tester channels wired in parallel as the cycler: each member's own voltage and current, so a
      // loose sense lead or a channel not sharing the current shows before the group check trips.
      const members = (i.members || []).length > 1
        ? h("div.members.small", { id: "group-members" }, i.members.map((mb) =>
          h("div", { "data-member": mb.channel }, `${mb.channel}: ${fmt(mb.voltage_v, 4)} V, ${fmt(mb.current_a, 3)} A · ${mb.status}`)))
        : null;
      return h("tr", { "data-instrument": i.name },
        h("td", null, h("b", null, i.name), h("div.small.muted", null, `${i.kind} · ${i.mode || ""} · ${i.address || ""}`)),
        h("td", null, pill(i.state)),
        h("td.num", null, i.data_age_s != null ? `${fmt(i.data_age_s, 1)} s` : i.kind === "cycler" && age != null ? `${fmt(age, 1)} s` : "–"),
        h("td.num", null, rate != null ? fmt(rate, 1) : "–"),
        h("td.num", { "data-metric": "faults" }, num(m("cellbench_instrument_faults_total"))),
        h("td.num", null, num(m("cellbench_instrument_reconnects_total"))),
        h("td.num", { "data-metric": "lost" }, num(m("cellbench_instrument_lost_frames_total"))),
        h("td.detail", null, extra, members));
    }))));
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

// Program position: step index/count, kind, time in step; a bar for how far through the program: by expected
// time (GET /status "progress": test time over the program's estimated duration) when given, else by steps.
export function stepBlock(run, progress = null) {
  const st = run?.step;
  if (!st) return h("div.muted.small", { style: "margin-top:10px" }, run ? "no step running" : "");
  return h("div", null,
    h("dl.step", null,
      h("dt", null, "step"), h("dd", { id: "step-index" }, `${st.index} of ${st.count}`),
      h("dt", null, "kind"), h("dd", { id: "step-kind" }, stepWords(st.type)),
      h("dt", null, "in step"), h("dd", null, hms(st.elapsed_s))),
    progress?.fraction != null
      ? h("div.progress", { id: "run-progress", title: `about ${Math.round(100 * progress.fraction)} % of the expected ${hms(progress.expected_duration_s)} (estimate)` },
        h("div", { style: `width:${(100 * progress.fraction).toFixed(1)}%` }))
      : h("div.progress", { title: "program position (steps)" }, h("div", { style: `width:${Math.min(100, (100 * st.index) / Math.max(1, st.count)).toFixed(1)}%` })));
}
