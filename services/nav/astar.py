"""Cost-aware 8-connected A* on a costmap, with clearance-keeping smoothing.

Search: a step from cell a to neighbour b costs ``step_m * (1 + cost_weight * c(b) / 252)`` where step_m is the
resolution (straight) or sqrt(2) times it (diagonal) and c(b) the planning cost of b; cells >= 253 (inscribed,
lethal) are impassable, 255 (unknown) too unless ``allow_unknown``. The octile distance in m is admissible and
consistent because every step costs at least its length. Ties on f break towards the larger g (nearer the goal),
then towards the lower cell index, so equal inputs give equal paths.

A start inside the inscribed zone (a robot that was pushed near a wall) may move through inscribed cells, but only
those connected to the start through inscribed cells: it can leave, never enter.

Implementation (measured with ``zagv bench --only astar``, docs/performance.md): the search loop is a small C
extension, ``services/nav/_astar.c``, built by setuptools at install. It does the same arithmetic in the same order
and orders its heap like ``heapq`` on ``(key, cell)``, so it expands the same cells and returns the same path as the
pure-Python loop (``AStarPlanner(compiled=False)``), which stays as the reference the tests compare against and as
the fallback where the extension could not be built (a warning says so).
"""

from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass

import numpy as np

from services.common import gridops
from services.nav.costmap import INSCRIBED, LETHAL, MAX_NON_OBSTACLE, NO_INFORMATION, Costmap2D

try:
    import services.nav._astar as _astar
except ImportError as exc:  # no C compiler at install: the pure-Python loop, same paths, ~15x slower
    _astar = None
    logging.getLogger(__name__).warning("A* runs its pure-Python loop: the compiled search is not built (%s)", exc)

SQRT2 = math.sqrt(2.0)
#: heap key f - TIE_BREAK * g: equal f expands the larger g first; costs at most a relative 1e-9 of optimality
TIE_BREAK = 1e-9


@dataclass
class PlanResult:
    """Cells (n, 2) as (i, j) from start to goal, cost in m-equivalent; ``error`` says why when empty."""

    cells: np.ndarray
    cost: float = 0.0
    expanded: int = 0
    error: str = ""

    @property
    def ok(self) -> bool:
        return not self.error


@dataclass
class AStarPlanner:
    """``cost_weight`` scales how much a cell's cost adds to its length (Smac's cost_travel_multiplier);
    ``compiled`` picks the C search loop when it is built (False: the pure-Python reference loop)."""

    cost_weight: float = 3.0
    allow_unknown: bool = False
    compiled: bool = True

    def __post_init__(self) -> None:
        if not (math.isfinite(self.cost_weight) and self.cost_weight >= 0.0):
            raise ValueError(f"cost_weight must be a finite number >= 0 (a cell's cost may only lengthen a step), "
                             f"got {self.cost_weight!r}")

    @property
    def uses_compiled(self) -> bool:
        return self.compiled and _astar is not None

    def plan(self, cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], resolution: float = 1.0
             ) -> PlanResult:
        h, w = cost.shape
        si, sj = start
        gi, gj = goal
        empty = np.zeros((0, 2), dtype=np.int64)
        if not (0 <= si < h and 0 <= sj < w):
            return PlanResult(empty, error=f"start cell ({si}, {sj}) is outside the {h}x{w} costmap")
        if not (0 <= gi < h and 0 <= gj < w):
            return PlanResult(empty, error=f"goal cell ({gi}, {gj}) is outside the {h}x{w} costmap")
        sc, gc = int(cost[si, sj]), int(cost[gi, gj])
        if sc == LETHAL:
            return PlanResult(empty, error="start is inside an obstacle (lethal cell)")
        if gc == LETHAL:
            return PlanResult(empty, error="goal is inside an obstacle (lethal cell)")
        if gc == INSCRIBED:
            return PlanResult(empty, error="goal is too close to an obstacle for the robot (inscribed cell)")
        if gc == NO_INFORMATION and not self.allow_unknown:
            return PlanResult(empty, error="goal is in unknown space (allow_unknown is off)")

        if self.uses_compiled:
            return self._plan_compiled(cost, start, goal, resolution)
        return self._plan_python(cost, start, goal, resolution)

    def _escape(self, cost: np.ndarray, start: tuple[int, int]) -> np.ndarray:
        """The inscribed cells 8-connected to the start's inscribed cell (which the search may leave through)."""
        labels, _ = gridops.label(cost == INSCRIBED)
        escape: np.ndarray = labels == labels[start]
        return escape

    def _plan_compiled(self, cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], resolution: float
                       ) -> PlanResult:
        h, w = cost.shape
        escape = None
        if cost[start] == INSCRIBED:
            escape = np.ascontiguousarray(self._escape(cost, start), dtype=np.uint8)
        cells, g_goal, expanded = _astar.plan(np.ascontiguousarray(cost, dtype=np.uint8), h, w,
                                              (int(start[0]), int(start[1])), (int(goal[0]), int(goal[1])),
                                              float(self.cost_weight), bool(self.allow_unknown), escape)
        if cells is None:
            return PlanResult(np.zeros((0, 2), dtype=np.int64), expanded=expanded,
                              error=f"no path: the goal is not reachable from the start ({expanded} cells searched)")
        return PlanResult(np.frombuffer(cells, dtype=np.int64).reshape(-1, 2).copy(), cost=g_goal * resolution,
                          expanded=expanded)

    def _plan_python(self, cost: np.ndarray, start: tuple[int, int], goal: tuple[int, int], resolution: float
                     ) -> PlanResult:
        """The reference loop in plain Python over flat lists (same result as the compiled loop)."""
        h, w = cost.shape
        si, sj = start
        gi, gj = goal
        empty = np.zeros((0, 2), dtype=np.int64)
        W = w + 2  # padded width
        # padded grid with a lethal border; blocked cells start out closed, so the loop needs one test per neighbour
        padded = np.full((h + 2, w + 2), LETHAL, dtype=np.uint8)
        padded[1:-1, 1:-1] = cost
        mult = 1.0 + self.cost_weight * np.minimum(padded, MAX_NON_OBSTACLE).astype(np.float64) / MAX_NON_OBSTACLE
        blocked = padded >= INSCRIBED
        if self.allow_unknown:
            blocked &= padded != NO_INFORMATION
        if padded[si + 1, sj + 1] == INSCRIBED:
            # escape: the inscribed cells connected to the start are passable (at the highest cost)
            escape = np.zeros(padded.shape, dtype=bool)
            escape[1:-1, 1:-1] = self._escape(cost, (si, sj))
            blocked &= ~escape
            mult[escape] = 1.0 + self.cost_weight
        m = mult.ravel().tolist()
        closed = bytearray(blocked.ravel().tobytes())
        start_n = (si + 1) * W + (sj + 1)
        goal_n = (gi + 1) * W + (gj + 1)
        n_cells = len(m)
        g = [math.inf] * n_cells
        parent = [-1] * n_cells
        g[start_n] = 0.0
        gx, gy = gj + 1, gi + 1
        offsets = ((1, 1.0), (-1, 1.0), (W, 1.0), (-W, 1.0), (W + 1, SQRT2), (W - 1, SQRT2), (-W + 1, SQRT2),
                   (-W - 1, SQRT2))
        k = SQRT2 - 2.0
        eps = TIE_BREAK
        heap = [(0.0, start_n)]
        expanded = 0
        push, pop = heapq.heappush, heapq.heappop
        while heap:
            _, n = pop(heap)
            if closed[n]:
                continue
            closed[n] = 1
            expanded += 1
            if n == goal_n:
                break
            gn = g[n]
            for off, step in offsets:
                nb = n + off
                if closed[nb]:
                    continue
                ng = gn + step * m[nb]
                if ng < g[nb]:
                    g[nb] = ng
                    parent[nb] = n
                    y, x = divmod(nb, W)
                    dx = x - gx
                    dy = y - gy
                    if dx < 0:
                        dx = -dx
                    if dy < 0:
                        dy = -dy
                    push(heap, (ng + dx + dy + k * (dx if dx < dy else dy) - eps * ng, nb))
        if g[goal_n] == math.inf or not closed[goal_n]:
            return PlanResult(empty, expanded=expanded,
                              error=f"no path: the goal is not reachable from the start ({expanded} cells searched)")
        cells = []
        n = goal_n
        while n != -1:
            cells.append((n // W - 1, n % W - 1))
            n = parent[n]
        cells.reverse()
        return PlanResult(np.asarray(cells, dtype=np.int64), cost=g[goal_n] * resolution, expanded=expanded)


def line_cells(i0: int, j0: int, i1: int, j1: int) -> tuple[np.ndarray, np.ndarray]:
    """Cells on the segment between two cell centres (supercover-ish sampling at 1/3 cell)."""
    n = int(max(abs(i1 - i0), abs(j1 - j0)) * 3) + 1
    t = np.linspace(0.0, 1.0, n + 1)
    ii = np.rint(i0 + t * (i1 - i0)).astype(np.int64)
    jj = np.rint(j0 + t * (j1 - j0)).astype(np.int64)
    return ii, jj


def smooth_cells(cost: np.ndarray, cells: np.ndarray, max_segment_cells: int = 60) -> np.ndarray:
    """Shortcut a cell path with straight segments that never cross a cell costlier than the worst cell of the
    stretch of path they replace (so clearance never shrinks); segments at most ``max_segment_cells`` long."""
    if len(cells) <= 2:
        return cells
    c = cost[cells[:, 0], cells[:, 1]].astype(np.int64)
    out = [cells[0]]
    a = 0
    n = len(cells)
    while a < n - 1:
        best = a + 1
        worst = int(c[a])
        hi = min(n - 1, a + max_segment_cells)
        for b in range(a + 1, hi + 1):
            worst = max(worst, int(c[b]))
            ii, jj = line_cells(int(cells[a, 0]), int(cells[a, 1]), int(cells[b, 0]), int(cells[b, 1]))
            if int(cost[ii, jj].max()) <= worst:
                best = b
        out.append(cells[best])
        a = best
    return np.asarray(out)


def cells_to_path(costmap: Costmap2D, cells: np.ndarray, start_xy: tuple[float, float], goal_pose: tuple[float,
                  float, float], spacing_m: float = 0.05) -> np.ndarray:
    """Poses (n, 3) in m / rad: start point, cell centres, then the exact goal, resampled every ``spacing_m``;
    theta is the direction of travel, the goal's own heading on the last pose."""
    x, y = costmap.map_to_world(cells[:, 0], cells[:, 1])
    pts = np.column_stack([x, y]).astype(np.float64)
    if len(pts) >= 1:
        pts[0] = start_xy
        pts[-1] = goal_pose[:2]
    else:
        pts = np.array([start_xy, goal_pose[:2]], dtype=np.float64)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    keep = np.concatenate([[True], seg > 1e-9])
    pts = pts[keep]
    if len(pts) < 2:
        return np.array([[goal_pose[0], goal_pose[1], goal_pose[2]]])
    seg = np.hypot(*np.diff(pts, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    n = max(2, int(math.ceil(s[-1] / spacing_m)) + 1)
    si = np.linspace(0.0, s[-1], n)
    px = np.interp(si, s, pts[:, 0])
    py = np.interp(si, s, pts[:, 1])
    th = np.arctan2(np.diff(py), np.diff(px))
    th = np.concatenate([th, [goal_pose[2]]])
    return np.column_stack([px, py, th])


def planning_cost(costmap: Costmap2D, distance_m: np.ndarray | None, inscribed_radius_m: float, clearance_m: float
                  ) -> np.ndarray:
    """The costmap plus a clearance preference: cells within ``clearance_m`` beyond the inscribed radius get a
    cost rising linearly to 252 towards the inscribed edge (max with the costmap's own cost). With the paper's
    inflation radius only 15 mm larger than the robot, this keeps planned paths off walls and corners.

    Always a new array: the search runs on a worker thread while the loop updates the costmap in place, so a view
    of the live grid would let the start cell's cost change between the planner's checks and its search (a start
    read as free, then inflated: closed before the first expansion, "no path (0 cells searched)")."""
    cost = costmap.cost
    if distance_m is None or clearance_m <= 0:
        return cost.copy()
    d = distance_m - inscribed_radius_m
    extra = np.zeros(cost.shape, dtype=np.uint8)
    band = (d > 0) & (d < clearance_m)
    extra[band] = (MAX_NON_OBSTACLE * (1.0 - d[band] / clearance_m) ** 2).astype(np.uint8)
    out = cost.copy()
    free = cost < INSCRIBED
    out[free] = np.maximum(cost[free], extra[free])
    return out
