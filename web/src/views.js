// Runs list, run page and diagnosis page.
import { ChartGroup, FitCharts, TraceCharts } from "./charts.js";
import { eventsTable, fitsTable, stepBlock } from "./parts.js";
import { API, apiToken, dateTime, duration, fmt, get, h, hms, isActive, pill, post, poller, stepWords } from "./util.js";

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
        h("td.num", null, r.samples ?? "–"), h("td", null, r.step ? `${r.step.index}/${r.step.count} ${stepWords(r.step.type)}` : ""),
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
    // Progress by expected time (GET /status), as on the live page, while this run is the active one.
    let progress = null;
    if (isActive(run)) {
      const status = await get("/status").catch(() => null);
      if (status?.run?.id === run.id) progress = status.progress;
    }
    head.replaceChildren(...[
      h("div.runhead", null, h("h1", null, `Run ${run.id}`), pill(run.state),
        h("span.meta", null, `${run.program} · cell ${run.cell} · created ${dateTime(run.created_unix_s)} · ${run.samples ?? 0} samples`,
          duration(run) != null ? ` · ${hms(duration(run))} wall` : ""),
        h("span", { style: "margin-left:auto;display:flex;gap:8px" },
          h("a.btn.primary", { href: `${API}/runs/${run.id}/export.bdf.csv`, download: `run-${run.id}.bdf.csv` }, "Export BDF CSV"),
          h("a.btn", { href: `#/diagnosis/${run.id}` }, "Diagnose…"))),
      isActive(run) ? stepBlock(run, progress) : null,
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
              h("td.num", null, x.cycle), h("td", null, stepWords(x.type)), h("td.num", null, hms(x.started_s)),
              h("td.num", null, x.ended_s != null ? hms(x.ended_s - x.started_s) : "…"),
              h("td.num", null, fmt(x.capacity_ah, 4)), h("td", null, x.end_reason || ""))))))
        : h("div.empty", null, "no steps recorded"));
      eventsCard.lastChild.replaceWith(events.length ? eventsTable(events) : h("div.empty", null, "no events"));
    }
    active = isActive(run);
  }, 2000);
  return () => { p.stop(); charts.destroy(); fitCharts.destroy(); };
}

// Diagnosis: the daemon diagnoses a finished run (POST /runs/{id}/diagnose) or an uploaded BDF CSV recording
// (POST /diagnose) on its own worker thread; the page polls the job (GET /diagnoses/{job}) with a progress bar
// and shows the findings, where the error sits and the traces (measured against simulated). Reports written
// by `cellbench diagnose --report/--json` can still be dropped here and are shown without uploading them.
export function diagnosisView(app, runId) {
  let runs = [], cells = { cells: [], parameter_sets: [] }, job = null, charts = null, stopped = false;
  const polls = [];

  const tokenInput = h("input", { type: "password", id: "diag-token", placeholder: "API token", autocomplete: "off", size: 16, value: apiToken.get() });
  tokenInput.addEventListener("change", () => apiToken.set(tokenInput.value.trim()));
  const runSel = h("select", { id: "diag-run" });
  const paramsSel = h("select", { id: "diag-params" });
  // Other finished runs of the cell every finding must not make worse (confirm_runs; none selected: not checked).
  const confirmSel = h("select", { id: "diag-confirm", multiple: true, size: 3, title: "Ctrl/Cmd-click to choose several" });
  const runBtn = h("button.btn.primary", { id: "diag-start", onclick: () => start("run") }, "Diagnose run");
  const fileInput = h("input", { type: "file", id: "diag-file", accept: ".csv,text/csv" });
  const upParamsSel = h("select", { id: "diag-upload-params" });
  const upBtn = h("button.btn", { id: "diag-upload", onclick: () => start("upload") }, "Upload and diagnose");
  const msg = h("div");
  const jobBox = h("div", { id: "diag-job" });
  const resultBox = h("div", { id: "diag-result" });
  const recentBox = h("div", { id: "diag-recent" });

  const field = (label, ...el) => h("label.field", null, h("span.small.muted", null, label), ...el);
  app.append(
    h("div.card", { style: "margin-bottom:16px" },
      h("h2", null, "Diagnose a run or a recording"),
      h("p.muted", { style: "margin-top:0" },
        "The daemon simulates the recording with a parameter set, shows where the simulation misses it and names the physics ",
        "the model leaves out (cellbench diagnose). It runs in the background, one job at a time; a diagnosis takes seconds to minutes."),
      h("div.toolbar", null, field("run", runSel), field("parameter set", paramsSel),
        field("confirm on other runs (optional)", confirmSel), runBtn),
      h("div.toolbar", null, field("or a recording (BDF CSV)", fileInput), field("parameter set", upParamsSel), upBtn),
      h("div.toolbar", { style: "margin-bottom:0" }, field("API token (for starting jobs; kept in this browser)", tokenInput)),
      msg, jobBox),
    resultBox,
    h("div.card", { style: "margin-bottom:16px" }, h("h2", null, "Recent diagnoses"), recentBox));

  const note = (text, cls = "warn") => msg.replaceChildren(text ? h("div.note." + cls, { style: "margin:10px 0 0" }, text) : "");

  function paramOptions(sel, withRun, preferred) {
    const keep = sel.value;
    const opts = (cells.parameter_sets || []).map((p) => h("option", { value: p.name }, p.cell ? `${p.name} · ${p.cell}` : p.name));
    if (withRun) opts.push(h("option", { value: "run" }, "the run's own fitted parameter set"));
    sel.replaceChildren(...opts);
    const want = [keep, preferred].find((v) => v && [...sel.options].some((o) => o.value === v));
    if (want) sel.value = want;
  }
  // The parameter set of the run's cell (config/cells/CELL.json "params"), else the first one.
  const cellParams = (r) => (cells.cells || []).find((c) => c.name === r?.cell)?.params;

  function fillRuns() {
    runSel.replaceChildren(...(runs.length ? runs.map((r) => h("option", { value: r.id, disabled: isActive(r) || null },
      `run ${r.id} · ${r.program} · ${r.cell} · ${r.state}${isActive(r) ? " (still recording)" : ""}`))
      : [h("option", { value: "" }, "no runs recorded yet")]));
    const pick = runs.find((r) => String(r.id) === String(runId) && !isActive(r)) || runs.find((r) => !isActive(r));
    if (pick) runSel.value = String(pick.id);
    runBtn.disabled = !pick || null;
    fillConfirm();
  }
  // The finished runs other than the one diagnosed, those of its cell first.
  function fillConfirm() {
    const r = runs.find((x) => String(x.id) === runSel.value);
    const others = runs.filter((x) => !isActive(x) && String(x.id) !== runSel.value)
      .sort((a, b) => (b.cell === r?.cell) - (a.cell === r?.cell));
    confirmSel.replaceChildren(...others.map((x) => h("option", { value: x.id }, `run ${x.id} · ${x.program} · ${x.cell}`)));
    confirmSel.disabled = !others.length || null;
  }
  runSel.addEventListener("change", () => {
    fillConfirm();
    const r = runs.find((x) => String(x.id) === runSel.value);
    paramOptions(paramsSel, true, cellParams(r));
    if (cellParams(r)) paramsSel.value = cellParams(r);
  });

  async function start(kind) {
    note("");
    try {
      let j;
      if (kind === "run") {
        if (!runSel.value) return note("Choose a finished run.");
        const confirm = [...confirmSel.selectedOptions].map((o) => Number(o.value));
        j = await post(`/runs/${runSel.value}/diagnose`, confirm.length ? { params: paramsSel.value, confirm_runs: confirm }
                                                                          : { params: paramsSel.value });
      } else {
        const f = fileInput.files[0];
        if (!f) return note("Choose a BDF CSV recording first.");
        const q = new URLSearchParams({ params: upParamsSel.value, name: f.name });
        j = await post(`/diagnose?${q}`, f, "text/csv");
      }
      follow(j.id);
      refreshRecent();
    } catch (e) {
      if (e.status === 401) note(`${e.message} — enter the API token (cellbenchd --token / CELLBENCH_TOKEN) above.`);
      else note(e.message);
    }
  }

  // Polls one job until it has finished, then shows its report.
  function follow(id) {
    polls.splice(0).forEach((p) => p.stop());
    job = id;
    resultBox.replaceChildren();
    const p = poller(async () => {
      const j = await get(`/diagnoses/${id}`);
      if (stopped || job !== id) return;
      const pct = Math.round(100 * (j.progress || 0));
      jobBox.replaceChildren(h("div", { style: "margin-top:12px" },
        h("div.small", null, h("b", null, `Job ${j.id}`), ` · ${describe(j)} · `, pill(j.state), ` ${pct} % · ${j.stage || ""}`),
        h("div.progress", { title: `${pct} %` }, h("div", { style: `width:${pct}%` }))));
      if (j.state === "running") return;
      p.stop();
      if (j.state === "failed") jobBox.append(h("div.note.warn", { style: "margin:10px 0 0" }, `Diagnosis failed: ${j.error}`));
      else showResult(j);
      refreshRecent();
    }, 700);
    polls.push(p);
  }

  function showResult(j) {
    if (charts) { charts.destroy(); charts = null; }
    const d = j.diagnosis;
    const t = j.traces;
    const chartsBox = h("div");
    const file = (obj, name, label) => h("a.btn", { download: name,
      href: URL.createObjectURL(new Blob([JSON.stringify(obj, null, 2)], { type: "application/json" })) }, label);
    resultBox.replaceChildren(
      h("div.card", { style: "margin-bottom:16px" },
        h("div.runhead", null, h("h1", null, `Diagnosis ${j.id}`), h("span.meta", null,
          `${describe(j)} · parameter set ${j.params_used || j.params}${j.wall_s != null ? ` · ${j.wall_s.toFixed(1)} s` : ""}`),
          h("span", { style: "margin-left:auto;display:flex;gap:8px" }, file(d, `diagnosis-${j.id}.json`, "Diagnosis JSON"),
            j.improved_params ? file(j.improved_params, `improved-params-${j.id}.json`, "Improved parameter set") : null)),
        d.summary ? h("p.note", { style: "margin:12px 0 0" }, d.summary) : null,
        ...(d.notes || []).map((n) => h("p.note", { style: "margin:8px 0 0;color:#7a4b00" }, `Note: ${n}`)),
        rmsTable(d)),
      chartsBox,
      diagnosisCard(d, "Findings and where the error sits"));
    if (t && t.time_s?.length) {
      const panels = [];
      const v = t.voltage_v || {}, e = t.voltage_error_v || {}, s = t.surface_c;
      panels.push({ title: "Voltage", unit: "V", digits: 4, series: [
        { label: "measured", color: "#1b2430", data: v.measured },
        { label: "baseline model", color: "#d92d20", data: v.baseline },
        v.improved && { label: "improved model", color: "#1f6feb", data: v.improved }].filter(Boolean) });
      const mv = (a) => (a || []).map((x) => (x == null ? null : 1e3 * x));
      panels.push({ title: "Voltage error, simulated − measured", unit: "mV", digits: 2, series: [
        { label: "baseline model", color: "#d92d20", data: mv(e.baseline) },
        e.improved && { label: "improved model", color: "#1f6feb", data: mv(e.improved) }].filter(Boolean) });
      if (s) panels.push({ title: "Surface temperature", unit: "°C", digits: 2, series: [
        { label: "measured", color: "#1b2430", data: s.measured },
        { label: "baseline model", color: "#d92d20", data: s.baseline },
        s.improved && { label: "improved model", color: "#1f6feb", data: s.improved }].filter(Boolean) });
      chartsBox.append(h("div.small.muted", { style: "margin:0 0 6px" },
        `${t.points} of ${t.rows} rows plotted (each bucket keeps its extremes) · drag to zoom, double-click to return`));
      charts = new TraceCharts(chartsBox, t.time_s, panels);
    }
  }

  async function refreshRecent() {
    const list = (await get("/diagnoses")).diagnoses || [];
    recentBox.replaceChildren(list.length ? h("table", null,
      h("thead", null, h("tr", null, ["job", "what", "parameter set", "state", "created", ""].map((x) => h("th", null, x)))),
      h("tbody", null, list.map((j) => h("tr", null, h("td.num", null, j.id), h("td", null, describe(j)),
        h("td", null, j.params_used || j.params), h("td", null, pill(j.state), j.state === "running" ? ` ${Math.round(100 * j.progress)} %` : ""),
        h("td.num", null, dateTime(j.created_unix_s)),
        h("td", null, j.id === job ? h("span.muted.small", null, "shown") : h("a", { href: "#", onclick: (ev) => { ev.preventDefault(); follow(j.id); refreshRecent(); } }, "show"))))))
      : h("div.empty", null, "none since cellbenchd started (the last 8 are kept in memory)"));
    return list;
  }

  Promise.all([get("/runs"), get("/cells").catch(() => cells)]).then(async ([r, c]) => {
    if (stopped) return;
    runs = r.runs || [];
    cells = c || cells;
    fillRuns();
    const sel = runs.find((x) => String(x.id) === runSel.value);
    paramOptions(paramsSel, true, cellParams(sel));
    paramOptions(upParamsSel, false, cellParams(runs[0]));
    const list = await refreshRecent();
    // Show the running job, else the newest one (a page reload keeps its report).
    const shown = list.find((j) => j.state === "running") || list[0];
    if (shown && job == null) { follow(shown.id); refreshRecent(); }
  }).catch((e) => note(`cannot reach cellbenchd: ${e.message}`));

  // Secondary: reports of `cellbench diagnose` files, read by the browser (nothing is uploaded).
  const input = h("input", { type: "file", accept: ".html,.htm,.json", multiple: true, style: "display:none" });
  const drop = h("div.drop", null, h("div", null, h("b", null, "Drop a diagnose report here"), " (", h("code", null, "--report R.html"), " or ",
    h("code", null, "--json D.json"), ") or "), h("button.btn", { onclick: () => input.click() }, "choose files…"), input);
  const out = h("div", { style: "margin-top:16px" });
  app.append(h("details.card", { style: "margin-bottom:16px" },
    h("summary", null, h("b", null, "Reports from the command line"), h("span.muted.small", null, " — view a report of cellbench diagnose; the files stay in your browser")),
    h("pre.code", { style: "white-space:pre-wrap;margin:10px 0" },
      "curl -o run-ID.bdf.csv URL/api/v1/runs/ID/export.bdf.csv\ncellbench diagnose --params config/cells/p45b-thesis.json run-ID.bdf.csv --json d.json --report r.html"),
    drop, out));
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
  return () => { stopped = true; polls.forEach((p) => p.stop()); if (charts) charts.destroy(); };
}

function describe(j) {
  const s = j.source || {};
  if (s.kind === "run") return `run ${s.run_id} (${s.program}, ${s.cell})`;
  if (s.kind === "upload") return `${s.name || "uploaded recording"} (${fmt((s.bytes || 0) / 1e6, 1)} MB)`;
  return "?";
}

const metrics = (m) => `V ${fmt(m?.voltage_rms_v, 1, 1e3)} mV · T ${fmt(m?.temperature_rms_c, 2)} °C · heat flux ${fmt(m?.heat_flux_rms_w, 3)} W`;

function rmsTable(d) {
  const row = (label, m) => h("tr", null, h("td", null, label), h("td.num", null, fmt(m?.voltage_rms_v, 2, 1e3)),
    h("td.num", null, fmt(m?.temperature_rms_c, 3)), h("td.num", null, fmt(m?.heat_flux_rms_w, 3)));
  return h("table", { style: "margin-top:12px;max-width:760px" },
    h("thead", null, h("tr", null, h("th", null, "RMS error (simulated − measured)"), h("th.num", null, "voltage mV"),
      h("th.num", null, "surface °C"), h("th.num", null, "heat flux W"))),
    h("tbody", null, row("baseline (the parameter set)", d.baseline),
      row(`improved (${(d.accepted || []).join(" + ") || "nothing accepted"})`, d.improved)));
}

// The findings and the "where" table of a cellbench.diagnosis/1 report.
function diagnosisCard(d, title) {
  const maxShare = Math.max(1e-9, ...(d.where || []).map((w) => w.share_of_voltage_error || 0));
  return h("div.card", null, h("h2", null, title),
    h("p", null, h("b", null, "Baseline RMS error: "), metrics(d.baseline || {})),
    h("h2", null, "Where the voltage error sits (residuals by operating condition)"),
    (d.where || []).length ? h("table", { id: "diag-where" },
      h("thead", null, h("tr", null, h("th", null, "condition"), h("th.num", null, "share of squared error"), h("th.num", null, "share of time"),
        h("th.num", null, "RMS mV"), h("th.num", null, "bias mV"), h("th"))),
      h("tbody", null, d.where.map((w) => h("tr", null, h("td", null, w.condition),
        h("td.num", null, fmt(w.share_of_voltage_error, 1, 100) + " %"), h("td.num", null, fmt(w.time_share, 1, 100) + " %"),
        h("td.num", null, fmt(w.voltage_rms_v, 2, 1e3)), h("td.num", null, fmt(w.voltage_bias_v, 2, 1e3)),
        h("td", { style: "width:30%" }, h("div.bar", { style: `width:${(100 * (w.share_of_voltage_error || 0)) / maxShare}%` }))))))
      : h("div.empty", null, "no condition stands out"),
    h("h2", { style: "margin-top:16px" }, "Findings (strongest first)"),
    h("div", { id: "diag-findings" }, (d.findings || []).length ? d.findings.map((f) => h("div.finding" + (f.significant ? ".sig" : ""), null,
      h("h3", null, f.effect, " ", pill(f.significant ? "significant" : "not significant", f.significant ? "ok" : ""),
        f.kind ? [" ", pill(f.kind === "parameters_wrong" ? "parameters wrong" : "physics missing", "")] : null,
        f.implausible ? [" ", pill("implausible", "warning")] : null,
        h("span.muted.small", null, ` score ${fmt(f.score, 2)}`)),
      h("div", null, f.explanation),
      f.improved ? h("div.small.muted", { style: "margin-top:4px" }, "with it: ", metrics(f.improved)) : null,
      // What the other recordings of the cell say (diagnose --confirm, confirm_runs).
      Array.isArray(f.confirmation) ? (f.confirmation.length ? f.confirmation.map((c) =>
        h("div.small.confirm", { style: "margin-top:4px" }, pill(c.verdict, c.verdict === "contradicts" ? "warning" : (c.verdict === "confirms" ? "ok" : "")),
          ` on ${c.recording}: `, metrics(c.before), " → ", metrics(c.after)))
        : h("div.small.muted", { style: "margin-top:4px" }, "not checked on the other recordings: a state of this recording, not of the cell")) : null))
      : h("div.empty", null, "no candidate was tried")));
}

function renderDiagnosis(name, text) {
  let d;
  try { d = JSON.parse(text); } catch (e) { return h("div.note.warn", null, `${name}: not JSON (${e.message})`); }
  if (d.schema !== "cellbench.diagnosis/1") return h("div.note.warn", null, `${name}: expected "schema": "cellbench.diagnosis/1", got ${JSON.stringify(d.schema)}`);
  return diagnosisCard(d, `${name}: diagnosis`);
}
