"""Dynamic Window Approach for a holonomic base (Fox, Burgard, Thrun 1997; Nav2 DWB's XYTheta iterator).

Window: each body velocity component (vx, vy, wz) may change by at most ``acc_lim * window_dt_s`` from the current
command and stays within the Table 2 limits. ``vx_samples x vy_samples x wz_samples`` twists are sampled on a grid over
the window (plus the exact zero of each axis when it lies inside, so stopping is always a candidate). Each twist is
held over ``sim_time_s`` and integrated exactly on SE(2):

    theta(t) = theta0 + wz t
    x(t) = x0 + vx S(t) - vy C(t),   y(t) = y0 + vx C(t) + vy S(t)
    S(t) = (sin theta(t) - sin theta0) / wz,   C(t) = (cos theta0 - cos theta(t)) / wz   (t cos theta0, t sin theta0
    as wz -> 0).

Critics, all vectorised over the samples (numpy), each scaled by its weight in ``DwaConfig`` and summed (lowest wins):
- obstacle: max costmap cost along the trajectory / 252; a cell >= 253 (or unknown) makes the sample invalid
  (except, when the robot already stands in the inscribed zone, trajectories that end outside it);
- path_distance: distance (m) from the trajectory end to the nearest point of the local path;
- path_alignment: |heading error| (rad) of the end pose against the path direction at that nearest point;
- goal_distance: distance (m) from the end to the local goal (the last point of the local path);
- goal_heading: |heading error| (rad) of the end pose against the goal's heading, only within
  ``goal_heading_activation_m`` of the goal;
- oscillation: 1 for each velocity component whose sign flips against the previous command.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import msgspec
import numpy as np

from services.common.robot import TwistLimits
from services.common.se2 import wrap_angle
from services.nav.costmap import INSCRIBED, MAX_NON_OBSTACLE, NO_INFORMATION, Costmap2D, Footprint

try:
    import services.nav._navops as _navops
except ImportError:  # built at install where a C compiler was available (setup.py); NumPy below otherwise
    _navops = None


class DwaConfig(msgspec.Struct, forbid_unknown_fields=True):
    """DWA sampling and critic weights ([nav.dwa])."""

    vx_samples: int = 20
    vy_samples: int = 5
    wz_samples: int = 20
    sim_time_s: float = 1.7
    sim_steps: int = 17
    window_dt_s: float = 0.25
    weight_obstacle: float = 0.5
    weight_path_distance: float = 8.0
    weight_path_alignment: float = 1.0
    weight_goal_distance: float = 6.0
    weight_goal_heading: float = 1.5
    weight_oscillation: float = 0.05
    goal_heading_activation_m: float = 1.0
    local_path_length_m: float = 1.5


@dataclass
class DwaResult:
    """Best twist, its trajectory (steps, 3) and per-critic scores; ``error`` when every sample is invalid."""

    twist: tuple[float, float, float]
    trajectory: np.ndarray
    scores: dict[str, float] = field(default_factory=dict)
    valid_samples: int = 0
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


def _axis(v: float, lo: float, hi: float, acc: float, dt: float, n: int) -> np.ndarray:
    a, b = max(lo, v - acc * dt), min(hi, v + acc * dt)
    if b < a:  # current velocity outside the box: head back into it
        a = b = min(max(v, lo), hi)
    vals = np.linspace(a, b, max(n, 1)) if n > 1 else np.array([(a + b) / 2])
    if a <= 0.0 <= b:
        vals = np.unique(np.concatenate([vals, [0.0]]))
    return vals


def nearest_points(ends: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Index (n,) of the first point of ``path`` (m, >= 2) nearest to each of ``ends`` (n, >= 2) in the plane and
    the squared distance (n,) to it; in ``_navops.c`` where it was built (same indices and bits)."""
    ends = np.ascontiguousarray(ends, dtype=np.float64)
    path = np.ascontiguousarray(path, dtype=np.float64)
    if _navops is not None and ends.ndim == path.ndim == 2 and len(path) and min(ends.shape[1], path.shape[1]) >= 2:
        raw_idx, raw_d2 = _navops.nearest_points(ends, path)
        return np.frombuffer(raw_idx, dtype=np.int64), np.frombuffer(raw_d2, dtype=np.float64)
    return nearest_points_numpy(ends, path)


def nearest_points_numpy(ends: np.ndarray, path: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``nearest_points`` in NumPy."""
    dx = ends[:, None, 0] - path[None, :, 0]
    dy = ends[:, None, 1] - path[None, :, 1]
    d2 = dx * dx + dy * dy
    nearest = np.argmin(d2, axis=1)
    return nearest, d2[np.arange(len(ends)), nearest]


class DwaPlanner:
    def __init__(self, config: DwaConfig, limits: TwistLimits, footprint: Footprint) -> None:
        self.config = config
        self.limits = limits
        self.footprint = footprint
        self._outline: np.ndarray | None = None if footprint.is_circle else footprint.outline(0.05)

    def samples(self, current: tuple[float, float, float]) -> np.ndarray:
        """(n, 3) twists in the dynamic window around ``current``."""
        c, lim = self.config, self.limits
        vx = _axis(current[0], lim.vx_min_mps, lim.vx_max_mps, lim.ax_max_mps2, c.window_dt_s, c.vx_samples)
        vy = _axis(current[1], -lim.vy_max_mps, lim.vy_max_mps, lim.ay_max_mps2, c.window_dt_s, c.vy_samples)
        wz = _axis(current[2], -lim.wz_max_radps, lim.wz_max_radps, lim.alpha_max_radps2, c.window_dt_s, c.wz_samples)
        g = np.stack(np.meshgrid(vx, vy, wz, indexing="ij"), axis=-1).reshape(-1, 3)
        return g

    def _per_wz(self, pose: tuple[float, float, float], twists: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """S(t), C(t) and theta(t) (u, steps) for each distinct wz of ``twists``, and the row (n,) of each twist:
        the trigonometry depends on wz only."""
        c = self.config
        t = np.linspace(c.sim_time_s / c.sim_steps, c.sim_time_s, c.sim_steps)[None, :]
        wz_u, inv = np.unique(twists[:, 2], return_inverse=True)
        wz = wz_u[:, None]
        th0 = pose[2]
        th_u = th0 + wz * t
        small = np.abs(wz) < 1e-6
        wz_safe = np.where(small, 1.0, wz)
        s_u = np.where(small, t * math.cos(th0), (np.sin(th_u) - math.sin(th0)) / wz_safe)
        c_u = np.where(small, t * math.sin(th0), (math.cos(th0) - np.cos(th_u)) / wz_safe)
        return s_u, c_u, th_u, inv.reshape(-1)

    def rollout(self, pose: tuple[float, float, float], twists: np.ndarray) -> np.ndarray:
        """Trajectories (n, steps, 3) of each twist held for sim_time from ``pose`` (exact SE(2) integration)."""
        s_u, c_u, th_u, inv = self._per_wz(pose, twists)
        s, cc, th = s_u[inv], c_u[inv], th_u[inv]
        vx, vy = twists[:, 0:1], twists[:, 1:2]
        x = pose[0] + vx * s - vy * cc
        y = pose[1] + vx * cc + vy * s
        return np.stack([x, y, th], axis=-1)

    def rollout_costs(self, costmap: Costmap2D, pose: tuple[float, float, float], twists: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
        """``rollout`` and the cost (n, steps) of the cell under each trajectory pose (``Costmap2D.cost_at``),
        in the C extension ``_navops.c`` where it was built (same bits, about 3x faster), else in NumPy."""
        twists = np.ascontiguousarray(twists, dtype=np.float64)
        if _navops is None or costmap.cost.ndim != 2 or costmap.cost.dtype != np.uint8:
            traj = self.rollout(pose, twists)
            return traj, costmap.cost_at(traj[..., 0], traj[..., 1])
        s_u, c_u, th_u, inv = self._per_wz(pose, twists)
        steps = s_u.shape[1]
        raw_traj, raw_cost = _navops.rollout_costs(
            np.ascontiguousarray(costmap.cost), float(costmap.origin_x), float(costmap.origin_y),
            float(costmap.resolution), NO_INFORMATION, float(pose[0]), float(pose[1]), twists,
            np.ascontiguousarray(inv, dtype=np.int64), np.ascontiguousarray(s_u), np.ascontiguousarray(c_u),
            np.ascontiguousarray(th_u))
        n = len(twists)
        return (np.frombuffer(raw_traj, dtype=np.float64).reshape(n, steps, 3),
                np.frombuffer(raw_cost, dtype=np.uint8).reshape(n, steps))

    def _obstacle_costs(self, costmap: Costmap2D, traj: np.ndarray, distance_m: np.ndarray | None = None,
                        centre_cost: np.ndarray | None = None) -> np.ndarray:
        """Max cost (n,) over each trajectory; >= 253 means a collision. ``centre_cost``: the cost under each pose
        of ``traj`` when already looked up.

        A polygon footprint is checked along its outline, but only at poses whose centre lies closer than the
        circumscribed radius to an obstacle (``distance_m``, the inflation layer's distance field, when given)."""
        if centre_cost is None:
            centre_cost = costmap.cost_at(traj[..., 0], traj[..., 1])
        centre = centre_cost.astype(np.int16)
        if self._outline is None:
            centre_worst: np.ndarray = centre.max(axis=1)
            return centre_worst
        centre = np.where(centre == INSCRIBED, MAX_NON_OBSTACLE, centre)  # inscribed is not a collision for a polygon
        if distance_m is not None and distance_m.shape == costmap.cost.shape:
            i, j = costmap.world_to_map(traj[..., 0], traj[..., 1])
            ok = costmap.in_bounds(i, j)
            d = np.zeros(i.shape, dtype=np.float32)
            d[ok] = distance_m[i[ok], j[ok]]
            near = d < self.footprint.circumscribed_radius_m + costmap.resolution
        else:
            near = np.ones(traj.shape[:2], dtype=bool)
        worst: np.ndarray = centre.max(axis=1)
        si, ki = np.nonzero(near)
        if len(si):
            poses = traj[si, ki]
            o = self._outline
            th = poses[:, 2:3]
            ox = poses[:, 0:1] + np.cos(th) * o[:, 0] - np.sin(th) * o[:, 1]
            oy = poses[:, 1:2] + np.sin(th) * o[:, 0] + np.cos(th) * o[:, 1]
            hit = costmap.cost_at(ox, oy).astype(np.int16).max(axis=1)
            hit = np.where(hit > INSCRIBED, hit, 0)
            np.maximum.at(worst, si, hit)
        return worst

    def plan(self, costmap: Costmap2D, pose: tuple[float, float, float], current: tuple[float, float, float],
             path: np.ndarray, goal: tuple[float, float, float], previous: tuple[float, float, float] | None = None,
             distance_m: np.ndarray | None = None) -> DwaResult:
        """Best twist towards the local part of ``path`` (m, m, rad rows, already pruned to start near the robot)."""
        c = self.config
        twists = self.samples(current)
        traj, centre_cost = self.rollout_costs(costmap, pose, twists)
        obstacle = self._obstacle_costs(costmap, traj, distance_m, centre_cost)
        valid = obstacle < INSCRIBED
        if int(costmap.cost_at(pose[0], pose[1])) == INSCRIBED and not valid.any():
            # escape: the robot already touches the inscribed zone; accept trajectories that leave it without
            # crossing a lethal or unknown cell
            end_cost = costmap.cost_at(traj[:, -1, 0], traj[:, -1, 1])
            valid = (obstacle <= INSCRIBED) & (end_cost < INSCRIBED)
            obstacle = np.minimum(obstacle, MAX_NON_OBSTACLE)
        end = traj[:, -1, :]
        if len(path) == 0:
            path = np.asarray([goal], dtype=float)
        # local path: up to local_path_length_m along the path
        seg = np.hypot(*np.diff(path[:, :2], axis=0).T) if len(path) > 1 else np.zeros(0)
        along = np.concatenate([[0.0], np.cumsum(seg)])
        local = path[along <= c.local_path_length_m]
        if len(local) == 0:
            local = path[:1]
        nearest, nearest_d2 = nearest_points(end, local)
        path_distance = np.sqrt(nearest_d2)
        path_alignment = np.abs(wrap_angle(end[:, 2] - local[nearest, 2]))
        # last pose of the path carries the goal heading; its direction of travel is the one before
        if len(local) == len(path) and len(path) > 1:
            path_alignment = np.where(nearest == len(local) - 1, np.abs(wrap_angle(end[:, 2] - local[-2, 2])),
                                      path_alignment)
        local_goal = local[-1]
        goal_distance = np.hypot(end[:, 0] - local_goal[0], end[:, 1] - local_goal[1])
        to_goal = math.hypot(pose[0] - goal[0], pose[1] - goal[1])
        if to_goal < c.goal_heading_activation_m:
            goal_heading = np.abs(wrap_angle(end[:, 2] - goal[2]))
            path_alignment = path_alignment * (to_goal / c.goal_heading_activation_m)
        else:
            goal_heading = np.zeros(len(end))
        if previous is not None:
            prev = np.asarray(previous)
            flips = (np.sign(twists) * np.sign(prev) < 0) & (np.abs(prev) > 1e-3)
            oscillation = flips.sum(axis=1).astype(float)
        else:
            oscillation = np.zeros(len(end))
        critics = {
            "obstacle": c.weight_obstacle * obstacle / MAX_NON_OBSTACLE,
            "path_distance": c.weight_path_distance * path_distance,
            "path_alignment": c.weight_path_alignment * path_alignment,
            "goal_distance": c.weight_goal_distance * goal_distance,
            "goal_heading": c.weight_goal_heading * goal_heading,
            "oscillation": c.weight_oscillation * oscillation,
        }
        total = sum(critics.values())
        n_valid = int(valid.sum())
        if n_valid == 0:
            return DwaResult((0.0, 0.0, 0.0), traj[0] if len(traj) else np.zeros((0, 3)), valid_samples=0,
                             error=f"no valid trajectory: all {len(twists)} samples collide within "
                                   f"{c.sim_time_s:.1f} s")
        total = np.where(valid, total, np.inf)
        best = int(np.argmin(total))
        vx, vy, wz = (float(v) for v in twists[best])
        return DwaResult((vx, vy, wz), traj[best],
                         {k: float(v[best]) for k, v in critics.items()}, valid_samples=n_valid)
