// zagv fleet view. Plain ES module, no build step. Talks to the fleet service: REST under /api (bearer token) and
// the /api/ws stream of every robot at the site.
const $ = (sel) => document.querySelector(sel);
const COLOURS = ["#2457c5", "#d2691e", "#2e8b57", "#8e44ad", "#c0392b", "#16a085", "#7f8c8d", "#b8860b"];

const state = {
  token: sessionStorage.getItem("zagv.fleet.token") || "",
  fleet: { robots: [], map: { version: 0 }, events: [] },
  selected: "",
  poses: [],
  map: null,          // {meta, image}
  mapVersion: -1,
  ws: null,
  drag: null,
};

async function api(method, path, body) {
  const headers = { authorization: `Bearer ${state.token}` };
  if (body !== undefined) headers["content-type"] = "application/json";
  const r = await fetch(path, { method, headers, body: body === undefined ? undefined : JSON.stringify(body) });
  if (r.status === 401 && path !== "/api/login") { showLogin("session ended: log in again"); }
  const data = await r.json().catch(() => ({}));
  if (!r.ok) throw new Error(data.detail || `error ${r.status}`);
  return data;
}

function say(text, bad = false) {
  const m = $("#message");
  m.textContent = text;
  m.dataset.bad = bad ? "1" : "";
}

// ------------------------------------------------------------------ login

function showLogin(message = "") {
  state.token = "";
  sessionStorage.removeItem("zagv.fleet.token");
  if (state.ws) state.ws.close();
  $("#login").hidden = false;
  $("#login-error").textContent = message;
  $("#login-password").focus();
}

$("#login-form").addEventListener("submit", async (ev) => {
  ev.preventDefault();
  try {
    const r = await fetch("/api/login", { method: "POST", headers: { "content-type": "application/json" },
      body: JSON.stringify({ password: $("#login-password").value }) });
    if (!r.ok) { $("#login-error").textContent = r.status === 401 ? "wrong password" : `error ${r.status}`; return; }
    state.token = (await r.json()).token;
    sessionStorage.setItem("zagv.fleet.token", state.token);
    $("#login-password").value = "";
    $("#login").hidden = true;
    start();
  } catch (e) { $("#login-error").textContent = e.message; }
});

$("#btn-logout").addEventListener("click", async () => {
  try { await api("POST", "/api/logout"); } catch (e) { /* gone anyway */ }
  showLogin();
});

// ------------------------------------------------------------------ stream

function connectWs() {
  if (!state.token) return;
  const proto = location.protocol === "https:" ? "wss" : "ws";
  const ws = new WebSocket(`${proto}://${location.host}/api/ws?token=${encodeURIComponent(state.token)}`);
  state.ws = ws;
  ws.onopen = () => { $("#chip-link").textContent = "live"; $("#chip-link").className = "chip ok"; };
  ws.onmessage = (ev) => {
    state.fleet = JSON.parse(ev.data);
    if (state.fleet.map.version !== state.mapVersion) loadMap();
    render();
  };
  ws.onclose = (ev) => {
    $("#chip-link").textContent = "offline"; $("#chip-link").className = "chip bad";
    if (ev.code === 1008) { showLogin("session ended: log in again"); return; }
    if (state.token) setTimeout(connectWs, 1000);
  };
}

async function loadMap() {
  const version = state.fleet.map.version;
  state.mapVersion = version;
  try {
    const meta = await api("GET", "/api/map");
    if (!meta.available) { state.map = null; return; }
    const image = new Image();
    image.onload = () => { state.map = { meta, image }; draw(); };
    image.src = `data:image/png;base64,${meta.png_base64}`;
  } catch (e) { state.mapVersion = -1; say(`map: ${e.message}`, true); }
}

// ------------------------------------------------------------------ map transform

function colour(id) {
  const ids = state.fleet.robots.map((r) => r.id);
  return COLOURS[Math.max(0, ids.indexOf(id)) % COLOURS.length];
}

function view() {
  const canvas = $("#map");
  const w = canvas.clientWidth, h = canvas.clientHeight;
  let x0, y0, wm, hm;
  if (state.map) {
    const m = state.map.meta;
    x0 = m.origin.x; y0 = m.origin.y; wm = m.width * m.resolution_m; hm = m.height * m.resolution_m;
  } else {
    const poses = state.fleet.robots.filter((r) => r.pose).map((r) => r.pose);
    const xs = poses.map((p) => p.x), ys = poses.map((p) => p.y);
    x0 = (xs.length ? Math.min(...xs) : 0) - 5; y0 = (ys.length ? Math.min(...ys) : 0) - 5;
    wm = (xs.length ? Math.max(...xs) : 0) + 5 - x0; hm = (ys.length ? Math.max(...ys) : 0) + 5 - y0;
  }
  const scale = Math.min(w / wm, h / hm);
  return { x0, y0, wm, hm, scale, ox: (w - wm * scale) / 2, oy: (h - hm * scale) / 2 };
}

function worldToCanvas(x, y) {
  const v = view();
  return [v.ox + (x - v.x0) * v.scale, v.oy + (v.hm - (y - v.y0)) * v.scale];
}

function canvasToWorld(px, py) {
  const v = view();
  return [v.x0 + (px - v.ox) / v.scale, v.y0 + v.hm - (py - v.oy) / v.scale];
}

// ------------------------------------------------------------------ drawing

function draw() {
  const canvas = $("#map");
  const dpr = window.devicePixelRatio || 1;
  canvas.width = canvas.clientWidth * dpr; canvas.height = canvas.clientHeight * dpr;
  const g = canvas.getContext("2d");
  g.setTransform(dpr, 0, 0, dpr, 0, 0);
  g.clearRect(0, 0, canvas.clientWidth, canvas.clientHeight);
  const v = view();
  if (state.map) {
    g.imageSmoothingEnabled = false;
    g.drawImage(state.map.image, v.ox, v.oy, v.wm * v.scale, v.hm * v.scale);
  }
  // the pose list being built
  g.fillStyle = "#444";
  state.poses.forEach((p, i) => {
    const [px, py] = worldToCanvas(p.x, p.y);
    g.beginPath(); g.arc(px, py, 4, 0, 2 * Math.PI); g.fill();
    g.fillText(String(i + 1), px + 6, py - 6);
  });
  const drawn = [];
  for (const r of state.fleet.robots) {
    if (!r.pose || r.pose.x === null || r.pose.y === null) continue;
    const c = colour(r.id);
    // path
    if (r.path.length >= 4) {
      g.strokeStyle = c; g.lineWidth = 2; g.setLineDash([6, 4]); g.beginPath();
      for (let i = 0; i + 1 < r.path.length; i += 2) {
        const [px, py] = worldToCanvas(r.path[i], r.path[i + 1]);
        if (i === 0) g.moveTo(px, py); else g.lineTo(px, py);
      }
      g.stroke(); g.setLineDash([]);
    }
    if (r.nav && r.nav.goal && ["planning", "driving", "rotating", "recovering"].includes(r.nav.state)) {
      const [gx, gy] = worldToCanvas(r.nav.goal.x, r.nav.goal.y);
      g.strokeStyle = c; g.lineWidth = 2; g.beginPath();
      g.moveTo(gx - 6, gy - 6); g.lineTo(gx + 6, gy + 6); g.moveTo(gx - 6, gy + 6); g.lineTo(gx + 6, gy - 6); g.stroke();
    }
    // footprint and heading
    const [px, py] = worldToCanvas(r.pose.x, r.pose.y);
    const rad = Math.max(3, r.footprint.radius_m * v.scale);
    g.globalAlpha = r.present ? 0.35 : 0.12; g.fillStyle = c;
    g.beginPath(); g.arc(px, py, rad, 0, 2 * Math.PI); g.fill();
    g.globalAlpha = 1; g.strokeStyle = c; g.lineWidth = r.id === state.selected ? 4 : 2;
    g.beginPath(); g.arc(px, py, rad, 0, 2 * Math.PI); g.stroke();
    const th = r.pose.theta || 0;
    g.beginPath(); g.moveTo(px, py); g.lineTo(px + rad * Math.cos(th), py - rad * Math.sin(th)); g.stroke();
    g.fillStyle = "#111"; g.font = "bold 12px system-ui";
    g.fillText(r.id + (r.present ? "" : " (away)"), px + rad + 3, py - rad);
    drawn.push(r.id);
  }
  canvas.dataset.drawn = drawn.join(",");
}

function render() {
  const robots = state.fleet.robots;
  $("#chip-count").textContent = `${robots.filter((r) => r.present).length}/${robots.length} robots`;
  const list = $("#robots");
  list.replaceChildren(...robots.map((r) => {
    const li = document.createElement("li");
    li.dataset.robot = r.id;
    li.className = (r.id === state.selected ? "selected " : "") + (r.present ? "" : "absent");
    const swatch = document.createElement("span");
    swatch.className = "swatch"; swatch.style.background = colour(r.id);
    const name = document.createElement("span");
    name.className = "name"; name.textContent = r.id;
    const meta = document.createElement("div");
    meta.className = "meta";
    const p = r.pose ? `(${r.pose.x?.toFixed(2)}, ${r.pose.y?.toFixed(2)}, ${r.pose.theta?.toFixed(2)}) ${r.pose.frame}` : "no pose";
    const nav = r.nav ? r.nav.state + (r.nav.distance_left_m ? ` ${r.nav.distance_left_m.toFixed(1)} m left` : "") : "nav ?";
    const drive = r.drive ? (r.drive.estopped ? "e-stop" : r.drive.enabled ? "enabled" : "disabled") : "drive ?";
    const battery = r.battery ? `${r.battery.percent} % (${r.battery.voltage_v} V)` : "battery ?";
    meta.textContent = `${r.present ? "at the site" : "away"} · ${p} · ${nav} · ${drive} · ${battery}`;
    meta.dataset.nav = r.nav ? r.nav.state : "";
    const faults = document.createElement("div");
    faults.className = "faults"; faults.textContent = r.faults.join("; ");
    li.append(swatch, name, meta, faults);
    li.addEventListener("click", () => select(r.id));
    return li;
  }));
  $("#events").replaceChildren(...state.fleet.events.slice().reverse().map((e) => {
    const li = document.createElement("li");
    li.textContent = `${e.robot_id} ${e.event === "left" ? "left the site" : "is at the site"}`;
    return li;
  }));
  draw();
}

function select(id) {
  state.selected = id;
  state.poses = [];
  $("#selected").textContent = id;
  $("#command").disabled = !id;
  $("#pose-count").textContent = "0";
  render();
}

// ------------------------------------------------------------------ commands

function goalFromInputs() {
  return { x: Number($("#goal-x").value), y: Number($("#goal-y").value),
    theta: Number($("#goal-theta").value) * Math.PI / 180 };
}

async function sendGoal(goal) {
  const id = state.selected;
  try {
    const r = await api("POST", `/api/robots/${encodeURIComponent(id)}/goal`, goal);
    say(`${id}: goal ${r.goal_id} accepted`);
  } catch (e) { say(`${id}: ${e.message}`, true); }
}

$("#btn-goal").addEventListener("click", () => sendGoal(goalFromInputs()));
$("#btn-add-pose").addEventListener("click", () => { state.poses.push(goalFromInputs()); posesChanged(); });
$("#btn-clear-poses").addEventListener("click", () => { state.poses = []; posesChanged(); });
$("#btn-send-poses").addEventListener("click", async () => {
  const id = state.selected;
  if (!state.poses.length) { say("the pose list is empty", true); return; }
  try {
    const r = await api("POST", `/api/robots/${encodeURIComponent(id)}/poses`, { poses: state.poses });
    say(`${id}: pose list ${r.goal_id} accepted (${state.poses.length} poses)`);
    state.poses = []; posesChanged();
  } catch (e) { say(`${id}: ${e.message}`, true); }
});
$("#btn-cancel").addEventListener("click", async () => {
  try { await api("POST", `/api/robots/${encodeURIComponent(state.selected)}/cancel`); say(`${state.selected}: canceled`); }
  catch (e) { say(`${state.selected}: ${e.message}`, true); }
});
$("#btn-estop").addEventListener("click", async () => {
  try { await api("POST", `/api/robots/${encodeURIComponent(state.selected)}/estop`); say(`${state.selected}: e-stop`); }
  catch (e) { say(`${state.selected}: ${e.message}`, true); }
});

function posesChanged() { $("#pose-count").textContent = String(state.poses.length); draw(); }

// map: a click on a robot selects it; elsewhere it sets the goal (drag to aim) or adds a pose in pose-list mode
const canvas = $("#map");
canvas.addEventListener("mousedown", (ev) => { state.drag = [ev.offsetX, ev.offsetY]; });
canvas.addEventListener("mouseup", (ev) => {
  if (!state.drag) return;
  const [sx, sy] = state.drag; state.drag = null;
  const v = view();
  const hit = state.fleet.robots.find((r) => {
    if (!r.pose) return false;
    const [px, py] = worldToCanvas(r.pose.x, r.pose.y);
    return Math.hypot(px - sx, py - sy) <= Math.max(6, r.footprint.radius_m * v.scale);
  });
  if (hit && Math.hypot(ev.offsetX - sx, ev.offsetY - sy) < 5) { select(hit.id); return; }
  if (!state.selected) { say("pick a robot first", true); return; }
  const [x, y] = canvasToWorld(sx, sy);
  const theta = Math.hypot(ev.offsetX - sx, ev.offsetY - sy) >= 10 ? Math.atan2(-(ev.offsetY - sy), ev.offsetX - sx)
    : Number($("#goal-theta").value) * Math.PI / 180;
  $("#goal-x").value = x.toFixed(2); $("#goal-y").value = y.toFixed(2);
  $("#goal-theta").value = (theta * 180 / Math.PI).toFixed(0);
  if ($("#pose-mode").checked) { state.poses.push({ x, y, theta }); posesChanged(); } else sendGoal({ x, y, theta });
});
window.addEventListener("resize", draw);

// for tests and scripting: the map transform and the last fleet document
window.fleetView = { worldToCanvas, canvasToWorld, state };

async function start() {
  try { await api("GET", "/api/fleet"); connectWs(); } catch (e) { /* 401 shows the login */ }
}

if (state.token) start(); else showLogin();
