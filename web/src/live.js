// Live page: the active run (or, when the bench is idle, the newest run) as it is being recorded.
import { ChartGroup } from "./charts.js";
import { controlCard } from "./control.js";
import { fitsTable, instrumentList, liveTiles, stepBlock } from "./parts.js";
import { duration, get, h, hms, isActive, pill, poller } from "./util.js";

const WINDOWS = [[300, "5 min"], [600, "10 min"], [1800, "30 min"], [3600, "1 h"], [null, "Whole run"]];

// Read by the browser test (tests/hil/dashboard_browser_test.cpp) through executeScript.
export const liveStats = { updates: 0, points: 0, lastTime: null, runId: null, fits: 0 };

export function liveView(app, setConn) {
  let windowS = 600, zoomed = false, runId = null, runActive = false, knownEnd = null, latestRunCheck = 0;
  let lastStatus = null, lastRunObj = null;

  const runCard = h("div.card.grow", { style: "min-width:320px;flex:1.2" });
  const tilesCard = h("div.card.grow", { style: "flex:2" }, h("h2", null, "Live values"));
  const tiles = h("div");
  tilesCard.append(tiles);
  const seg = h("div.seg", null, WINDOWS.map(([s, label]) => h("button", {
    "data-window": s ?? "all", class: s === windowS ? "on" : null,
    onclick: (e) => {
      windowS = s;
      seg.querySelectorAll("button").forEach((b) => b.classList.toggle("on", b === e.currentTarget));
      charts.resetZoom();
      refreshSamples();
    },
  }, label)));
  const zoomNote = h("span.muted.small", null, "drag on a chart to zoom, double-click to return");
  const runLink = h("a.small");
  const toolbar = h("div.toolbar", null, h("span.small.muted", null, "show"), seg, zoomNote, h("span", { style: "margin-left:auto" }, runLink));
  const chartsBox = h("div");
  const instCard = h("div.card.instruments", null, h("h2", null, "Instruments"), h("div"));
  const faultCard = h("div.card", null, h("h2", null, "Latest warnings and faults"), h("div"));
  const fitsCard = h("div.card", null, h("h2", null, "Online fits (completed HPPC pulse sets)"), h("div"));
  const control = controlCard(() => { latestRunCheck = 0; refreshStatus().then(refreshSamples).catch(() => {}); });
  app.append(h("div.row", null, runCard, tilesCard), control.card, toolbar, chartsBox, instCard, faultCard, fitsCard);

  const charts = new ChartGroup(chartsBox, undefined, {
    onZoom: (z) => {
      zoomed = z;
      zoomNote.textContent = z ? "zoomed: not following new data — double-click a chart to follow live" : "drag on a chart to zoom, double-click to return";
      zoomNote.classList.toggle("muted", !z);
    },
  });

  function renderRun(run, live, progress) {
    runCard.replaceChildren();
    if (!run) {
      runCard.append(h("h2", null, "No run"), h("div.muted", null, "The bench is idle and no run has been recorded yet. Start one under Run control below, or with ",
        h("code", null, "cellbench start --program hppc_short --cell p45b --server URL --token TOKEN"), "."));
      return;
    }
    const d = duration(run);
    runCard.append(...[
      h("div.runhead", null, h("h1", null, `Run ${run.id}`), pill(run.state), runActive ? null : h("span.muted.small", null, "(newest run; none active)")),
      h("div.meta.muted", { style: "margin-top:4px" }, `${run.program} · cell ${run.cell} · ${run.samples ?? 0} samples`,
        d != null ? ` · ${hms(d)} wall` : "", live?.test_time_s != null && runActive ? ` · test time ${hms(live.test_time_s)}` : ""),
      stepBlock(runActive ? run : null, runActive ? progress : null),
      run.error ? h("div.note.warn", { style: "margin:10px 0 0" }, run.error) : null].filter(Boolean));
  }

  async function refreshStatus() {
    let status;
    try {
      status = await get("/status");
      setConn(true, `cellbenchd ${status.version} · up ${hms(status.uptime_s)}`);
    } catch (e) {
      setConn(false, "cellbenchd unreachable");
      throw e;
    }
    lastStatus = status;
    let run = status.run;
    runActive = isActive(run);
    if (!run && (runId == null || Date.now() - latestRunCheck > 5000)) {
      latestRunCheck = Date.now();
      const runs = (await get("/runs")).runs || [];
      run = runs[0] || null;
    } else if (!run && runId != null) {
      run = lastRunObj && lastRunObj.id === runId ? lastRunObj : await get(`/runs/${runId}`);
    }
    if ((run?.id ?? null) !== runId) { knownEnd = null; charts.resetZoom(); }
    runId = run?.id ?? null;
    lastRunObj = run;
    liveStats.runId = runId;
    renderRun(run, status.live, status.progress);
    runLink.replaceChildren(runId ? h("a", { href: `#/runs/${runId}` }, `run ${runId}: steps, events, fits, export →`) : "");
    runLink.href = runId ? `#/runs/${runId}` : "#/runs";
    tiles.replaceChildren(liveTiles(status.live));
    control.update(runActive ? run : null);
    let metrics = "";
    try { metrics = await (await fetch("/metrics")).text(); } catch { /* shown as – */ }
    instCard.lastChild.replaceWith(h("div", null, instrumentList(status.instruments, status.live, metrics)));
  }

  async function refreshSamples() {
    if (runId == null) return;
    const now = runActive && lastStatus?.live?.test_time_s != null ? lastStatus.live.test_time_s : knownEnd;
    const width = charts.plots[0]?.plot.width || 800;
    const q = new URLSearchParams({ max_points: String(Math.min(4000, Math.max(1000, 2 * width))) });
    if (windowS != null && now != null) q.set("from", String(Math.max(0, now - windowS)));
    const resp = await get(`/runs/${runId}/samples?${q}`);
    if (resp.to_s != null) knownEnd = resp.to_s;
    charts.setData(resp);
    if (windowS != null && now != null) charts.setWindow([Math.max(0, now - windowS), Math.max(now, resp.to_s ?? now)]);
    else charts.setWindow(null);
    liveStats.updates++;
    liveStats.points = charts.points;
    liveStats.lastTime = charts.lastTime;
  }

  async function refreshSide() {
    if (runId == null) return;
    const [ev, fits] = await Promise.all([get(`/runs/${runId}/events`), get(`/runs/${runId}/fits`)]);
    const faults = (ev.events || []).filter((e) => e.level !== "info").slice(-8).reverse();
    faultCard.lastChild.replaceWith(faults.length
      ? h("div.scroll", null, h("table", null, h("tbody", null, faults.map((e) => h("tr", null,
          h("td.num", null, hms(e.test_time_s)), h("td.level-" + e.level, null, e.level), h("td", null, e.kind), h("td", null, e.message))))))
      : h("div.empty", null, "none in this run"));
    const list = fits.fits || [];
    liveStats.fits = list.length;
    fitsCard.lastChild.replaceWith(list.length ? fitsTable(list)
      : h("div", null, h("div.empty", null, "no pulse set completed yet"), h("table", { id: "fits-table" }, h("tbody"))));
  }

  const polls = [
    poller(async () => { await refreshStatus(); await refreshSamples(); }, 1000),
    poller(refreshSide, 2000),
  ];
  return () => { polls.forEach((p) => p.stop()); charts.destroy(); };
}
