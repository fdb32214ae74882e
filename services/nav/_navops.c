/* nav's per-cycle grid work in C, where NumPy's temporaries and gathers were most of the nav process's time: the
 * DWA's trajectory rollout, centre-cell costs and nearest path points (services/nav/dwa.py: ~2200 twists x 17 steps
 * at 20 Hz) and the obstacle layer's ray clearing and marking (services/nav/costmap.py: every beam, every half cell,
 * into two costmaps at 5 Hz). Each does the floating-point operations of the NumPy code it replaces, in the same
 * order (built without fused multiply-add), so both give the same bits; trigonometry is computed by NumPy and
 * passed in.
 *
 * rollout_costs(cost, origin_x, origin_y, resolution, outside, x0, y0, twists, inv, s_u, c_u, th_u)
 *     -> (bytearray of n x steps x 3 float64 poses, bytearray of n x steps uint8 costs)
 *
 *   twists: float64 (n, 3); inv: int64 (n), the row of each twist's wz in the per-wz tables s_u, c_u, th_u (float64
 *   (u, steps), computed by dwa.py: S(t), C(t) and theta(t) of the exact SE(2) integration). Pose of twist k at
 *   step m: x = (x0 + vx S) - vy C, y = (y0 + vx C) + vy S, theta = theta(t), the same operations in the same
 *   order as dwa.py's NumPy (built without fused multiply-add), so both give the same bits. Its cost is the cell
 *   (floor((y - oy) / res), floor((x - ox) / res)) of ``cost`` (uint8 (h, w)), ``outside`` off the grid or for a
 *   non-finite pose (Costmap2D.cost_at).
 *
 * nearest_points(ends, path) -> (bytearray of n int64, bytearray of n float64)
 *
 *   For each trajectory end (float64 (n, >= 2)) the first path point (float64 (m, >= 2)) nearest to it in the
 *   plane and the squared distance dx^2 + dy^2 to it (np.argmin over the same d2, so the same index and bits).
 *
 * raytrace(grid, gx, gy, res, ox, oy, cos, sin, clear_len, n_steps, step, mark_x, mark_y, free_value, mark_value)
 *
 *   In place on grid (uint8 (h, w), cell (0, 0) at (gx, gy)): for each ray b (float64 (n) each) the samples
 *   t = k step, k < n_steps, with t < clear_len_b - res / 2, at ox_b + min(t, clear_len_b) (cos_b, sin_b), set
 *   their cells to free_value; then the cells of the points (mark_x, mark_y) (float64 (m) each) to mark_value.
 *   Points off the grid are skipped.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "_pybuffer.h"

#include <math.h>
#include <stdint.h>
#include <string.h>

static PyObject *rollout_costs(PyObject *self, PyObject *args) {
    PyObject *cost_obj, *twists_obj, *inv_obj, *s_obj, *c_obj, *th_obj;
    double ox, oy, res, x0, y0;
    int outside;
    if (!PyArg_ParseTuple(args, "OdddiddOOOOO", &cost_obj, &ox, &oy, &res, &outside, &x0, &y0, &twists_obj,
                          &inv_obj, &s_obj, &c_obj, &th_obj)) {
        return NULL;
    }
    Py_buffer cost, twists, inv, su, cu, thu;
    PyObject *traj_out = NULL, *cost_out = NULL;
    if (get_buffer(cost_obj, &cost, 2, 1, NULL, "cost") < 0) {
        return NULL;
    }
    if (get_buffer(twists_obj, &twists, 2, 8, "d", "twists") < 0) {
        goto release_cost;
    }
    if (get_buffer(inv_obj, &inv, 1, 8, NULL, "inv (int64)") < 0) {
        goto release_twists;
    }
    if (get_buffer(s_obj, &su, 2, 8, "d", "s_u") < 0) {
        goto release_inv;
    }
    if (get_buffer(c_obj, &cu, 2, 8, "d", "c_u") < 0) {
        goto release_su;
    }
    if (get_buffer(th_obj, &thu, 2, 8, "d", "th_u") < 0) {
        goto release_cu;
    }
    Py_ssize_t n = twists.shape[0], u = su.shape[0], steps = su.shape[1], h = cost.shape[0], w = cost.shape[1];
    if (twists.shape[1] != 3 || inv.shape[0] != n || cu.shape[0] != u || cu.shape[1] != steps ||
        thu.shape[0] != u || thu.shape[1] != steps) {
        PyErr_SetString(PyExc_ValueError, "rollout_costs: twists (n, 3), inv (n), s_u, c_u and th_u (u, steps)");
        goto release_all;
    }
    const int64_t *row = inv.buf;
    for (Py_ssize_t k = 0; k < n; k++) {
        if (row[k] < 0 || row[k] >= u) {
            PyErr_SetString(PyExc_ValueError, "rollout_costs: inv indexes past the per-wz tables");
            goto release_all;
        }
    }
    traj_out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * steps * 3 * sizeof(double)));
    cost_out = PyByteArray_FromStringAndSize(NULL, n * steps);
    if (!traj_out || !cost_out) {
        Py_CLEAR(traj_out);
        Py_CLEAR(cost_out);
        goto release_all;
    }
    const double *tw = twists.buf, *s = su.buf, *c = cu.buf, *th = thu.buf;
    const uint8_t *grid = cost.buf;
    double *traj = (double *)PyByteArray_AS_STRING(traj_out);
    uint8_t *out = (uint8_t *)PyByteArray_AS_STRING(cost_out);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < n; k++) {
        double vx = tw[3 * k], vy = tw[3 * k + 1];
        Py_ssize_t base = row[k] * steps;
        for (Py_ssize_t m = 0; m < steps; m++) {
            double sm = s[base + m], cm = c[base + m];
            double x = (x0 + vx * sm) - vy * cm, y = (y0 + vx * cm) + vy * sm;
            double *pose = traj + 3 * (k * steps + m);
            pose[0] = x;
            pose[1] = y;
            pose[2] = th[base + m];
            double fj = floor((x - ox) / res), fi = floor((y - oy) / res);
            out[k * steps + m] = (fi >= 0.0 && fi < (double)h && fj >= 0.0 && fj < (double)w)
                                     ? grid[(Py_ssize_t)fi * w + (Py_ssize_t)fj]
                                     : (uint8_t)outside;
        }
    }
    Py_END_ALLOW_THREADS
release_all:
    PyBuffer_Release(&thu);
release_cu:
    PyBuffer_Release(&cu);
release_su:
    PyBuffer_Release(&su);
release_inv:
    PyBuffer_Release(&inv);
release_twists:
    PyBuffer_Release(&twists);
release_cost:
    PyBuffer_Release(&cost);
    if (!traj_out) {
        return NULL;
    }
    return Py_BuildValue("(NN)", traj_out, cost_out);
}

static PyObject *nearest_points(PyObject *self, PyObject *args) {
    PyObject *ends_obj, *path_obj;
    if (!PyArg_ParseTuple(args, "OO", &ends_obj, &path_obj)) {
        return NULL;
    }
    Py_buffer ends, path;
    if (get_buffer(ends_obj, &ends, 2, 8, "d", "ends") < 0) {
        return NULL;
    }
    if (get_buffer(path_obj, &path, 2, 8, "d", "path") < 0) {
        PyBuffer_Release(&ends);
        return NULL;
    }
    Py_ssize_t n = ends.shape[0], m = path.shape[0], ce = ends.shape[1], cp = path.shape[1];
    PyObject *idx_out = NULL, *d2_out = NULL;
    if (ce < 2 || cp < 2 || m < 1) {
        PyErr_SetString(PyExc_ValueError, "nearest_points: ends (n, >= 2) and a path (m >= 1, >= 2)");
        goto done;
    }
    idx_out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * sizeof(int64_t)));
    d2_out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(n * sizeof(double)));
    if (!idx_out || !d2_out) {
        Py_CLEAR(idx_out);
        Py_CLEAR(d2_out);
        goto done;
    }
    const double *e = ends.buf, *p = path.buf;
    int64_t *idx = (int64_t *)PyByteArray_AS_STRING(idx_out);
    double *best = (double *)PyByteArray_AS_STRING(d2_out);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < n; k++) {
        double ex = e[k * ce], ey = e[k * ce + 1], b = 0.0;
        int64_t bi = -1;
        for (Py_ssize_t j = 0; j < m; j++) {
            double dx = ex - p[j * cp], dy = ey - p[j * cp + 1];
            double d2 = dx * dx + dy * dy;
            if (bi < 0 || d2 < b || (isnan(d2) && !isnan(b))) { /* the first minimum; NaN wins, as in argmin */
                b = d2;
                bi = j;
            }
        }
        idx[k] = bi;
        best[k] = b;
    }
    Py_END_ALLOW_THREADS
done:
    PyBuffer_Release(&ends);
    PyBuffer_Release(&path);
    if (!idx_out) {
        return NULL;
    }
    return Py_BuildValue("(NN)", idx_out, d2_out);
}

static PyObject *raytrace(PyObject *self, PyObject *args) {
    PyObject *grid_obj, *ox_obj, *oy_obj, *cos_obj, *sin_obj, *len_obj, *mx_obj, *my_obj;
    double gx, gy, res, step;
    Py_ssize_t n_steps;
    int free_value, mark_value;
    if (!PyArg_ParseTuple(args, "OdddOOOOOndOOii", &grid_obj, &gx, &gy, &res, &ox_obj, &oy_obj, &cos_obj, &sin_obj,
                          &len_obj, &n_steps, &step, &mx_obj, &my_obj, &free_value, &mark_value)) {
        return NULL;
    }
    Py_buffer grid, bufs[7];
    PyObject *objs[7] = {ox_obj, oy_obj, cos_obj, sin_obj, len_obj, mx_obj, my_obj};
    const char *names[7] = {"ox", "oy", "cos", "sin", "clear_len", "mark_x", "mark_y"};
    if (PyObject_GetBuffer(grid_obj, &grid, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND | PyBUF_WRITABLE) < 0) {
        return NULL;
    }
    if (grid.ndim != 2 || grid.itemsize != 1) {
        PyBuffer_Release(&grid);
        PyErr_SetString(PyExc_ValueError, "raytrace: grid must be a writable C-contiguous 2-D uint8 array");
        return NULL;
    }
    int got = 0;
    for (; got < 7; got++) {
        if (get_buffer(objs[got], &bufs[got], 1, 8, "d", names[got]) < 0) {
            break;
        }
    }
    int ok = got == 7;
    Py_ssize_t n = ok ? bufs[0].shape[0] : 0, m = ok ? bufs[5].shape[0] : 0;
    if (ok && (bufs[1].shape[0] != n || bufs[2].shape[0] != n || bufs[3].shape[0] != n || bufs[4].shape[0] != n ||
               bufs[6].shape[0] != m || n_steps < 0)) {
        PyErr_SetString(PyExc_ValueError, "raytrace: ox, oy, cos, sin and clear_len of one length, mark_x and mark_y "
                                          "of another, n_steps >= 0");
        ok = 0;
    }
    if (ok) {
        const double *ox = bufs[0].buf, *oy = bufs[1].buf, *ca = bufs[2].buf, *sa = bufs[3].buf;
        const double *cl = bufs[4].buf, *mx = bufs[5].buf, *my = bufs[6].buf;
        uint8_t *g = grid.buf;
        Py_ssize_t h = grid.shape[0], w = grid.shape[1];
        Py_BEGIN_ALLOW_THREADS
        for (Py_ssize_t b = 0; b < n; b++) {
            double stop = cl[b] - 0.5 * res;
            for (Py_ssize_t k = 0; k < n_steps; k++) {
                double t = (double)k * step;
                if (!(t < stop)) {
                    break; /* t grows with k: no later sample of this ray is valid either */
                }
                double d = t < cl[b] ? t : cl[b];
                double fj = floor(((ox[b] + d * ca[b]) - gx) / res), fi = floor(((oy[b] + d * sa[b]) - gy) / res);
                if (fi >= 0.0 && fi < (double)h && fj >= 0.0 && fj < (double)w) {
                    g[(Py_ssize_t)fi * w + (Py_ssize_t)fj] = (uint8_t)free_value;
                }
            }
        }
        for (Py_ssize_t k = 0; k < m; k++) {
            double fj = floor((mx[k] - gx) / res), fi = floor((my[k] - gy) / res);
            if (fi >= 0.0 && fi < (double)h && fj >= 0.0 && fj < (double)w) {
                g[(Py_ssize_t)fi * w + (Py_ssize_t)fj] = (uint8_t)mark_value;
            }
        }
        Py_END_ALLOW_THREADS
    }
    for (int k = 0; k < got; k++) {
        PyBuffer_Release(&bufs[k]);
    }
    PyBuffer_Release(&grid);
    if (!ok) {
        return NULL;
    }
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"rollout_costs", rollout_costs, METH_VARARGS,
     "rollout_costs(cost, origin_x, origin_y, resolution, outside, x0, y0, twists, inv, s_u, c_u, th_u) -> "
     "(bytearray of float64 poses, bytearray of uint8 costs)"},
    {"raytrace", raytrace, METH_VARARGS,
     "raytrace(grid, origin_x, origin_y, resolution, ox, oy, cos, sin, clear_len, n_steps, step, mark_x, mark_y, "
     "free_value, mark_value) -> None: clears the rays' cells, then marks the endpoints' (in place)"},
    {"nearest_points", nearest_points, METH_VARARGS,
     "nearest_points(ends, path) -> (bytearray of int64 indices, bytearray of float64 squared distances)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_navops", NULL, -1, methods};

PyMODINIT_FUNC PyInit__navops(void) { return PyModule_Create(&module); }
