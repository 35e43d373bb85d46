// Run control on the live page: start a run (program, cell, parameter overrides), pause, resume and stop the
// active one. Every action is a POST with the API token (kept in this browser's localStorage).
import { apiToken, get, h, post } from "./util.js";

// "name=value" pairs, one per line or separated by commas -> {"name": number|string}; throws on a bad pair.
export function parseParameters(text) {
  const out = {};
  for (const raw of text.split(/[\n,]/)) {
    const part = raw.trim();
    if (!part) continue;
    const eq = part.indexOf("=");
    if (eq <= 0) throw new Error(`parameter "${part}": expected name=value`);
    const k = part.slice(0, eq).trim(), v = part.slice(eq + 1).trim();
    out[k] = v !== "" && Number.isFinite(Number(v)) ? Number(v) : v;
  }
  return out;
}

export function controlCard(onChange) {
  const programSel = h("select", { id: "ctl-program" });
  const cellSel = h("select", { id: "ctl-cell" });
  const params = h("input", { id: "ctl-params", placeholder: "e.g. current_a=4, rest_s=600", size: 28 });
  const token = h("input", { id: "ctl-token", type: "password", placeholder: "API token", autocomplete: "off", size: 14, value: apiToken.get() });
  token.addEventListener("change", () => apiToken.set(token.value.trim()));
  const msg = h("div", { id: "ctl-msg" });
  const startBtn = h("button.btn.primary", { id: "ctl-start", onclick: () => act(() => start()) }, "Start run");
  const pauseBtn = h("button.btn", { id: "ctl-pause", onclick: () => act(() => post(`/runs/${runId}/pause`, {})) }, "Pause");
  const resumeBtn = h("button.btn", { id: "ctl-resume", onclick: () => act(() => post(`/runs/${runId}/resume`, {})) }, "Resume");
  const stopBtn = h("button.btn.danger", { id: "ctl-stop", onclick: () => {
    if (window.confirm && !window.__cellbenchNoConfirm && !window.confirm(`Stop run ${runId}? The current goes off and the chamber returns to its safe set point.`)) return;
    act(() => post(`/runs/${runId}/stop`, {}));
  } }, "Stop");
  let runId = null;

  const field = (label, el) => h("label.field", null, h("span.small.muted", null, label), el);
  const card = h("div.card", { id: "control" }, h("h2", null, "Run control"),
    h("div.toolbar", null, field("program", programSel), field("cell", cellSel), field("parameters (optional)", params), startBtn),
    h("div.toolbar", { style: "margin-bottom:0" }, field("API token (kept in this browser)", token), pauseBtn, resumeBtn, stopBtn),
    msg);

  const note = (text, cls = "warn") => msg.replaceChildren(text ? h("div.note." + cls, { style: "margin:10px 0 0" }, text) : "");

  async function start() {
    const body = { program: programSel.value, cell: cellSel.value };
    const p = parseParameters(params.value);
    if (Object.keys(p).length) body.parameters = p;
    const run = await post("/runs", body);
    return run;
  }

  async function act(fn) {
    note("");
    apiToken.set(token.value.trim());
    for (const b of [startBtn, pauseBtn, resumeBtn, stopBtn]) b.disabled = true;
    try {
      const r = await fn();
      if (r?.id != null) note(`run ${r.id}: ${r.state}`, "ok");
      onChange?.();
    } catch (e) {
      if (e.status === 401 || e.status === 403) note(`${e.message} — enter the API token (cellbenchd --token / CELLBENCH_TOKEN).`);
      else note(e.message);
    } finally {
      update(lastRun);
    }
  }

  get("/cells").then((c) => {
    programSel.replaceChildren(...(c.programs || []).map((p) => h("option", { value: p }, p)));
    cellSel.replaceChildren(...(c.cells || []).map((x) => h("option", { value: x.name }, x.description ? `${x.name} · ${x.description}` : x.name)));
    if ([...programSel.options].some((o) => o.value === "hppc_short")) programSel.value = "hppc_short";
  }).catch((e) => note(`cannot list programs and cells: ${e.message}`));

  let lastRun = null;
  // Buttons follow the active run's state.
  function update(run) {
    lastRun = run;
    const live = run && ["starting", "waiting_equilibrium", "running", "paused", "stopping"].includes(run.state);
    runId = live ? run.id : null;
    startBtn.disabled = !!live;
    pauseBtn.disabled = !live || run.state === "paused" || run.state === "stopping";
    resumeBtn.disabled = !live || run.state !== "paused";
    stopBtn.disabled = !live || run.state === "stopping";
  }
  update(null);
  return { card, update };
}
