"""A scenario's results as tables and plots: per-goal summary (the paper's Table 3 layout), totals over legs, and
per-leg path and velocity plots (matplotlib, imported when plotting)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from proto import codec
from proto import messages as m
from services.scenario.client import Leg


def summarize(runs: list[dict]) -> list[dict]:
    """Per goal (in order): target, mean error over reached runs, reached count, mean time."""
    rows: dict[str, dict] = {}
    for run in runs:
        for g in run["goals"]:
            r = rows.setdefault(g["id"], {"id": g["id"], "target": g["target"], "errors": [], "times": [],
                                          "reached": 0, "total": 0})
            r["total"] += 1
            if g["reached"]:
                r["reached"] += 1
                r["errors"].append(g["error"])
                r["times"].append(g["time_s"])
    out = []
    for r in rows.values():
        e = np.asarray(r["errors"], dtype=float).reshape(-1, 3)
        out.append({"id": r["id"], "target": r["target"], "reached": r["reached"], "total": r["total"],
                    "mean_error": e.mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_abs_error": np.abs(e).mean(axis=0).tolist() if len(e) else [math.nan] * 3,
                    "mean_time_s": float(np.mean(r["times"])) if r["times"] else math.nan})
    return out


def leg_totals(runs: list[dict]) -> dict:
    """Totals over every goal of ``runs``: goals, reached (ground truth), claimed succeeded, claimed succeeded
    outside the tolerance, collisions, recoveries, localization error max and RMS (m, over all samples, RMS
    weighted by leg), time (s) and ground-truth distance driven (m), and time per metre (s/m) of the reached legs."""
    goals = [g for r in runs for g in r["goals"]]
    reached = [g for g in goals if g["reached"]]
    loc_max = [g.get("loc_error_max_m") for g in goals if g.get("loc_error_max_m") is not None]
    loc_rms = [g.get("loc_error_rms_m") for g in goals if g.get("loc_error_rms_m") is not None]
    t = sum(g["time_s"] for g in reached)
    d = sum(g.get("driven_m", 0.0) for g in reached)
    return {"goals": len(goals), "reached": len(reached),
            "claimed": sum(g.get("claimed", "succeeded" if g["reached"] else "") == "succeeded" for g in goals),
            "claimed_outside": sum(g.get("claimed") == "succeeded" and not g["reached"] for g in goals),
            "collisions": sum(g.get("collisions", 0) for g in goals),
            "recoveries": sum(g.get("recoveries", 0) for g in goals),
            "loc_error_max_m": max(loc_max) if loc_max else math.nan,
            "loc_error_rms_m": float(np.sqrt(np.mean(np.square(loc_rms)))) if loc_rms else math.nan,
            "time_s": t, "driven_m": d, "time_per_metre_s": t / d if d > 0 else math.nan}


def format_table(summary: list[dict]) -> str:
    w = max([len(str(r["id"])) for r in summary] + [4])
    head = f"{'goal':>{w}}  {'target (x, y, θ)':<24}  {'mean error x / y / θ':<26}  {'|error| x / y / θ':<26}  " \
           f"{'reached':>8}  {'time s':>7}"
    lines = [head, "-" * len(head)]
    for r in summary:
        t = "({:.2f}, {:.2f}, {:.2f})".format(*r["target"])
        e = "{:+.3f} / {:+.3f} / {:+.3f}".format(*r["mean_error"])
        a = "{:.3f} / {:.3f} / {:.3f}".format(*r["mean_abs_error"])
        lines.append(f"{r['id']:>{w}}  {t:<24}  {e:<26}  {a:<26}  {r['reached']:>3}/{r['total']:<4}  "
                     f"{r['mean_time_s']:>7.1f}")
    return "\n".join(lines)



def draw_plots(legs: list[Leg], grid: m.OccupancyGrid | None, out_dir: Path) -> list[Path]:
    """Per leg: map + planned path + driven path as heading arrows; vx, vy, wz against time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    files = []
    for k, leg in enumerate(legs, 1):
        tr = np.asarray(leg.trace, dtype=float).reshape(-1, 7)
        fig, ax = plt.subplots(figsize=(9, 6))
        if grid is not None and grid.width:
            data = codec.array(grid, "data").reshape(grid.height, grid.width)
            img = np.where(data < 0, 0.6, 1.0 - np.clip(data, 0, 100) / 100.0)
            ext = (grid.origin.x, grid.origin.x + grid.width * grid.resolution, grid.origin.y,
                   grid.origin.y + grid.height * grid.resolution)
            ax.imshow(img, cmap="gray", origin="lower", extent=ext, vmin=0, vmax=1)
        for r in leg.obstacles:
            ax.add_patch(plt.Rectangle((r[0], r[1]), r[2] - r[0], r[3] - r[1], color="orange", alpha=0.8,
                                       label="dynamic obstacle"))
        if leg.plan is not None and len(leg.plan):
            ax.plot(leg.plan[:, 0], leg.plan[:, 1], "b-", lw=1.5, label="global plan")
        if leg.final_plan is not None:
            ax.plot(leg.final_plan[:, 0], leg.final_plan[:, 1], "c--", lw=1.2, label="replanned around the obstacle")
        if len(tr):
            step = max(1, len(tr) // 60)
            s = tr[::step]
            ax.quiver(s[:, 1], s[:, 2], np.cos(s[:, 3]), np.sin(s[:, 3]), color="r", scale=40, width=0.003,
                      label="driven (heading)")
            pad = 2.0
            xs = np.concatenate([tr[:, 1], [leg.goal.pose[0]]])
            ys = np.concatenate([tr[:, 2], [leg.goal.pose[1]]])
            ax.set_xlim(xs.min() - pad, xs.max() + pad)
            ax.set_ylim(ys.min() - pad, ys.max() + pad)
        ax.plot(*leg.goal.pose[:2], "g*", ms=12, label=f"goal {leg.goal.id}")
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.legend(loc="best", fontsize=8)
        ax.set_title(f"run {leg.run}, leg {k}: to goal {leg.goal.id}")
        f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_path.png"
        fig.savefig(f, dpi=110, bbox_inches="tight")
        plt.close(fig)
        files.append(f)
        if len(tr):
            fig, ax = plt.subplots(figsize=(9, 4))
            t = tr[:, 0] - tr[0, 0]
            ax.plot(t, tr[:, 4], label="vx (m/s)")
            ax.plot(t, tr[:, 5], label="vy (m/s)")
            ax.plot(t, tr[:, 6], label="wz (rad/s)")
            ax.set_xlabel("time (s)")
            ax.grid(True, alpha=0.3)
            ax.legend(loc="best", fontsize=8)
            ax.set_title(f"run {leg.run}, leg {k}: velocities to goal {leg.goal.id}")
            f = out_dir / f"leg{k:02d}_goal{leg.goal.id}_velocity.png"
            fig.savefig(f, dpi=110, bbox_inches="tight")
            plt.close(fig)
            files.append(f)
    return files
