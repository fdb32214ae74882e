/* Grid operations of services/common/gridops.py in C, so that the services that need them (nav's inflation and
 * planner, localization's likelihood field and particle clusters) do not import scipy.ndimage, which loads
 * scipy.special and numpy.testing and costs about 30 MB resident per process.
 *
 * edt_sq(grid) -> float64 array: squared Euclidean distance (cells^2) from each cell to the nearest zero cell,
 *   0 on zero cells, inf everywhere when there is none. Felzenszwalb & Huttenlocher (2012), "Distance Transforms of
 *   Sampled Functions": the 1-D transform  d(q) = min_p ((q - p)^2 + f(p))  (lower envelope of parabolas) along
 *   axis 0 with f = 0 on zero cells and inf elsewhere, then along axis 1 on the result. Every value is an integer
 *   below 2^53, so the result is exact.
 * label(grid) -> (int32 array, count): connected components of the nonzero cells of a 2-D or 3-D grid, every cell
 *   of the 3^n - 1 neighbourhood connected (scipy.ndimage.label with structure=np.ones((3,) * n)); components are
 *   numbered 1..count in the C order of their first cell, background 0. Union-find over the cells in C order.
 * quadratic_sample(field, origin_x, origin_y, resolution, points) -> float64 array of 3N: the values M(p) (N), then
 *   the gradients dM/dp (N x 2, per metre) of a float32 field at points (N x 2, float64), from the second-order
 *   Taylor expansion about the nearest cell centre (see gridops.quadratic_sample); 0 where the expansion's 3x3
 *   neighbourhood leaves the field. The arithmetic is NumPy's, operation by operation (float32 where it is float32,
 *   no fused multiply-add), so both give the same bits.
 * max_gaussian_splat(field, origin_x, origin_y, resolution, sigma_cells, radius_cells, points) -> None: in place,
 *   field[iy, ix] = max(field[iy, ix], exp(-d^2 / (2 sigma^2))) for every point (N x 2, float64) and every cell
 *   centre within radius_cells (a square window) of the cell holding it, d the centre's distance to the point in
 *   cells; cells outside the float32 field are skipped. The exponent and exp are evaluated in double and rounded
 *   to float32 once, as in NumPy (gridops._max_gaussian_splat_numpy).
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

/* 1-D squared distance transform of f (n values, stride in elements) into d; v, z: work buffers (n, n + 1). */
static void dt1d(const double *f, Py_ssize_t n, Py_ssize_t stride, double *d, Py_ssize_t *v, double *z) {
    Py_ssize_t k = -1;
    for (Py_ssize_t q = 0; q < n; q++) {
        double fq = f[q * stride];
        if (isinf(fq)) {
            continue;
        }
        if (k < 0) {
            k = 0;
            v[0] = q;
            z[0] = -INFINITY;
            z[1] = INFINITY;
            continue;
        }
        double s;
        for (;;) {
            Py_ssize_t p = v[k];
            s = ((fq + (double)q * q) - (f[p * stride] + (double)p * p)) / (2.0 * (double)(q - p));
            if (s > z[k]) {
                break;
            }
            k--;
        }
        k++;
        v[k] = q;
        z[k] = s;
        z[k + 1] = INFINITY;
    }
    if (k < 0) {
        for (Py_ssize_t q = 0; q < n; q++) {
            d[q] = INFINITY;
        }
        return;
    }
    k = 0;
    for (Py_ssize_t q = 0; q < n; q++) {
        while (z[k + 1] < (double)q) {
            k++;
        }
        double dq = (double)(q - v[k]);
        d[q] = dq * dq + f[v[k] * stride];
    }
}

static PyObject *as_array(PyObject *obj, Py_buffer *view, int ndim_min, int ndim_max) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND) < 0) {
        return NULL;
    }
    if (view->ndim < ndim_min || view->ndim > ndim_max || view->itemsize != 1) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "expected a C-contiguous uint8/bool grid of %d to %d dimensions", ndim_min,
                     ndim_max);
        return NULL;
    }
    return obj;
}

static PyObject *edt_sq(PyObject *self, PyObject *args) {
    PyObject *obj;
    Py_buffer grid;
    if (!PyArg_ParseTuple(args, "O", &obj) || !as_array(obj, &grid, 2, 2)) {
        return NULL;
    }
    Py_ssize_t h = grid.shape[0], w = grid.shape[1], n = h > w ? h : w;
    PyObject *out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(h * w * sizeof(double)));
    double *col = malloc((size_t)n * sizeof(double));
    Py_ssize_t *v = malloc((size_t)n * sizeof(Py_ssize_t));
    double *z = malloc((size_t)(n + 1) * sizeof(double));
    if (!out || !col || !v || !z) {
        Py_XDECREF(out);
        free(col);
        free(v);
        free(z);
        PyBuffer_Release(&grid);
        return PyErr_NoMemory();
    }
    double *d = (double *)PyByteArray_AS_STRING(out);
    const uint8_t *g = grid.buf;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < h * w; i++) {
        d[i] = g[i] ? INFINITY : 0.0;
    }
    for (Py_ssize_t j = 0; j < w; j++) { /* along axis 0 (columns), in place through col */
        dt1d(d + j, h, w, col, v, z);
        for (Py_ssize_t i = 0; i < h; i++) {
            d[i * w + j] = col[i];
        }
    }
    for (Py_ssize_t i = 0; i < h; i++) { /* along axis 1 (rows) */
        dt1d(d + i * w, w, 1, col, v, z);
        memcpy(d + i * w, col, (size_t)w * sizeof(double));
    }
    Py_END_ALLOW_THREADS
    free(col);
    free(v);
    free(z);
    PyBuffer_Release(&grid);
    return out;
}

static int64_t find_root(int64_t *parent, int64_t a) {
    while (parent[a] != a) {
        parent[a] = parent[parent[a]];
        a = parent[a];
    }
    return a;
}

static void unite(int64_t *parent, int64_t a, int64_t b) {
    a = find_root(parent, a);
    b = find_root(parent, b);
    if (a < b) {
        parent[b] = a;
    } else if (b < a) {
        parent[a] = b;
    }
}

static PyObject *label(PyObject *self, PyObject *args) {
    PyObject *obj;
    Py_buffer grid;
    if (!PyArg_ParseTuple(args, "O", &obj) || !as_array(obj, &grid, 2, 3)) {
        return NULL;
    }
    Py_ssize_t a = grid.ndim == 3 ? grid.shape[0] : 1;
    Py_ssize_t b = grid.shape[grid.ndim - 2], c = grid.shape[grid.ndim - 1];
    Py_ssize_t cells = a * b * c;
    PyObject *out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(cells * sizeof(int32_t)));
    int64_t *parent = malloc((size_t)(cells > 0 ? cells : 1) * sizeof(int64_t));
    if (!out || !parent) {
        Py_XDECREF(out);
        free(parent);
        PyBuffer_Release(&grid);
        return PyErr_NoMemory();
    }
    int32_t *lab = (int32_t *)PyByteArray_AS_STRING(out);
    const uint8_t *g = grid.buf;
    int64_t count = 0;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t i = 0; i < a; i++) {
        for (Py_ssize_t j = 0; j < b; j++) {
            for (Py_ssize_t k = 0; k < c; k++) {
                int64_t p = (i * b + j) * c + k;
                parent[p] = p;
                if (!g[p]) {
                    continue;
                }
                /* the neighbours that come before p in C order: the whole previous plane, the previous row, the
                 * previous cell */
                for (Py_ssize_t di = -1; di <= 0; di++) {
                    Py_ssize_t ni = i + di;
                    if (ni < 0) {
                        continue;
                    }
                    for (Py_ssize_t dj = -1; dj <= 1; dj++) {
                        Py_ssize_t nj = j + dj;
                        if (nj < 0 || nj >= b || (di == 0 && dj > 0)) {
                            continue;
                        }
                        for (Py_ssize_t dk = -1; dk <= 1; dk++) {
                            Py_ssize_t nk = k + dk;
                            if (nk < 0 || nk >= c || (di == 0 && dj == 0 && dk >= 0)) {
                                continue;
                            }
                            int64_t q = (ni * b + nj) * c + nk;
                            if (g[q]) {
                                unite(parent, p, q);
                            }
                        }
                    }
                }
            }
        }
    }
    /* a root is the first cell of its component in C order: numbering roots as they come numbers components in the
     * order of their first cell */
    for (int64_t p = 0; p < cells; p++) {
        if (!g[p]) {
            lab[p] = 0;
        } else {
            int64_t r = find_root(parent, p);
            lab[p] = r == p ? (int32_t)++count : lab[r];
        }
    }
    Py_END_ALLOW_THREADS
    free(parent);
    PyBuffer_Release(&grid);
    return Py_BuildValue("(NL)", out, (long long)count);
}

/* The float32 field (2-D, C-contiguous, writable when asked) and float64 points (N x 2) of quadratic_sample and
 * max_gaussian_splat; 0 with both buffers held, -1 with none held and a ValueError naming `name`. */
static int field_and_points(PyObject *field_obj, PyObject *points_obj, Py_buffer *field, Py_buffer *points,
                            int writable, const char *name) {
    int flags = PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND | (writable ? PyBUF_WRITABLE : 0);
    if (PyObject_GetBuffer(field_obj, field, flags) < 0) {
        return -1;
    }
    if (field->ndim != 2 || field->itemsize != 4 || strcmp(field->format, "f") != 0) {
        PyBuffer_Release(field);
        PyErr_Format(PyExc_ValueError, "%s: expected a %sC-contiguous 2-D float32 field", name,
                     writable ? "writable " : "");
        return -1;
    }
    if (PyObject_GetBuffer(points_obj, points, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND) < 0) {
        PyBuffer_Release(field);
        return -1;
    }
    if (points->ndim != 2 || points->shape[1] != 2 || points->itemsize != 8 || strcmp(points->format, "d") != 0) {
        PyBuffer_Release(field);
        PyBuffer_Release(points);
        PyErr_Format(PyExc_ValueError, "%s: expected C-contiguous float64 points of shape (N, 2)", name);
        return -1;
    }
    return 0;
}

static PyObject *quadratic_sample(PyObject *self, PyObject *args) {
    PyObject *field_obj, *points_obj;
    double ox, oy, res;
    Py_buffer field, points;
    if (!PyArg_ParseTuple(args, "OdddO", &field_obj, &ox, &oy, &res, &points_obj)) {
        return NULL;
    }
    if (field_and_points(field_obj, points_obj, &field, &points, 0, "quadratic_sample") < 0) {
        return NULL;
    }
    Py_ssize_t height = field.shape[0], width = field.shape[1], n = points.shape[0];
    PyObject *out = PyByteArray_FromStringAndSize(NULL, (Py_ssize_t)(3 * n * sizeof(double)));
    if (!out) {
        PyBuffer_Release(&field);
        PyBuffer_Release(&points);
        return NULL;
    }
    const float *f = field.buf;
    const double *p = points.buf;
    double *value = (double *)PyByteArray_AS_STRING(out), *grad = value + n;
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < n; k++) {
        double u = (p[2 * k] - ox) / res - 0.5, v = (p[2 * k + 1] - oy) / res - 0.5;
        double ru = rint(u), rv = rint(v);
        if (!(ru >= 1.0 && rv >= 1.0 && ru < (double)(width - 1) && rv < (double)(height - 1))) {
            value[k] = 0.0;
            grad[2 * k] = grad[2 * k + 1] = 0.0;
            continue;
        }
        Py_ssize_t x = (Py_ssize_t)ru, y = (Py_ssize_t)rv, i = y * width + x;
        double du = u - (double)x, dv = v - (double)y;
        float c = f[i], e = f[i + 1], w = f[i - 1], nn = f[i + width], s = f[i - width];
        float gx = 0.5f * (e - w), gy = 0.5f * (nn - s);
        float hxx = (e - 2.0f * c) + w, hyy = (nn - 2.0f * c) + s;
        float hxy = 0.25f * (((f[i + width + 1] - f[i - width + 1]) - f[i + width - 1]) + f[i - width - 1]);
        double quad = ((double)hxx * du * du + (double)(2.0f * hxy) * du * dv) + (double)hyy * dv * dv;
        value[k] = (((double)c + (double)gx * du) + (double)gy * dv) + 0.5 * quad;
        grad[2 * k] = (((double)gx + (double)hxx * du) + (double)hxy * dv) / res;
        grad[2 * k + 1] = (((double)gy + (double)hxy * du) + (double)hyy * dv) / res;
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&field);
    PyBuffer_Release(&points);
    return out;
}

static PyObject *max_gaussian_splat(PyObject *self, PyObject *args) {
    PyObject *field_obj, *points_obj;
    double ox, oy, res, sigma;
    Py_ssize_t radius;
    Py_buffer field, points;
    if (!PyArg_ParseTuple(args, "OddddnO", &field_obj, &ox, &oy, &res, &sigma, &radius, &points_obj)) {
        return NULL;
    }
    if (!(res > 0.0) || !(sigma > 0.0) || radius < 0) {
        PyErr_SetString(PyExc_ValueError, "max_gaussian_splat: resolution and sigma must be > 0, radius >= 0");
        return NULL;
    }
    if (field_and_points(field_obj, points_obj, &field, &points, 1, "max_gaussian_splat") < 0) {
        return NULL;
    }
    Py_ssize_t height = field.shape[0], width = field.shape[1], n = points.shape[0];
    float *f = field.buf;
    const double *p = points.buf;
    double two_var = 2.0 * (sigma * sigma);
    Py_BEGIN_ALLOW_THREADS
    for (Py_ssize_t k = 0; k < n; k++) {
        double u = (p[2 * k] - ox) / res - 0.5, v = (p[2 * k + 1] - oy) / res - 0.5;
        if (!isfinite(u) || !isfinite(v)) {
            continue;
        }
        double cu = rint(u), cv = rint(v);
        if (cu < (double)(-radius) || cv < (double)(-radius) || cu > (double)(width + radius) ||
            cv > (double)(height + radius)) {
            continue;
        }
        Py_ssize_t cx = (Py_ssize_t)cu, cy = (Py_ssize_t)cv;
        for (Py_ssize_t y = cy - radius; y <= cy + radius; y++) {
            if (y < 0 || y >= height) {
                continue;
            }
            double dy = (double)y - v;
            for (Py_ssize_t x = cx - radius; x <= cx + radius; x++) {
                if (x < 0 || x >= width) {
                    continue;
                }
                double dx = (double)x - u;
                float value = (float)exp(-(dx * dx + dy * dy) / two_var);
                float *cell = f + y * width + x;
                if (value > *cell) {
                    *cell = value;
                }
            }
        }
    }
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&field);
    PyBuffer_Release(&points);
    Py_RETURN_NONE;
}

static PyMethodDef methods[] = {
    {"edt_sq", edt_sq, METH_VARARGS, "edt_sq(grid) -> bytearray of float64: squared distance to the nearest zero cell"},
    {"label", label, METH_VARARGS, "label(grid) -> (bytearray of int32 labels, count): fully connected components"},
    {"quadratic_sample", quadratic_sample, METH_VARARGS,
     "quadratic_sample(field, origin_x, origin_y, resolution, points) -> bytearray of float64: values, gradients"},
    {"max_gaussian_splat", max_gaussian_splat, METH_VARARGS,
     "max_gaussian_splat(field, origin_x, origin_y, resolution, sigma_cells, radius_cells, points) -> None"},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_gridops", NULL, -1, methods};

PyMODINIT_FUNC PyInit__gridops(void) { return PyModule_Create(&module); }
