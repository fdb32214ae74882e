// Canvas map view: occupancy map, 1 m grid, stored poses, particles, global and local paths, nav goal,
// scan points and the robot (footprint circle, heading, swerve modules at their steer angles).
// World frame is the map frame (x right, y up); view = centre (cx, cy) in m and scale in px/m.

const COLORS = { scan: "#dc2626", particles: "rgba(126, 34, 206, 0.55)", global: "#16a34a", local: "#0891b2",
  robot: "rgba(37, 99, 235, 0.25)", robotLine: "#1d4ed8", goal: "#dc2626", pose: "#ea580c", drag: "#f59e0b" };

export class MapView {
  constructor(canvas, state, opts = {}) {
    this.canvas = canvas;
    this.ctx = canvas.getContext("2d");
    this.state = state;
    this.opts = opts;
    this.view = { cx: 0, cy: 0, scale: 40 };
    this.tool = "pan";
    this.follow = !opts.interactive;
    this.layers = { scan: true, particles: true, paths: true };
    this.drag = null;
    this.pending = false;
    this.fitted = false;
    if (opts.interactive) this.bindPointer();
    new ResizeObserver(() => this.resize()).observe(canvas);
  }

  resize() {
    const dpr = window.devicePixelRatio || 1;
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h) return;
    if (this.canvas.width !== Math.round(w * dpr) || this.canvas.height !== Math.round(h * dpr)) {
      this.canvas.width = Math.round(w * dpr);
      this.canvas.height = Math.round(h * dpr);
      if (!this.fitted) this.fit();
    }
    this.draw();
  }

  fit() {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    const m = this.state.map && this.state.map.meta;
    if (!w || !h) return;
    if (m && this.opts.interactive) {
      const mw = m.width * m.resolution_m, mh = m.height * m.resolution_m;
      this.view = { cx: m.origin.x + mw / 2, cy: m.origin.y + mh / 2, scale: 0.95 * Math.min(w / mw, h / mh) };
    } else {
      const p = this.robotPose();
      this.view = { cx: p ? p.x : 0, cy: p ? p.y : 0, scale: Math.max(20, Math.min(w, h) / 8) };
    }
    this.fitted = true;
    this.draw();
  }

  zoom(k, sx, sy) {
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    sx = sx ?? w / 2; sy = sy ?? h / 2;
    const before = this.toWorld(sx, sy);
    this.view.scale = Math.min(400, Math.max(2, this.view.scale * k));
    const after = this.toWorld(sx, sy);
    this.view.cx += before.x - after.x;
    this.view.cy += before.y - after.y;
    this.draw();
  }

  toScreen(x, y) {
    const v = this.view;
    return { x: this.canvas.clientWidth / 2 + (x - v.cx) * v.scale, y: this.canvas.clientHeight / 2 - (y - v.cy) * v.scale };
  }

  toWorld(sx, sy) {
    const v = this.view;
    return { x: v.cx + (sx - this.canvas.clientWidth / 2) / v.scale, y: v.cy - (sy - this.canvas.clientHeight / 2) / v.scale };
  }

  robotPose() {
    const s = this.state.status;
    return s && s.pose && s.pose.x !== null ? s.pose : null;
  }

  bindPointer() {
    const c = this.canvas;
    const local = (ev) => { const r = c.getBoundingClientRect(); return { x: ev.clientX - r.left, y: ev.clientY - r.top }; };
    const touches = new Map();  // pointerId -> position, for two-finger pinch zoom on tablets
    let pinch = null;
    c.addEventListener("pointerdown", (ev) => {
      c.setPointerCapture(ev.pointerId);
      const p = local(ev);
      touches.set(ev.pointerId, p);
      if (touches.size === 2) {
        const [a, b] = [...touches.values()];
        pinch = { dist: Math.hypot(a.x - b.x, a.y - b.y), scale: this.view.scale };
        this.drag = null;
        return;
      }
      this.drag = { tool: this.tool, start: p, now: p, view: { ...this.view } };
    });
    const lift = (ev) => { touches.delete(ev.pointerId); if (touches.size < 2) pinch = null; };
    c.addEventListener("pointerup", lift);
    c.addEventListener("pointercancel", lift);
    c.addEventListener("pointermove", (ev) => {
      const p = local(ev);
      if (touches.has(ev.pointerId)) touches.set(ev.pointerId, p);
      if (pinch && touches.size === 2) {
        const [a, b] = [...touches.values()];
        const k = (pinch.scale * Math.hypot(a.x - b.x, a.y - b.y) / Math.max(1, pinch.dist)) / this.view.scale;
        this.zoom(k, (a.x + b.x) / 2, (a.y + b.y) / 2);
        return;
      }
      const w = this.toWorld(p.x, p.y);
      if (this.opts.onCursor) this.opts.onCursor(w.x, w.y);
      if (!this.drag) return;
      this.drag.now = p;
      if (this.drag.tool === "pan") {
        this.view.cx = this.drag.view.cx - (p.x - this.drag.start.x) / this.view.scale;
        this.view.cy = this.drag.view.cy + (p.y - this.drag.start.y) / this.view.scale;
      }
      this.draw();
    });
    const finish = () => {
      const d = this.drag;
      this.drag = null;
      if (!d || d.tool === "pan") return;
      const a = this.toWorld(d.start.x, d.start.y), b = this.toWorld(d.now.x, d.now.y);
      const dragged = Math.hypot(d.now.x - d.start.x, d.now.y - d.start.y) > 8;
      const theta = dragged ? Math.atan2(b.y - a.y, b.x - a.x) : 0;
      if (this.opts.onPose) this.opts.onPose(d.tool, round(a.x), round(a.y), round(theta));
      this.draw();
    };
    c.addEventListener("pointerup", finish);
    c.addEventListener("pointercancel", () => { this.drag = null; this.draw(); });
    c.addEventListener("wheel", (ev) => { ev.preventDefault(); const p = local(ev); this.zoom(ev.deltaY < 0 ? 1.15 : 1 / 1.15, p.x, p.y); },
      { passive: false });
  }

  draw() {
    if (this.pending) return;
    this.pending = true;
    requestAnimationFrame(() => { this.pending = false; this.render(); });
  }

  render() {
    const ctx = this.ctx, dpr = window.devicePixelRatio || 1;
    const w = this.canvas.clientWidth, h = this.canvas.clientHeight;
    if (!w || !h || this.canvas.offsetParent === null) return;
    const robot = this.robotPose();
    if (this.follow && robot) { this.view.cx = robot.x; this.view.cy = robot.y; }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = "#9ca3af";
    ctx.fillRect(0, 0, w, h);
    const map = this.state.map;
    if (map) {
      const m = map.meta;
      const tl = this.toScreen(m.origin.x, m.origin.y + m.height * m.resolution_m);
      ctx.imageSmoothingEnabled = this.view.scale * m.resolution_m < 2;
      ctx.drawImage(map.image, tl.x, tl.y, m.width * m.resolution_m * this.view.scale, m.height * m.resolution_m * this.view.scale);
    }
    this.drawGrid(w, h);
    this.drawPoses();
    const L = this.opts.interactive ? this.layers : { scan: true, particles: false, paths: true };
    if (L.particles) this.drawParticles();
    if (L.paths) {
      this.polyline(this.state.paths.global, COLORS.global, 3);
      this.polyline(this.state.paths.local, COLORS.local, 2);
    }
    this.drawGoal();
    if (L.scan) this.drawScan();
    if (robot) this.drawRobot(robot);
    if (this.drag && this.drag.tool !== "pan") this.drawDrag();
    this.drawScaleBar(h);
    if (!map) {
      ctx.fillStyle = "#1f2937"; ctx.font = "14px system-ui"; ctx.fillText("no map yet", 12, 22);
    }
  }

  drawGrid(w, h) {
    const ctx = this.ctx, s = this.view.scale;
    if (s < 8) return;
    const a = this.toWorld(0, h), b = this.toWorld(w, 0);
    ctx.strokeStyle = "rgba(59, 130, 246, 0.18)";
    ctx.lineWidth = 1;
    ctx.beginPath();
    for (let x = Math.ceil(a.x); x <= b.x; x++) { const p = this.toScreen(x, 0).x; ctx.moveTo(p, 0); ctx.lineTo(p, h); }
    for (let y = Math.ceil(a.y); y <= b.y; y++) { const p = this.toScreen(0, y).y; ctx.moveTo(0, p); ctx.lineTo(w, p); }
    ctx.stroke();
  }

  drawScaleBar(h) {
    const ctx = this.ctx;
    const metres = [0.5, 1, 2, 5, 10, 20].find((m) => m * this.view.scale > 60) || 50;
    const len = metres * this.view.scale;
    ctx.fillStyle = "rgba(255,255,255,0.8)";
    ctx.fillRect(8, h - 28, len + 16, 20);
    ctx.fillStyle = "#111827";
    ctx.fillRect(16, h - 16, len, 3);
    ctx.font = "11px system-ui";
    ctx.fillText(`${metres} m`, 18, h - 19);
  }

  polyline(flat, color, width) {
    if (!flat || flat.length < 6) return;
    const ctx = this.ctx;
    ctx.strokeStyle = color; ctx.lineWidth = width; ctx.lineJoin = "round";
    ctx.beginPath();
    for (let i = 0; i + 2 < flat.length; i += 3) {
      const p = this.toScreen(flat[i], flat[i + 1]);
      if (i === 0) ctx.moveTo(p.x, p.y); else ctx.lineTo(p.x, p.y);
    }
    ctx.stroke();
  }

  arrow(x, y, theta, len, color, width = 2) {
    const ctx = this.ctx, p = this.toScreen(x, y);
    const ex = p.x + Math.cos(theta) * len, ey = p.y - Math.sin(theta) * len;
    ctx.strokeStyle = color; ctx.fillStyle = color; ctx.lineWidth = width;
    ctx.beginPath(); ctx.moveTo(p.x, p.y); ctx.lineTo(ex, ey); ctx.stroke();
    const hx = Math.cos(theta), hy = -Math.sin(theta), k = Math.max(5, len * 0.3);
    ctx.beginPath();
    ctx.moveTo(ex, ey);
    ctx.lineTo(ex - k * hx - k * 0.5 * hy, ey - k * hy + k * 0.5 * hx);
    ctx.lineTo(ex - k * hx + k * 0.5 * hy, ey - k * hy - k * 0.5 * hx);
    ctx.closePath(); ctx.fill();
  }

  drawParticles() {
    const f = this.state.particles;
    if (!f || !f.length) return;
    const len = Math.max(4, 0.15 * this.view.scale);
    for (let i = 0; i + 2 < f.length; i += 3) this.arrow(f[i], f[i + 1], f[i + 2], len, COLORS.particles, 1);
  }

  drawScan() {
    const f = this.state.scan, ctx = this.ctx;
    if (!f || !f.length) return;
    ctx.fillStyle = COLORS.scan;
    const r = Math.max(1.5, Math.min(3, 0.03 * this.view.scale));
    for (let i = 0; i + 1 < f.length; i += 2) {
      if (f[i] === null) continue;
      const p = this.toScreen(f[i], f[i + 1]);
      ctx.fillRect(p.x - r / 2, p.y - r / 2, r, r);
    }
  }

  drawGoal() {
    const n = this.state.status && this.state.status.nav;
    if (!n || !n.goal || n.goal.x === null || ["idle", "succeeded", "canceled"].includes(n.state)) return;
    this.arrow(n.goal.x, n.goal.y, n.goal.theta, Math.max(18, 0.6 * this.view.scale), COLORS.goal, 3);
  }

  drawPoses() {
    const ctx = this.ctx;
    ctx.font = "bold 11px system-ui";
    for (const p of this.state.poses || []) {
      const s = this.toScreen(p.x, p.y);
      this.arrow(p.x, p.y, p.theta, Math.max(12, 0.4 * this.view.scale), COLORS.pose, 2);
      ctx.fillStyle = COLORS.pose;
      ctx.beginPath(); ctx.arc(s.x, s.y, 8, 0, 2 * Math.PI); ctx.fill();
      ctx.fillStyle = "#fff"; ctx.textAlign = "center"; ctx.textBaseline = "middle";
      ctx.fillText(String(p.index), s.x, s.y + 0.5);
      ctx.textAlign = "start"; ctx.textBaseline = "alphabetic";
    }
  }

  drawRobot(pose) {
    const ctx = this.ctx, robot = this.state.robot, s = this.view.scale;
    const p = this.toScreen(pose.x, pose.y);
    const radius = (robot ? robot.chassis_radius_m : 0.63) * s;
    ctx.fillStyle = COLORS.robot; ctx.strokeStyle = COLORS.robotLine; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(p.x, p.y, radius, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    const c = Math.cos(pose.theta), sn = Math.sin(pose.theta);
    const wheels = this.state.status && this.state.status.wheels;
    const modules = robot ? robot.modules : [];
    modules.forEach((m, i) => {
      const wx = pose.x + c * m.x - sn * m.y, wy = pose.y + sn * m.x + c * m.y;
      const steer = wheels && wheels.modules[i] && wheels.modules[i].steer_rad !== null ? wheels.modules[i].steer_rad : 0;
      const q = this.toScreen(wx, wy);
      ctx.save();
      ctx.translate(q.x, q.y);
      ctx.rotate(-(pose.theta + steer));
      ctx.fillStyle = "#111827";
      ctx.fillRect(-0.1 * s, -0.04 * s, 0.2 * s, 0.08 * s);
      ctx.restore();
    });
    this.arrow(pose.x, pose.y, pose.theta, Math.max(16, radius * 1.1), COLORS.robotLine, 3);
  }

  drawDrag() {
    const d = this.drag, a = this.toWorld(d.start.x, d.start.y), b = this.toWorld(d.now.x, d.now.y);
    const theta = Math.atan2(b.y - a.y, b.x - a.x);
    const len = Math.max(20, Math.hypot(d.now.x - d.start.x, d.now.y - d.start.y));
    this.arrow(a.x, a.y, theta, len, d.tool === "goal" ? COLORS.goal : COLORS.drag, 3);
  }
}

function round(v) { return Math.round(v * 1000) / 1000; }
