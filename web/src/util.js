// Small helpers: DOM building, formatting, the REST client.

export const API = "/api/v1";

// GET a JSON endpoint; throws Error(message from {"error": ...} or the status).
export async function get(path, signal) {
  const res = await fetch(API + path, { signal, headers: { Accept: "application/json" } });
  if (!res.ok) {
    let msg = `${res.status} ${res.statusText}`;
    try { msg = (await res.json()).error || msg; } catch { /* not JSON */ }
    throw new Error(msg);
  }
  return res.json();
}

// The API token for mutating requests (POST), kept in this browser's localStorage. cellbenchd refuses POSTs
// without it (401) or when it has none configured (403).
const TOKEN_KEY = "cellbench.token";
export const apiToken = {
  get() { try { return localStorage.getItem(TOKEN_KEY) || ""; } catch { return ""; } },
  set(t) { try { if (t) localStorage.setItem(TOKEN_KEY, t); else localStorage.removeItem(TOKEN_KEY); } catch { /* private mode */ } },
};

// POST to the API with the stored token. body: an object (sent as JSON) or a Blob/File/string with `type`.
// Throws Error(message from {"error": ...}) with .status.
export async function post(path, body, type = "application/json") {
  const headers = { Accept: "application/json", "Content-Type": type };
  const t = apiToken.get();
  if (t) headers.Authorization = `Bearer ${t}`;
  const payload = type === "application/json" && typeof body !== "string" ? JSON.stringify(body ?? {}) : body;
  const res = await fetch(API + path, { method: "POST", headers, body: payload });
  let j = null;
  try { j = await res.json(); } catch { /* not JSON */ }
  if (!res.ok) {
    const e = new Error(j?.error || `${res.status} ${res.statusText}`);
    e.status = res.status;
    throw e;
  }
  return j;
}

// h("div.card", {onclick}, child, "text", ...)
export function h(tag, attrs, ...children) {
  const [name, ...classes] = tag.split(".");
  const el = document.createElement(name || "div");
  if (classes.length) el.className = classes.join(" ");
  if (attrs) {
    for (const [k, v] of Object.entries(attrs)) {
      if (v == null || v === false) continue;
      if (k.startsWith("on")) el.addEventListener(k.slice(2), v);
      else if (k === "html") el.innerHTML = v;
      else el.setAttribute(k, v === true ? "" : v);
    }
  }
  append(el, children);
  return el;
}
function append(el, children) {
  for (const c of children) {
    if (c == null || c === false) continue;
    if (Array.isArray(c)) append(el, c);
    else el.append(c instanceof Node ? c : String(c));
  }
}

export const esc = (s) => String(s).replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);

// Numbers: fixed decimals, "–" for null/NaN.
export function fmt(x, digits = 3, scale = 1) {
  if (x == null || !Number.isFinite(x)) return "–";
  const s = (x * scale).toFixed(digits);
  return /^-0(\.0*)?$/.test(s) ? s.slice(1) : s;  // never "-0.000"
}

// The tester's step kinds in words (Neware step types as the daemon reports them).
const STEP_WORDS = {
  rest: "rest", dc: "constant-current discharge", cc: "constant-current charge", cv: "constant-voltage charge",
  cccv: "constant-current, constant-voltage charge", dcv: "constant-voltage discharge", cp: "constant-power charge",
  dp: "constant-power discharge", cr: "constant-resistance discharge", pulse: "current pulse", end: "end of program",
  cc_discharge: "constant-current discharge", cc_charge: "constant-current charge", cv_charge: "constant-voltage charge",
  cccv_dc: "constant-current, constant-voltage discharge", cccv_dchg: "constant-current, constant-voltage discharge",
  cc_dchg: "constant-current discharge", cc_chg: "constant-current charge", cv_chg: "constant-voltage charge",
  cccv_chg: "constant-current, constant-voltage charge",
};
export function stepWords(kind) {
  if (!kind) return "–";
  const w = STEP_WORDS[String(kind).toLowerCase().replace(/[\s-]+/g, "_")];
  if (!w) return String(kind);
  return w.toLowerCase() === String(kind).toLowerCase() ? w : `${w} (${kind})`;
}

// Test time in seconds as h:mm:ss (or m:ss).
export function hms(s, withTenths = false) {
  if (s == null || !Number.isFinite(s)) return "–";
  const neg = s < 0;
  s = Math.abs(s);
  const hh = Math.floor(s / 3600), mm = Math.floor((s % 3600) / 60);
  const ss = withTenths ? (s % 60).toFixed(1).padStart(4, "0") : String(Math.floor(s % 60)).padStart(2, "0");
  return (neg ? "-" : "") + (hh ? `${hh}:${String(mm).padStart(2, "0")}:${ss}` : `${mm}:${ss}`);
}

export function dateTime(unix) {
  if (unix == null) return "–";
  const d = new Date(unix * 1000);
  const p = (n) => String(n).padStart(2, "0");
  return `${d.getFullYear()}-${p(d.getMonth() + 1)}-${p(d.getDate())} ${p(d.getHours())}:${p(d.getMinutes())}:${p(d.getSeconds())}`;
}

export function duration(run) {
  if (!run.started_unix_s) return null;
  return (run.ended_unix_s ?? Date.now() / 1000) - run.started_unix_s;
}

export const pill = (text, cls = text) => h("span.pill." + String(cls).replace(/[^a-z_-]/gi, ""), null, text);

export function isActive(run) { return run && ["starting", "waiting_equilibrium", "running", "paused", "stopping"].includes(run.state); }

// A repeating poll that never overlaps itself; stop() cancels it.
export function poller(fn, periodMs) {
  let timer = null, stopped = false;
  const loop = async () => {
    if (stopped) return;
    try { await fn(); } catch (e) { if (!stopped) console.warn(e); }
    if (!stopped) timer = setTimeout(loop, periodMs);
  };
  loop();
  return { stop() { stopped = true; clearTimeout(timer); } };
}
