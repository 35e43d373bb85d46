// Runs list, run page and diagnosis page.
import { ChartGroup, FitCharts } from "./charts.js";
import { eventsTable, fitsTable, stepBlock } from "./parts.js";
import { API, dateTime, duration, esc, fmt, get, h, hms, isActive, pill, poller } from "./util.js";

export function runsView(app) {
  const box = h("div.card", null, h("h2", null, "Runs"), h("div.empty", null, "loading…"));
  app.append(box);
  const p = poller(async () => {
    const runs = (await get("/runs")).runs || [];
    box.lastChild.replaceWith(runs.length ? h("table", { id: "runs-table" },
      h("thead", null, h("tr", null, ["run", "program", "cell", "state"].map((t) => h("th", null, t)),
        ["created", "duration", "samples"].map((t) => h("th.num", null, t)), h("th", null, "step"), h("th"))),
      h("tbody", null, runs.map((r) => h("tr", null,
        h("td", null, h("a", { href: `#/runs/${r.id}` }, `#${r.id}`)), h("td", null, r.program), h("td", null, r.cell),
        h("td", null, pill(r.state)), h("td.num", null, dateTime(r.created_unix_s)), h("td.num", null, hms(duration(r))),
        h("td.num", null, r.samples ?? "–"), h("td", null, r.step ? `${r.step.index}/${r.step.count} ${r.step.type}` : ""),
        h("td", null, h("a", { href: `${API}/runs/${r.id}/export.bdf.csv` }, "BDF CSV"))))))
      : h("div.empty", null, "no runs recorded yet"));
  }, 3000);
  return () => p.stop();
}

export function runView(app, id) {
  const head = h("div.card", { style: "margin-bottom:16px" }, h("div.empty", null, "loading…"));
  const chartsBox = h("div");
  const fitsCard = h("div.card", { style: "margin-bottom:16px" }, h("h2", null, "Online fits by pulse set"), h("div"), h("div", { style: "margin-top:14px" }));
  const stepsCard = h("div.card", null, h("h2", null, "Steps the tester ran"), h("div"));
  const eventsCard = h("div.card", null, h("h2", null, "Events"), h("div"));
  app.append(head, chartsBox, fitsCard, h("div.grid2", null, stepsCard, eventsCard));
  const charts = new ChartGroup(chartsBox, undefined, { height: 190 });
  const fitCharts = new FitCharts(fitsCard.lastChild);
  let active = true, sig = "";

  const p = poller(async () => {
    if (!active) return;
    const [run, ev, fits, st] = await Promise.all([get(`/runs/${id}`), get(`/runs/${id}/events`), get(`/runs/${id}/fits`),
                                                   get(`/runs/${id}/steps`)]);
    head.replaceChildren(...[
      h("div.runhead", null, h("h1", null, `Run ${run.id}`), pill(run.state),
        h("span.meta", null, `${run.program} · cell ${run.cell} · created ${dateTime(run.created_unix_s)} · ${run.samples ?? 0} samples`,
          duration(run) != null ? ` · ${hms(duration(run))} wall` : ""),
        h("span", { style: "margin-left:auto;display:flex;gap:8px" },
          h("a.btn.primary", { href: `${API}/runs/${run.id}/export.bdf.csv`, download: `run-${run.id}.bdf.csv` }, "Export BDF CSV"),
          h("a.btn", { href: `#/diagnosis/${run.id}` }, "Diagnose…"))),
      isActive(run) ? stepBlock(run) : null,
      run.error ? h("div.note.warn", { style: "margin:10px 0 0" }, run.error) : null].filter(Boolean));
    // Charts and tables only change while the run records; a finished run is fetched once.
    const s = `${run.samples}|${(ev.events || []).length}|${(fits.fits || []).length}|${(st.steps || []).length}`;
    if (s !== sig) {
      sig = s;
      const resp = await get(`/runs/${id}/samples?max_points=3000`);
      charts.setData(resp);
      const list = fits.fits || [];
      fitsCard.children[1].replaceWith(list.length ? fitsTable(list) : h("div.empty", null, "no completed pulse set in this run"));
      fitCharts.root.style.display = list.length ? "" : "none";
      fitCharts.setFits(list);
      const events = ev.events || [];
      // GET /runs/{id}/steps: every step with its times, charge moved and why it ended.
      const steps = st.steps || [];
      stepsCard.lastChild.replaceWith(steps.length
        ? h("div.scroll", null, h("table", null,
            h("thead", null, h("tr", null, ["#", "step", "cycle", "type", "start", "duration", "Ah", "ended by"].map((t) => h("th", null, t)))),
            h("tbody", null, steps.map((x) => h("tr", null, h("td.num", null, x.index), h("td.num", null, x.step_id),
              h("td.num", null, x.cycle), h("td", null, x.type), h("td.num", null, hms(x.started_s)),
              h("td.num", null, x.ended_s != null ? hms(x.ended_s - x.started_s) : "…"),
              h("td.num", null, fmt(x.capacity_ah, 4)), h("td", null, x.end_reason || ""))))))
        : h("div.empty", null, "no steps recorded"));
      eventsCard.lastChild.replaceWith(events.length ? eventsTable(events) : h("div.empty", null, "no events"));
    }
    active = isActive(run);
  }, 2000);
  return () => { p.stop(); charts.destroy(); fitCharts.destroy(); };
}

// Diagnosis: `cellbench diagnose` runs offline (seconds to minutes of CPU; it is not a request the daemon's
// I/O threads should serve). The page shows what it writes: the HTML report (--report) in a sandboxed frame,
// or the diagnosis JSON (--json) rendered here. Files are read by the browser, nothing is uploaded.
export function diagnosisView(app, runId) {
  const cmdBox = h("div");
  const input = h("input", { type: "file", accept: ".html,.htm,.json", multiple: true, style: "display:none" });
  const drop = h("div.drop", null, h("div", null, h("b", null, "Drop a diagnose report here"), " (", h("code", null, "--report R.html"), " or ",
    h("code", null, "--json D.json"), ") or "), h("button.btn", { onclick: () => input.click() }, "choose files…"), input);
  const out = h("div", { style: "margin-top:16px" });
  app.append(h("div.card", { style: "margin-bottom:16px" }, h("h2", null, "Diagnose a run or a recording"),
    h("p.muted", { style: "margin-top:0" }, "cellbench diagnose compares a recording with what the parameter set predicts and names the physics the model leaves out. ",
      "It runs offline with the command line tool; this page shows its report. The files stay in your browser."), cmdBox), drop, out);

  get("/runs").then(({ runs }) => {
    const sel = h("select", { id: "diag-run" }, (runs || []).map((r) => h("option", { value: r.id, selected: String(r.id) === String(runId) || null }, `run ${r.id} · ${r.program} · ${r.cell} · ${r.state}`)));
    const cmd = h("pre", { style: "margin:8px 0 0;white-space:pre-wrap" });
    const update = () => {
      const r = (runs || []).find((x) => String(x.id) === sel.value);
      if (!r) { cmd.textContent = "no runs recorded yet"; return; }
      const base = location.origin;
      cmd.innerHTML = esc(`curl -o run-${r.id}.bdf.csv ${base}${API}/runs/${r.id}/export.bdf.csv\n` +
        `cellbench diagnose --params config/cells/${r.cell}.json run-${r.id}.bdf.csv --json run-${r.id}.diagnosis.json --report run-${r.id}.report.html`);
    };
    sel.addEventListener("change", update);
    cmdBox.append(h("div", null, h("span.small.muted", null, "for a run: "), sel, " ", h("a.small", { href: "#", onclick: (e) => { e.preventDefault(); location.href = `${API}/runs/${sel.value}/export.bdf.csv`; } }, "download its BDF CSV")), h("div.code", null, cmd));
    update();
  }).catch(() => {});

  const show = async (files) => {
    out.replaceChildren();
    for (const f of files) {
      const text = await f.text();
      if (/\.json$/i.test(f.name) || text.trimStart().startsWith("{")) out.append(renderDiagnosis(f.name, text));
      else out.append(h("div.card", { style: "margin-bottom:16px" }, h("h2", null, f.name),
        h("iframe.report", { sandbox: "", srcdoc: text, title: "diagnose report" })));
    }
  };
  input.addEventListener("change", () => show([...input.files]));
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", (e) => { e.preventDefault(); drop.classList.remove("over"); show([...e.dataTransfer.files]); });
  return () => {};
}

function renderDiagnosis(name, text) {
  let d;
  try { d = JSON.parse(text); } catch (e) { return h("div.note.warn", null, `${name}: not JSON (${e.message})`); }
  if (d.schema !== "cellbench.diagnosis/1") return h("div.note.warn", null, `${name}: expected "schema": "cellbench.diagnosis/1", got ${JSON.stringify(d.schema)}`);
  const b = d.baseline || {};
  const metrics = (m) => `V ${fmt(m?.voltage_rms_v, 1, 1e3)} mV · T ${fmt(m?.temperature_rms_c, 2)} °C · heat flux ${fmt(m?.heat_flux_rms_w, 3)} W`;
  const maxShare = Math.max(1e-9, ...(d.where || []).map((w) => w.share_of_voltage_error || 0));
  return h("div.card", null, h("h2", null, `${name}: diagnosis`),
    h("p", null, h("b", null, "Baseline RMS error: "), metrics(b)),
    h("h2", null, "Where the voltage error sits"),
    (d.where || []).length ? h("table", null, h("tbody", null, d.where.map((w) => h("tr", null, h("td", null, w.condition),
      h("td.num", null, fmt(w.share_of_voltage_error, 1, 100) + " %"),
      h("td", { style: "width:40%" }, h("div.bar", { style: `width:${(100 * (w.share_of_voltage_error || 0)) / maxShare}%` }))))))
      : h("div.empty", null, "no condition stands out"),
    h("h2", { style: "margin-top:16px" }, "Findings (strongest first)"),
    (d.findings || []).map((f) => h("div.finding" + (f.significant ? ".sig" : ""), null,
      h("h3", null, f.effect, " ", pill(f.significant ? "significant" : "not significant", f.significant ? "ok" : ""), h("span.muted.small", null, ` score ${fmt(f.score, 2)}`)),
      h("div", null, f.explanation),
      f.improved ? h("div.small.muted", { style: "margin-top:4px" }, "with it: ", metrics(f.improved)) : null)));
}
