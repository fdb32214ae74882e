// Live curves of commanded (cmd_vel) and measured (odometry) body velocities over the last window.
// Rows: [t_s, cmd_vx, cmd_vy, cmd_wz, meas_vx, meas_vy, meas_wz] (m/s, rad/s), as GET /api/velocities gives.

const COLUMNS = { vx: [1, 4], vy: [2, 5], wz: [3, 6] };
const MIN_RANGE = { vx: 0.25, vy: 0.25, wz: 0.6 };

export class Curves {
  constructor(canvases, windowS) {
    this.canvases = canvases;
    this.windowS = windowS;
    this.rows = [];
  }

  load(rows) { this.rows = rows.slice(); this.draw(); }

  push(row) {
    const last = this.rows[this.rows.length - 1];
    if (last && row[0] <= last[0]) {
      if (row[0] < last[0] - 1) this.rows = [];  // the clock restarted
      else return;
    }
    this.rows.push(row);
    const cut = row[0] - this.windowS;
    let i = 0;
    while (i < this.rows.length && this.rows[i][0] < cut) i++;
    if (i) this.rows.splice(0, i);
  }

  resize() {
    const dpr = window.devicePixelRatio || 1;
    for (const c of this.canvases) {
      if (!c.clientWidth) continue;
      c.width = Math.round(c.clientWidth * dpr);
      c.height = Math.round(c.clientHeight * dpr);
    }
    this.draw();
  }

  draw() {
    for (const c of this.canvases) this.drawOne(c);
  }

  drawOne(canvas) {
    const w = canvas.clientWidth, h = canvas.clientHeight;
    if (!w || !h) return;
    const dpr = window.devicePixelRatio || 1;
    if (canvas.width !== Math.round(w * dpr)) { canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr); }
    const ctx = canvas.getContext("2d");
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.clearRect(0, 0, w, h);
    const key = canvas.dataset.col, [ci, mi] = COLUMNS[key];
    const rows = this.rows;
    const tEnd = rows.length ? rows[rows.length - 1][0] : 0;
    let range = MIN_RANGE[key];
    for (const r of rows) for (const v of [r[ci], r[mi]]) if (v !== null && Math.abs(v) > range) range = Math.abs(v);
    range *= 1.1;
    const left = 52, right = 10, top = 8, bottom = 18;
    const X = (t) => left + (1 - (tEnd - t) / this.windowS) * (w - left - right);
    const Y = (v) => top + (1 - (v + range) / (2 * range)) * (h - top - bottom);
    ctx.strokeStyle = "#e5e7eb"; ctx.lineWidth = 1; ctx.font = "11px system-ui"; ctx.fillStyle = "#6b7280";
    ctx.beginPath();
    for (const v of [-range / 1.1, 0, range / 1.1]) { ctx.moveTo(left, Y(v)); ctx.lineTo(w - right, Y(v)); ctx.fillText(v.toFixed(2), 6, Y(v) + 4); }
    for (let s = 0; s <= this.windowS; s += 10) { ctx.moveTo(X(tEnd - s), top); ctx.lineTo(X(tEnd - s), h - bottom); ctx.fillText(`-${s}s`, X(tEnd - s) - 12, h - 4); }
    ctx.stroke();
    ctx.fillStyle = "#111827"; ctx.font = "bold 12px system-ui";
    ctx.fillText(canvas.dataset.label, left + 6, top + 12);
    this.line(ctx, rows, ci, X, Y, "#ea580c", [6, 4]);
    this.line(ctx, rows, mi, X, Y, "#2563eb", []);
  }

  line(ctx, rows, col, X, Y, color, dash) {
    ctx.strokeStyle = color; ctx.lineWidth = 2; ctx.setLineDash(dash);
    ctx.beginPath();
    let pen = false;
    for (const r of rows) {
      if (r[col] === null) { pen = false; continue; }
      const x = X(r[0]), y = Y(r[col]);
      if (pen) ctx.lineTo(x, y); else ctx.moveTo(x, y);
      pen = true;
    }
    ctx.stroke();
    ctx.setLineDash([]);
  }
}
