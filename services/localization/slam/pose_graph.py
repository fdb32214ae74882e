"""Pose graph of SE(2) keyframes optimised by sparse Gauss-Newton / Levenberg-Marquardt.

Edge (i, j, z, Ω) measures node j in the frame of node i. Error (Grisetti et al. 2010, "A tutorial on
graph-based SLAM"):  e = t2v(Z⁻¹ (Xᵢ⁻¹ Xⱼ)), i.e.
    e_t = R_zᵀ (R_iᵀ (t_j − t_i) − t_z),   e_θ = wrap(θ_j − θ_i − θ_z)
with Jacobians A = ∂e/∂x_i = [[−R_zᵀR_iᵀ, R_zᵀ dR_iᵀ/dθ (t_j − t_i)], [0, 0, −1]] and
B = ∂e/∂x_j = [[R_zᵀR_iᵀ, 0], [0, 0, 1]]. Robust edges are down-weighted by the Cauchy kernel
w = 1 / (1 + χ²/c²), χ² = eᵀΩe. An edge can be switched off (a loop closure found false); the optimiser
ignores it. The first node is held fixed.
"""

from __future__ import annotations

import numpy as np

from services.common.se2 import wrap_angle


class PoseGraph:
    """Nodes (x, y, theta) and relative-pose edges; ``optimize`` updates the node poses in place."""

    def __init__(self) -> None:
        self._poses: list[np.ndarray] = []
        self._edges_i: list[int] = []
        self._edges_j: list[int] = []
        self._edges_z: list[np.ndarray] = []
        self._edges_info: list[np.ndarray] = []
        self._edges_robust: list[float] = []
        self._edges_active: list[bool] = []

    @property
    def n_nodes(self) -> int:
        return len(self._poses)

    @property
    def n_edges(self) -> int:
        return len(self._edges_i)

    def add_node(self, pose: np.ndarray) -> int:
        self._poses.append(np.asarray(pose, float).copy())
        return len(self._poses) - 1

    def pose(self, i: int) -> np.ndarray:
        return self._poses[i]

    def poses(self) -> np.ndarray:
        return np.array(self._poses).reshape(-1, 3)

    def set_poses(self, poses: np.ndarray) -> None:
        self._poses = [p.copy() for p in np.asarray(poses, float)]

    def add_edge(self, i: int, j: int, measurement: np.ndarray, information: np.ndarray, *,
                 robust_scale: float = 0.0) -> int:
        """Constraint x_j seen from x_i = ``measurement``; ``robust_scale`` > 0 applies the Cauchy kernel.
        Returns the edge's index."""
        if not (0 <= i < self.n_nodes and 0 <= j < self.n_nodes) or i == j:
            raise ValueError(f"edge ({i}, {j}) needs two distinct existing nodes (have {self.n_nodes})")
        self._edges_i.append(i)
        self._edges_j.append(j)
        self._edges_z.append(np.asarray(measurement, float).copy())
        self._edges_info.append(np.asarray(information, float).copy())
        self._edges_robust.append(float(robust_scale))
        self._edges_active.append(True)
        return self.n_edges - 1

    def set_active(self, edge: int, active: bool) -> None:
        """Switch edge ``edge`` on or off (an inactive edge does not take part in ``optimize`` or ``chi2``)."""
        self._edges_active[edge] = bool(active)

    def is_active(self, edge: int) -> bool:
        return self._edges_active[edge]

    def edge_chi2(self, edges: list[int] | np.ndarray, poses: np.ndarray | None = None) -> np.ndarray:
        """eᵀΩe of the given edges at ``poses`` (default: current), without robust weighting."""
        err = self.edge_errors(poses)[np.asarray(edges, dtype=np.intp)]
        info = np.asarray(self._edges_info).reshape(-1, 3, 3)[np.asarray(edges, dtype=np.intp)]
        chi2: np.ndarray = np.einsum("ni,nij,nj->n", err, info, err)
        return chi2

    def edge_errors(self, poses: np.ndarray | None = None) -> np.ndarray:
        """Error vectors e (E, 3) of every edge at ``poses`` (default: current)."""
        x = self.poses() if poses is None else poses
        return self._linearize(x)[0]

    def _linearize(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        i = np.asarray(self._edges_i)
        j = np.asarray(self._edges_j)
        z = np.asarray(self._edges_z).reshape(-1, 3)
        xi, xj = x[i], x[j]
        ci, si = np.cos(xi[:, 2]), np.sin(xi[:, 2])
        cz, sz = np.cos(z[:, 2]), np.sin(z[:, 2])
        dx = xj[:, 0] - xi[:, 0]
        dy = xj[:, 1] - xi[:, 1]
        # t_ij = R_i^T (t_j - t_i)
        tx = ci * dx + si * dy
        ty = -si * dx + ci * dy
        ex = cz * (tx - z[:, 0]) + sz * (ty - z[:, 1])
        ey = -sz * (tx - z[:, 0]) + cz * (ty - z[:, 1])
        eth = wrap_angle(xj[:, 2] - xi[:, 2] - z[:, 2])
        err = np.stack([ex, ey, eth], axis=1)
        n = len(i)
        # R_z^T R_i^T = rotation by -(theta_i + theta_z)
        c, s = np.cos(xi[:, 2] + z[:, 2]), np.sin(xi[:, 2] + z[:, 2])
        rot = np.empty((n, 2, 2))
        rot[:, 0, 0], rot[:, 0, 1], rot[:, 1, 0], rot[:, 1, 1] = c, s, -s, c
        # d(R_i^T)/dtheta (t_j - t_i) = (-s_i dx + c_i dy, -c_i dx - s_i dy) = (ty, -tx)
        dvec = np.stack([ty, -tx], axis=1)
        rz_t = np.empty((n, 2, 2))
        rz_t[:, 0, 0], rz_t[:, 0, 1], rz_t[:, 1, 0], rz_t[:, 1, 1] = cz, sz, -sz, cz
        a = np.zeros((n, 3, 3))
        b = np.zeros((n, 3, 3))
        a[:, :2, :2] = -rot
        a[:, :2, 2] = np.einsum("nij,nj->ni", rz_t, dvec)
        a[:, 2, 2] = -1.0
        b[:, :2, :2] = rot
        b[:, 2, 2] = 1.0
        return err, a, b

    def chi2(self, poses: np.ndarray | None = None) -> float:
        """Σ eᵀΩe over all edges (without robust weighting)."""
        err = self.edge_errors(poses)
        info = np.asarray(self._edges_info).reshape(-1, 3, 3)
        active = np.asarray(self._edges_active, bool)
        return float(np.einsum("ni,nij,nj->", err[active], info[active], err[active]))

    def optimize(self, iterations: int = 20, *, tolerance: float = 1e-6, damping: float = 1e-6) -> int:
        """Sparse Gauss-Newton with a small Levenberg damping; returns the number of iterations run."""
        if self.n_edges == 0 or self.n_nodes < 2:
            return 0
        # imported here: scipy.sparse (and the scipy.linalg it loads) is about 10 MB resident, and the localization
        # service loads this module in navigation mode too, where no graph is ever optimised
        import scipy.sparse as sp
        from scipy.sparse.linalg import spsolve

        x = self.poses()
        n = len(x)
        i = np.asarray(self._edges_i)
        j = np.asarray(self._edges_j)
        info = np.asarray(self._edges_info).reshape(-1, 3, 3)
        robust = np.asarray(self._edges_robust)
        info = info * np.asarray(self._edges_active, float)[:, None, None]
        idx3 = np.arange(3)
        done = 0
        for done in range(1, iterations + 1):  # noqa: B007 (returned)
            err, a, b = self._linearize(x)
            chi2 = np.einsum("ni,nij,nj->n", err, info, err)
            weight = np.ones(len(err))
            has_kernel = robust > 0
            weight[has_kernel] = 1.0 / (1.0 + chi2[has_kernel] / robust[has_kernel] ** 2)
            omega = info * weight[:, None, None]
            blocks = {
                (0, 0): np.einsum("nki,nkl,nlj->nij", a, omega, a),
                (0, 1): np.einsum("nki,nkl,nlj->nij", a, omega, b),
                (1, 1): np.einsum("nki,nkl,nlj->nij", b, omega, b),
            }
            blocks[(1, 0)] = np.transpose(blocks[(0, 1)], (0, 2, 1))
            nodes = (i, j)
            rows, cols, vals = [], [], []
            for (p, q), block in blocks.items():
                r = 3 * nodes[p][:, None, None] + idx3[None, :, None]
                c = 3 * nodes[q][:, None, None] + idx3[None, None, :]
                rows.append(np.broadcast_to(r, block.shape).ravel())
                cols.append(np.broadcast_to(c, block.shape).ravel())
                vals.append(block.ravel())
            # anchor the first node and damp the diagonal
            rows.append(np.arange(3 * n))
            cols.append(np.arange(3 * n))
            diag = np.full(3 * n, damping)
            diag[:3] += 1e12
            vals.append(diag)
            hessian = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                                    shape=(3 * n, 3 * n))
            ga = np.einsum("nki,nkl,nl->ni", a, omega, err)
            gb = np.einsum("nki,nkl,nl->ni", b, omega, err)
            gradient = np.zeros(3 * n)
            np.add.at(gradient, (3 * i[:, None] + idx3).ravel(), ga.ravel())
            np.add.at(gradient, (3 * j[:, None] + idx3).ravel(), gb.ravel())
            step = spsolve(hessian, -gradient).reshape(n, 3)
            x = x + step
            x[:, 2] = wrap_angle(x[:, 2])
            if np.abs(step).max() < tolerance:
                break
        self.set_poses(x)
        return done
