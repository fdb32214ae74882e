// zagv web HMI: control window (paper Fig. 8), map view, pose database, velocity curves.
// Plain ES module, no build step. Talks to hmi_api: REST under /api (bearer token) and the /api/ws stream.
import { MapView } from "/static/mapview.js";
import { Curves } from "/static/curves.js";

const $ = (sel) => document.querySelector(sel);
const $$ = (sel) => [...document.querySelectorAll(sel)];

const state = {
  token: sessionStorage.getItem("zagv.token") || "",
  robot: null,        // GET /api/robot
  status: null,       // latest status (WS)
  scan: [], particles: [], paths: { global: [], local: [] },
  map: null,          // {meta, image}
  poses: [],
  jogMode: "rotate",  // or "translate": what the left/right buttons do
  ws: null,
};

// ------------------------------------------------------------------ API

class ApiError extends Error {
  constructor(status, detail) { super(detail); this.status = status; }
}

async function api(method, path, body) {
  const headers = { authorization: `Bearer ${state.token}` };
  if (body !== undefined) headers["content-type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  const ct = r.headers.get("content-type") || "";
  const data = ct.includes("json") ? await r.json() : await r.text();
  if (r.status === 401 && path !== "/api/login") { showLogin("session ended: log in again"); }
  if (!r.ok) throw new ApiError(r.status, (data && data.detail) || `${r.status}`);
  return data;
}

let toastTimer = null;
function toast(text, isError = false) {
  const t = $("#toast");
  t.textContent = text;
  t.classList.toggle("bad", isError);
  clearTimeout(toastTimer);
  toastTimer = setTimeout(() => { t.textContent = ""; }, isError ? 15000 : 6000);
}

// Run an action from a button: show what happened in the status bar.
async function act(label, fn) {
  try {
    const r = await fn();
    toast(`${label}: ${(r && (r.message || r.goal_id)) || "ok"}`);
    return r;
  } catch (e) {
    toast(`${label} failed: ${e.message}`, true);
    return null;
  }
}

// ------------------------------------------------------------------ login

function showLogin(message = "") {
  state.token = "";
  sessionStorage.removeItem("zagv.token");
  $("#login").hidden = false;
  $("#login-error").textContent = message;
  $("#login-password").focus();
  if (state.ws) { state.ws.close(); state.ws = null; }
}

$("#login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  try {
    const r = await fetch("/api/login", { method: "POST", headers: { "content-type": "application/json" },
      body: JSON.stringify({ password: $("#login-password").value }) });
    if (!r.ok) { $("#login-error").textContent = r.status === 401 ? "wrong password" : `error ${r.status}`; return; }
    state.token = (await r.json()).token;
    sessionStorage.setItem("zagv.token", state.token);
    $("#login-password").value = "";
    $("#login").hidden = true;
    await start();
  } catch (e) { $("#login-error").textContent = e.message; }
});

$("#btn-logout").addEventListener("click", async () => {
  try { await api("POST", "/api/logout"); } catch (e) { /* logged out anyway */ }
  showLogin();
});

// ------------------------------------------------------------------ tabs

function showTab(name) {
  for (const b of $$(".tab")) b.classList.toggle("on", b.dataset.tab === name);
  for (const p of $$(".page")) p.hidden = p.id !== `tab-${name}`;
  if (location.hash !== `#${name}`) history.replaceState(null, "", `#${name}`);
  if (name === "poses") loadPoses();
  if (name === "curves") curves.resize();
  smallMap.resize(); bigMap.resize();
}
for (const b of $$(".tab")) b.addEventListener("click", () => showTab(b.dataset.tab));

// ------------------------------------------------------------------ function buttons

$("#btn-enable").addEventListener("click", () => act("enable", () => api("POST", "/api/drive/enable")));
$("#btn-disable").addEventListener("click", () => act("disable", () => api("POST", "/api/drive/disable")));
$("#btn-release").addEventListener("click", () => act("release", () => api("POST", "/api/drive/release")));
$("#btn-estop").addEventListener("click", () => { stopJog(); act("E-STOP", () => api("POST", "/api/drive/estop")); });
$("#btn-home").addEventListener("click", () => act("home", () => api("POST", "/api/home")));
$("#btn-cancel").addEventListener("click", () => act("cancel", () => api("POST", "/api/goal/cancel")));
$("#btn-navstart").addEventListener("click", () => act("navigation (run pose list)", () => api("POST", "/api/poses/run")));
$("#btn-teach-control").addEventListener("click", () => teach($("#teach-name")));
document.addEventListener("keydown", (ev) => { if (ev.key === "Escape") $("#btn-estop").click(); });

// ------------------------------------------------------------------ jog (dead-man: held buttons keep sending)

const JOG_PERIOD_MS = 100;
let jogTimer = null;
let jogTwist = null;

function jogTwistFor(dir) {
  const lim = state.robot ? state.robot.limits : { vx_min_mps: -0.1, vx_max_mps: 0.2, vy_max_mps: 0.2, wz_max_radps: 0.5 };
  const k = Number($("#jog-speed").value) / 100;
  const t = { vx: 0, vy: 0, wz: 0 };
  if (dir === "forward") t.vx = k * lim.vx_max_mps;
  if (dir === "back") t.vx = k * lim.vx_min_mps;
  if (dir === "left") { if (state.jogMode === "rotate") t.wz = k * lim.wz_max_radps; else t.vy = k * lim.vy_max_mps; }
  if (dir === "right") { if (state.jogMode === "rotate") t.wz = -k * lim.wz_max_radps; else t.vy = -k * lim.vy_max_mps; }
  return t;
}

async function sendJog() {
  if (!jogTwist) return;
  try {
    const r = await api("POST", "/api/jog", jogTwist);
    $("#jog-state").textContent = `jog vx ${r.vx.toFixed(2)} vy ${r.vy.toFixed(2)} wz ${r.wz.toFixed(2)}`;
  } catch (e) { toast(`jog failed: ${e.message}`, true); stopJog(); }
}

function startJog(dir, button) {
  stopJog();
  if (dir === "stop") { api("POST", "/api/jog", { vx: 0, vy: 0, wz: 0 }).catch(() => {}); return; }
  jogTwist = jogTwistFor(dir);
  button.classList.add("held");
  sendJog();
  jogTimer = setInterval(sendJog, JOG_PERIOD_MS);
}

function stopJog() {
  if (jogTimer) clearInterval(jogTimer);
  jogTimer = null;
  if (jogTwist) api("POST", "/api/jog", { vx: 0, vy: 0, wz: 0 }).catch(() => {});
  jogTwist = null;
  for (const b of $$(".jog.held")) b.classList.remove("held");
  $("#jog-state").textContent = "idle";
}

for (const b of $$(".jog")) {
  b.addEventListener("pointerdown", (ev) => { ev.preventDefault(); b.setPointerCapture(ev.pointerId); startJog(b.dataset.jog, b); });
  for (const evName of ["pointerup", "pointercancel", "lostpointercapture"]) b.addEventListener(evName, stopJog);
  b.addEventListener("contextmenu", (ev) => ev.preventDefault());
}
window.addEventListener("blur", stopJog);
document.addEventListener("visibilitychange", () => { if (document.hidden) stopJog(); });

const KEYS = { ArrowUp: "forward", ArrowDown: "back", ArrowLeft: "left", ArrowRight: "right" };
document.addEventListener("keydown", (ev) => {
  if (!KEYS[ev.key] || ev.repeat || ev.target.tagName === "INPUT" || $("#tab-control").hidden) return;
  ev.preventDefault();
  startJog(KEYS[ev.key], $(`[data-jog=${KEYS[ev.key]}]`));
});
document.addEventListener("keyup", (ev) => { if (KEYS[ev.key]) stopJog(); });

function setJogMode(mode) {
  state.jogMode = mode;
  const b = $("#btn-mode");
  b.textContent = `Mode: ${mode}`;
  b.setAttribute("aria-pressed", String(mode === "translate"));
  $("#jog-left").textContent = mode === "rotate" ? "⟲" : "◀";
  $("#jog-right").textContent = mode === "rotate" ? "⟳" : "▶";
}
$("#btn-mode").addEventListener("click", () => setJogMode(state.jogMode === "rotate" ? "translate" : "rotate"));
$("#jog-speed").addEventListener("input", () => { $("#jog-speed-out").textContent = `${$("#jog-speed").value} %`; });

// ------------------------------------------------------------------ status bar

const fmt = (v, d = 2) => (v === null || v === undefined ? "–" : Number(v).toFixed(d));
const deg = (rad) => (rad === null || rad === undefined ? "–" : `${(rad * 180 / Math.PI).toFixed(1)}°`);

function chip(id, text, cls) {
  const c = $(id);
  c.textContent = text;
  c.className = `chip ${cls || ""}`;
}

function renderStatus(s) {
  const stale = s.stale || [];
  const o = s.odom;
  $("#st-odom").textContent = o ? `x ${fmt(o.x)} y ${fmt(o.y)} θ ${deg(o.theta)} | v ${fmt(o.vx)} ${fmt(o.vy)} ${fmt(o.wz)}` : "–";
  const p = s.pose;
  const verdict = p && p.localization && p.localization !== "tracking" ? ` (${p.localization})` : "";
  $("#st-pose").textContent = p ? `${p.frame} x ${fmt(p.x)} y ${fmt(p.y)} θ ${deg(p.theta)}${verdict}` : "–";
  const w = s.wheels;
  $("#st-modules").textContent = w && w.modules.length
    ? w.modules.map((m, i) => `M${i + 1} ${deg(m.steer_rad)} ${fmt(m.speed_mps)} m/s`).join(" · ") : "–";
  const n = s.nav;
  $("#st-nav").textContent = n ? `${n.state}${n.goal_id ? ` ${n.goal_id}` : ""}${n.distance_left_m ? ` ${fmt(n.distance_left_m)} m left` : ""}`
    + (n.waypoint_count ? ` (${n.waypoint_index + 1}/${n.waypoint_count})` : "") + (n.error ? ` — ${n.error}` : "") : "–";
  $("#st-health").textContent = (s.health.join(" ") || "–") + (stale.length ? ` | silent: ${stale.join(" ")}` : "");
  if (!w) chip("#chip-drive", "drive: no data", "warn");
  else if (stale.includes("wheels")) chip("#chip-drive", "drive: silent", "bad");
  else if (w.estopped) chip("#chip-drive", "E-STOPPED", "bad");
  else if (w.fault) chip("#chip-drive", `fault: ${w.fault}`, "bad");
  else chip("#chip-drive", w.enabled ? "drive enabled" : "drive disabled", w.enabled ? "good" : "");
  const busy = n && ["planning", "driving", "rotating", "recovering"].includes(n.state);
  chip("#chip-nav", n ? `nav ${n.state}${stale.includes("nav") ? " (silent)" : ""}` : "nav: no data", !n ? "warn" : n.state === "failed" ? "bad" : busy ? "good" : "");
  const sf = s.safety;
  $("#st-safety").textContent = sf ? `${sf.action}${sf.action !== "clear" ? ` — ${sf.reason}` : ""} (${sf.interventions} interventions)` : "–";
  if (!sf) chip("#chip-safety", "safety: no data", "warn");
  else if (sf.action === "stop" || sf.action === "no_scan") chip("#chip-safety", `SAFETY STOP: ${sf.reason}`, "bad");
  else if (sf.action !== "clear") chip("#chip-safety", `safety ${sf.action} ×${fmt(sf.scale)}`, "warn");
  else chip("#chip-safety", "safety clear", "good");
  const loc = s.localization;
  if (!loc) chip("#chip-loc", "localization: no data", "warn");
  else chip("#chip-loc", `localization ${loc.state} (match ${fmt(loc.match_score)}, spread ${fmt(loc.spread_m)} m)`,
    loc.state === "tracking" ? "good" : loc.state === "lost" ? "bad" : "warn");
  for (const tr of $$("#pose-table tbody tr")) {
    tr.classList.toggle("active", !!(n && busy && n.goal_id && n.goal_id.startsWith(`pose${tr.dataset.id}-`)));
  }
}

// ------------------------------------------------------------------ live stream

function connectWs() {
  if (!state.token) return;
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${proto}://${location.host}/api/ws?token=${encodeURIComponent(state.token)}`);
  state.ws = ws;
  ws.onopen = () => chip("#chip-link", "live", "good");
  ws.onmessage = (ev) => {
    const f = JSON.parse(ev.data);
    state.status = f.status;
    state.scan = f.scan || [];
    if (f.paths) state.paths = f.paths;
    if (f.particles) state.particles = f.particles;
    if (f.vel) curves.push(f.vel);
    renderStatus(f.status);
    if (f.status.map.available && (!state.map || state.map.meta.version !== f.status.map.version)) loadMap();
    smallMap.draw(); bigMap.draw();
    if (!$("#tab-curves").hidden) curves.draw();
  };
  ws.onclose = () => {
    chip("#chip-link", "offline", "bad");
    if (state.ws === ws) {
      state.ws = null;
      setTimeout(async () => {
        try { await api("GET", "/api/status"); connectWs(); } catch (e) { /* 401 shows the login */ }
      }, 1000);
    }
  };
}

let mapLoading = false;
async function loadMap() {
  if (mapLoading) return;
  mapLoading = true;
  try {
    const m = await api("GET", "/api/map");
    if (m.available) {
      const img = new Image();
      img.onload = () => { const first = !state.map; state.map = { meta: m, image: img }; if (first) { smallMap.fit(); bigMap.fit(); } };
      img.src = `data:image/png;base64,${m.png_base64}`;
    }
  } catch (e) { toast(`map: ${e.message}`, true); } finally { mapLoading = false; }
}

// ------------------------------------------------------------------ map views

const smallMap = new MapView($("#map-small"), state, { interactive: false });
const bigMap = new MapView($("#map-big"), state, {
  interactive: true,
  onPose: async (tool, x, y, theta) => {
    if (tool === "goal") await act("goal", () => api("POST", "/api/goal", { x, y, theta }));
    if (tool === "initial") await act("initial pose", () => api("POST", "/api/initial_pose", { x, y, theta }));
  },
  onCursor: (x, y) => { $("#cursor-pos").textContent = `x ${x.toFixed(2)} y ${y.toFixed(2)}`; },
});
for (const b of $$(".tool")) {
  b.addEventListener("click", () => {
    for (const o of $$(".tool")) o.classList.toggle("on", o === b);
    bigMap.tool = b.dataset.tool;
  });
}
// mapping: start SLAM, save the map under a name, then localize (AMCL) on the saved map
let lastSavedMap = "";
$("#btn-map-start").addEventListener("click", () => {
  if (confirm("Start a new map? Localization switches to mapping until you navigate on a saved map.")) {
    act("start mapping", () => api("POST", "/api/mapping/start"));
  }
});
$("#btn-map-save").addEventListener("click", async () => {
  const name = prompt("Save the map as (letters, digits, _ - .):", lastSavedMap || "map");
  if (!name) return;
  const r = await act("save map", () => api("POST", "/api/mapping/save", { name }));
  if (r) lastSavedMap = name;
});
$("#btn-map-navigate").addEventListener("click", () => {
  const map = prompt("Navigate on which saved map (its name; empty: the last saved)?", lastSavedMap);
  if (map === null) return;
  act("navigate on map", () => api("POST", "/api/mapping/stop", { map }));
});
$("#btn-fit").addEventListener("click", () => bigMap.fit());
$("#btn-zoom-in").addEventListener("click", () => bigMap.zoom(1.25));
$("#btn-zoom-out").addEventListener("click", () => bigMap.zoom(0.8));
$("#follow").addEventListener("change", (ev) => { bigMap.follow = ev.target.checked; });
for (const layer of ["scan", "particles", "paths"]) {
  $(`#layer-${layer}`).addEventListener("change", (ev) => { bigMap.layers[layer] = ev.target.checked; bigMap.draw(); });
}

// ------------------------------------------------------------------ pose database

async function loadPoses() {
  try { renderPoses(await api("GET", "/api/poses")); } catch (e) { toast(`poses: ${e.message}`, true); }
}

function renderPoses(poses) {
  state.poses = poses;
  const body = $("#pose-table tbody");
  body.replaceChildren();
  for (const p of poses) {
    const tr = document.createElement("tr");
    tr.dataset.id = p.id;
    tr.innerHTML = `<td class="num">${p.index}</td><td class="name"></td><td class="num">${p.x.toFixed(3)}</td>`
      + `<td class="num">${p.y.toFixed(3)}</td><td class="num">${p.theta.toFixed(3)}</td><td class="actions"><div>`
      + `<button data-act="up" title="move up">▲</button><button data-act="down" title="move down">▼</button>`
      + `<button data-act="send" class="primary">Send</button><button data-act="edit">Edit</button>`
      + `<button data-act="delete">Delete</button></div></td>`;
    tr.querySelector(".name").textContent = p.name;
    body.append(tr);
  }
  $("#pose-empty").hidden = poses.length > 0;
  smallMap.draw(); bigMap.draw();
}

$("#pose-table").addEventListener("click", async (ev) => {
  const b = ev.target.closest("button");
  const tr = ev.target.closest("tr");
  if (!tr || !tr.dataset.id) return;
  for (const r of $$("#pose-table tr.selected")) r.classList.remove("selected");
  tr.classList.add("selected");
  if (!b) return;
  const id = tr.dataset.id;
  const a = b.dataset.act;
  if (a === "up" || a === "down") {
    const r = await act(`move ${a}`, () => api("POST", `/api/poses/${id}/move`, { direction: a }));
    if (r) renderPoses(r);
  } else if (a === "send") {
    await act(`send pose ${id}`, () => api("POST", `/api/poses/${id}/send`));
  } else if (a === "delete") {
    if (!confirm(`Delete pose "${tr.querySelector(".name").textContent}"?`)) return;
    if (await act("delete", () => api("DELETE", `/api/poses/${id}`))) loadPoses();
  } else if (a === "edit") {
    editRow(tr);
  } else if (a === "save") {
    const val = (k) => tr.querySelector(`[data-k=${k}]`).value;
    const body = { name: val("name"), x: Number(val("x")), y: Number(val("y")), theta: Number(val("theta")) };
    if (await act("save", () => api("PATCH", `/api/poses/${id}`, body))) loadPoses();
  } else if (a === "cancel") {
    loadPoses();
  }
});

function editRow(tr) {
  const p = state.poses.find((q) => String(q.id) === tr.dataset.id);
  const cells = tr.children;
  const input = (k, v, type = "number") => `<input data-k="${k}" type="${type}" step="0.01" value="">`;
  cells[1].innerHTML = input("name", p.name, "text");
  cells[2].innerHTML = input("x"); cells[3].innerHTML = input("y"); cells[4].innerHTML = input("theta");
  tr.querySelector("[data-k=name]").value = p.name;
  tr.querySelector("[data-k=x]").value = p.x; tr.querySelector("[data-k=y]").value = p.y;
  tr.querySelector("[data-k=theta]").value = p.theta.toFixed(4);
  cells[5].innerHTML = `<div><button data-act="save" class="primary">Save</button><button data-act="cancel">Cancel</button></div>`;
}

async function teach(nameInput) {
  const name = nameInput.value.trim() || `pose ${new Date().toLocaleTimeString()}`;
  const r = await act(`teach "${name}"`, () => api("POST", "/api/poses", { name, from_current: true }));
  if (r) { nameInput.value = ""; loadPoses(); }
}
$("#btn-teach").addEventListener("click", () => teach($("#pose-name")));

$("#btn-add-pose").addEventListener("click", async () => {
  const num = (id) => ($(id).value === "" ? null : Number($(id).value));
  const body = { name: $("#pose-name").value.trim(), x: num("#pose-x"), y: num("#pose-y"), theta: num("#pose-theta") ?? 0 };
  if (!body.name || body.x === null || body.y === null) { toast("add: give a name, x and y", true); return; }
  if (await act(`add "${body.name}"`, () => api("POST", "/api/poses", body))) {
    for (const id of ["#pose-name", "#pose-x", "#pose-y", "#pose-theta"]) $(id).value = "";
    loadPoses();
  }
});

$("#btn-run").addEventListener("click", () => act("run all", () => api("POST", "/api/poses/run")));

function download(name, text, type) {
  const a = document.createElement("a");
  a.href = URL.createObjectURL(new Blob([text], { type }));
  a.download = name;
  document.body.append(a);
  a.click();
  setTimeout(() => { URL.revokeObjectURL(a.href); a.remove(); }, 1000);
}

$("#btn-export").addEventListener("click", async () => {
  const doc = await act("export", () => api("GET", "/api/poses/export"));
  if (doc) download("zagv-poses.json", JSON.stringify(doc, null, 2), "application/json");
});

$("#import-file").addEventListener("change", async (ev) => {
  const file = ev.target.files[0];
  ev.target.value = "";
  if (!file) return;
  let doc;
  try { doc = JSON.parse(await file.text()); } catch (e) { toast(`import: not JSON (${e.message})`, true); return; }
  doc.replace = confirm("Replace the current list? (Cancel appends)");
  const r = await act(`import ${doc.poses ? doc.poses.length : 0} poses`, () => api("POST", "/api/poses/import", doc));
  if (r) renderPoses(r);
});

// ------------------------------------------------------------------ curves

const curves = new Curves($$(".curves canvas"), 60);
$("#btn-csv").addEventListener("click", async () => {
  try {
    const r = await fetch("/api/velocities.csv", { headers: { authorization: `Bearer ${state.token}` } });
    if (!r.ok) throw new Error(`${r.status}`);
    download("zagv-velocities.csv", await r.text(), "text/csv");
    toast("velocities downloaded");
  } catch (e) { toast(`CSV: ${e.message}`, true); }
});

// ------------------------------------------------------------------ start

async function start() {
  try {
    state.robot = await api("GET", "/api/robot");
  } catch (e) { if (e.status === 401) return; toast(e.message, true); }
  const hist = await api("GET", "/api/velocities?window_s=60").catch(() => null);
  if (hist) curves.load(hist.rows);
  loadPoses();
  loadMap();
  connectWs();
}

window.addEventListener("resize", () => { smallMap.resize(); bigMap.resize(); curves.resize(); });
setJogMode("rotate");
showTab((location.hash || "#control").slice(1).replace(/[^a-z]/g, "") || "control");
if (state.token) start(); else showLogin();
window.zagv = { state, smallMap, bigMap, curves };  // for inspection from the browser console and tests
