// cellbench dashboard: one page, hash routes.
//   #/              live view of the active run (or the newest run)
//   #/runs          runs list
//   #/runs/ID       one run: charts, fits (table and against SOC), steps, events, BDF export
//   #/diagnosis[/ID] the `cellbench diagnose` report of a run or a recording
import "./style.css";
import { liveStats, liveView } from "./live.js";
import { diagnosisView, runView, runsView } from "./views.js";
import { h } from "./util.js";

window.cellbench = { live: liveStats };

const app = document.getElementById("app");
const conn = document.getElementById("conn");
let dispose = null;

function setConn(ok, text) {
  conn.classList.toggle("ok", ok);
  conn.classList.toggle("bad", !ok);
  conn.querySelector(".txt").textContent = text;
}

function route() {
  if (dispose) dispose();
  dispose = null;
  app.replaceChildren();
  const path = (location.hash || "#/").slice(1);
  let m, nav = "live";
  try {
    if (path === "/" || path === "") dispose = liveView(app, setConn);
    else if (path === "/runs") { nav = "runs"; dispose = runsView(app); }
    else if ((m = path.match(/^\/runs\/(\d+)$/))) { nav = "runs"; dispose = runView(app, +m[1]); }
    else if ((m = path.match(/^\/diagnosis(?:\/(\d+))?$/))) { nav = "diagnosis"; dispose = diagnosisView(app, m[1]); }
    else { nav = ""; app.append(h("div.note.warn", null, "No such page. ", h("a", { href: "#/" }, "Back to the live view"))); }
  } catch (e) {
    app.append(h("div.note.warn", null, "This page failed: " + e.message));
  }
  document.querySelectorAll("[data-nav]").forEach((a) => a.classList.toggle("active", a.dataset.nav === nav));
  if (nav !== "live") fetch("/api/v1/health").then((r) => r.json()).then((j) => setConn(true, `cellbenchd ${j.version} · ${j.status}`)).catch(() => setConn(false, "cellbenchd unreachable"));
}

window.addEventListener("hashchange", route);
route();
