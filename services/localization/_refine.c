/* The scan log-likelihood of services/localization/refine.py in C: the refinement at rest scores every beam of a
 * dense scan at every candidate of a 7 x 7 x 7 grid, five times over (about 10^6 beam endpoints); in NumPy that is
 * about a quarter of a second on the event loop, here about 50 ms (the exp and log of each beam dominate).
 *
 * log_likelihood(distance, occupied, ox, oy, oyaw, resolution, z_hit, rand_density, two_sigma_sq, max_dist,
 *                poses, ranges, bearings, mx, my, mth, clearance) -> bytearray of k float64
 *
 *   distance: C-contiguous float64 (h, w) field per cell corner; occupied: uint8 cells or None; poses: float64
 *   (k, 3); ranges, bearings: float64 (n). For each pose q = (x, y, th) the laser sits at q o (mx, my, mth) and
 *   beam b ends at l + r_b (cos g, sin g), g = th + mth + bearing_b. Its distance d_b is the bilinear interpolation
 *   of the field at the endpoint (beyond the corners: the nearest edge value plus the distance to it, at most
 *   max_dist); a beam whose points r_b - (clearance + resolution (0, 1/2, 1, 3/2)) (not below 0) fall in an
 *   occupied cell scores d_b = max_dist. The result is sum_b log(max(z_hit exp(-d_b^2 / two_sigma_sq) +
 *   rand_density, 1e-300)).
 *
 *   The arithmetic is refine.py's, except that cos g and sin g come from the angle-sum identities on cos/sin of
 *   (th + mth) and of the bearing, and the sum runs in beam order: results agree with NumPy's to about 1e-12
 *   relative. A non-finite endpoint scores as a beam ending max_dist from any surface.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include "_pybuffer.h"

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* Bilinear field value at map point (x, y); NAN when the point is not finite. */
static double field_at(const double *dist, Py_ssize_t h, Py_ssize_t w, double ox, double oy, double c0, double s0,
                       double res, double outside, double x, double y) {
    double dx = x - ox, dy = y - oy;
    double u = (c0 * dx + s0 * dy) / res;
    double v = (-s0 * dx + c0 * dy) / res;
    if (!isfinite(u) || !isfinite(v)) {
        return NAN;
    }
    double umax = (double)(w - 1) - 0.000001, vmax = (double)(h - 1) - 0.000001;
    double uc = u < 0.0 ? 0.0 : (u > umax ? umax : u);
    double vc = v < 0.0 ? 0.0 : (v > vmax ? vmax : v);
    double beyond = (uc == u && vc == v) ? 0.0 : hypot(u - uc, v - vc) * res;
    Py_ssize_t j = (Py_ssize_t)uc, i = (Py_ssize_t)vc;
    double fu = uc - (double)j, fv = vc - (double)i;
    const double *r0 = dist + i * w + j, *r1 = r0 + w;
    double d = (r0[0] * (1 - fu) + r0[1] * fu) * (1 - fv) + (r1[0] * (1 - fu) + r1[1] * fu) * fv;
    if (beyond > 0.0) {
        double a = d + beyond, b = d > outside ? d : outside;
        d = a < b ? a : b;
    }
    return d;
}

/* Whether the occupied cell holding map point (x, y) is set (0 beyond the map). */
static int cell_set(const uint8_t *occ, Py_ssize_t h, Py_ssize_t w, double ox, double oy, double c0, double s0,
                    double res, double x, double y) {
    double dx = x - ox, dy = y - oy;
    double tj = (c0 * dx + s0 * dy) / res, ti = (-s0 * dx + c0 * dy) / res;
    if (!(ti >= 0.0 && ti < (double)h && tj >= 0.0 && tj < (double)w)) { /* floor(t) in [0, n) iff t in [0, n) */
        return 0;
    }
    return occ[(Py_ssize_t)ti * w + (Py_ssize_t)tj] != 0;
}

static PyObject *log_likelihood(PyObject *self, PyObject *args) {
    PyObject *dist_obj, *occ_obj, *poses_obj, *ranges_obj, *bearings_obj;
    double ox, oy, oyaw, res, z_hit, rand_density, two_sigma_sq, max_dist, mx, my, mth, clearance;
    if (!PyArg_ParseTuple(args, "OOddddddddOOOdddd", &dist_obj, &occ_obj, &ox, &oy, &oyaw, &res, &z_hit,
                          &rand_density, &two_sigma_sq, &max_dist, &poses_obj, &ranges_obj, &bearings_obj, &mx, &my,
                          &mth, &clearance)) {
        return NULL;
    }
    Py_buffer dist, occ, poses, ranges, bearings;
    int have_occ = occ_obj != Py_None;
    if (get_buffer(dist_obj, &dist, 2, 8, "d", "distance") < 0) {
        return NULL;
    }
    if (have_occ && get_buffer(occ_obj, &occ, 2, 1, NULL, "occupied") < 0) {
        PyBuffer_Release(&dist);
        return NULL;
    }
    if (get_buffer(poses_obj, &poses, 2, 8, "d", "poses") < 0) {
        goto fail_occ;
    }
    if (get_buffer(ranges_obj, &ranges, 1, 8, "d", "ranges") < 0) {
        goto fail_poses;
    }
    if (get_buffer(bearings_obj, &bearings, 1, 8, "d", "bearings") < 0) {
        goto fail_ranges;
    }
    Py_ssize_t h = dist.shape[0], w = dist.shape[1], k = poses.shape[0], n = ranges.shape[0];
    Py_ssize_t oh = have_occ ? occ.shape[0] : 0, ow = have_occ ? occ.shape[1] : 0;
    if (poses.shape[1] != 3 || bearings.shape[0] != n || h < 2 || w < 2) {
        PyErr_SetString(PyExc_ValueError, "log_likelihood: poses must be (k, 3), ranges and bearings of one length "
                                          "and the field at least 2 x 2");
        goto fail_all;
    }
    PyObject *out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(k * sizeof(double)));
    double *cb = malloc((size_t)(n > 0 ? n : 1) * sizeof(double));
    double *sb = malloc((size_t)(n > 0 ? n : 1) * sizeof(double));
    if (!out || !cb || !sb) {
        Py_XDECREF(out);
        free(cb);
        free(sb);
        PyErr_NoMemory();
        goto fail_all;
    }
    const double *fd = dist.buf, *q = poses.buf, *r = ranges.buf, *bear = bearings.buf;
    const uint8_t *oc = have_occ ? occ.buf : NULL;
    double *total = (double *)PyByteArray_AS_STRING(out);
    Py_BEGIN_ALLOW_THREADS
    double c0 = cos(oyaw), s0 = sin(oyaw);
    double backs[4] = {clearance + res * 0.0, clearance + res * 0.5, clearance + res * 1.0, clearance + res * 1.5};
    double miss = log(fmax(z_hit * exp(-(max_dist * max_dist) / two_sigma_sq) + rand_density, 1e-300));
    for (Py_ssize_t b = 0; b < n; b++) {
        cb[b] = cos(bear[b]);
        sb[b] = sin(bear[b]);
    }
    for (Py_ssize_t p = 0; p < k; p++) {
        double x = q[3 * p], y = q[3 * p + 1], th = q[3 * p + 2];
        double ct = cos(th), st = sin(th);
        double lx = x + ct * mx - st * my, ly = y + st * mx + ct * my;
        double a = th + mth, ca = cos(a), sa = sin(a);
        double sum = 0.0;
        for (Py_ssize_t b = 0; b < n; b++) {
            double cg = ca * cb[b] - sa * sb[b], sg = sa * cb[b] + ca * sb[b];
            double d = field_at(fd, h, w, ox, oy, c0, s0, res, max_dist, lx + r[b] * cg, ly + r[b] * sg);
            if (isnan(d)) {
                sum += miss;
                continue;
            }
            if (oc) {
                for (int m = 0; m < 4; m++) {
                    double s = r[b] - backs[m];
                    s = s > 0.0 ? s : 0.0;
                    if (cell_set(oc, oh, ow, ox, oy, c0, s0, res, lx + s * cg, ly + s * sg)) {
                        d = max_dist;
                        break;
                    }
                }
            }
            sum += log(fmax(z_hit * exp(-(d * d) / two_sigma_sq) + rand_density, 1e-300));
        }
        total[p] = sum;
    }
    Py_END_ALLOW_THREADS
    free(cb);
    free(sb);
    PyBuffer_Release(&bearings);
    PyBuffer_Release(&ranges);
    PyBuffer_Release(&poses);
    if (have_occ) {
        PyBuffer_Release(&occ);
    }
    PyBuffer_Release(&dist);
    return out;

fail_all:
    PyBuffer_Release(&bearings);
fail_ranges:
    PyBuffer_Release(&ranges);
fail_poses:
    PyBuffer_Release(&poses);
fail_occ:
    if (have_occ) {
        PyBuffer_Release(&occ);
    }
    PyBuffer_Release(&dist);
    return NULL;
}

static PyMethodDef methods[] = {
    {"log_likelihood", log_likelihood, METH_VARARGS,
     "log_likelihood(distance, occupied, ox, oy, oyaw, resolution, z_hit, rand_density, two_sigma_sq, max_dist, "
     "poses, ranges, bearings, mx, my, mth, clearance) -> bytearray of float64 (one per pose)"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_refine", NULL, -1, methods};

PyMODINIT_FUNC PyInit__refine(void) { return PyModule_Create(&module); }
