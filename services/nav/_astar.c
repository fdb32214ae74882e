/* The search loop of services/nav/astar.py in C: the same cost model, heuristic, tie-breaking and arithmetic, so
 * the compiled and the pure-Python planner expand the same cells in the same order and return the same path.
 *
 * Grid: the costmap padded with a one-cell lethal frame (no bounds checks in the loop). A step from a into
 * neighbour b costs  step * m[c(b)]  with step 1 or sqrt(2) and  m[c] = 1 + (w * min(c, 252)) / 252  (w the cost
 * weight); cells of cost >= 253 start closed, except unknown (255) with allow_unknown and the start's escape cells
 * (inscribed, m = 1 + w). Open list: binary min-heap ordered by (f - 1e-9 g, cell), i.e. Python's heapq on the
 * tuples (key, cell), with lazy deletion. Any heap that pops the least (key, cell) pops the same sequence; this one
 * compares an entry in one unsigned 128-bit comparison (see entry), because the two-field comparison's branch on the
 * key was mispredicted about half the time in the sift-down and cost a third of the search (88 -> 58 ms on the
 * 1000 x 1000 bench workload). Built with -ffp-contract=off so no fused multiply-add changes a rounding.
 *
 * Work buffers are reused across calls (no page faults per plan) and guarded by a lock taken without the GIL; the GIL
 * is released during the search, so the node's control loop keeps running while a plan is computed in a worker thread.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define SQRT2 1.4142135623730951 /* == math.sqrt(2.0) */
#define TIE_BREAK 1e-9
enum { MAX_NON_OBSTACLE = 252, INSCRIBED = 253, NO_INFORMATION = 255 };

/* A heap entry: the key's IEEE-754 bits above the cell index. Keys are finite and >= 0, whose bit patterns order
 * like their values, so one unsigned 128-bit comparison orders entries by (key, cell) without a branch. */
typedef unsigned __int128 entry;

static inline entry make_entry(double key, int64_t cell) {
    uint64_t bits;
    memcpy(&bits, &key, sizeof bits);
    return ((entry)bits << 64) | (uint64_t)cell;
}

static inline int64_t entry_cell(entry e) { return (int64_t)(uint64_t)e; }

typedef struct {
    double *g;
    int32_t *parent;
    uint8_t *closed;
    uint8_t *cls; /* padded cost, index into the multiplier table */
    size_t cells;
    entry *heap;
    size_t heap_cap;
} workspace;

static workspace ws;
static PyThread_type_lock ws_lock;

static int reserve(size_t cells) {
    if (cells > ws.cells) {
        free(ws.g);
        free(ws.parent);
        free(ws.closed);
        free(ws.cls);
        ws.g = malloc(cells * sizeof(double));
        ws.parent = malloc(cells * sizeof(int32_t));
        ws.closed = malloc(cells);
        ws.cls = malloc(cells);
        if (!ws.g || !ws.parent || !ws.closed || !ws.cls) {
            ws.cells = 0;
            return -1;
        }
        ws.cells = cells;
    }
    if (!ws.heap) {
        ws.heap_cap = 1 << 16;
        ws.heap = malloc(ws.heap_cap * sizeof(entry));
        if (!ws.heap) return -1;
    }
    return 0;
}

static inline int before(const entry *a, const entry *b) {
    return *a < *b;
}

static inline int push(size_t *n, double key, int64_t cell) {
    if (*n == ws.heap_cap) {
        entry *grown = realloc(ws.heap, 2 * ws.heap_cap * sizeof(entry));
        if (!grown) return -1;
        ws.heap = grown;
        ws.heap_cap *= 2;
    }
    entry *h = ws.heap;
    entry e = make_entry(key, cell);
    size_t i = (*n)++;
    while (i > 0) {
        size_t up = (i - 1) / 2;
        if (!before(&e, &h[up])) break;
        h[i] = h[up];
        i = up;
    }
    h[i] = e;
    return 0;
}

/* Floyd's bottom-up pop: move the hole down along the smaller child, then sift the last entry up into it. */
static inline int64_t pop(size_t *n) {
    entry *h = ws.heap;
    const int64_t top = entry_cell(h[0]);
    const entry last = h[--(*n)];
    const size_t m = *n;
    size_t i = 0;
    for (;;) {
        size_t c = 2 * i + 1;
        if (c + 1 >= m) {
            if (c < m) {
                h[i] = h[c];
                i = c;
            }
            break;
        }
        c += before(&h[c + 1], &h[c]);
        h[i] = h[c];
        i = c;
    }
    while (i > 0) {
        size_t up = (i - 1) / 2;
        if (!before(&last, &h[up])) break;
        h[i] = h[up];
        i = up;
    }
    h[i] = last;
    return top;
}

/* The search proper (no Python objects): returns expansions, or -1 when out of memory. */
static long long search(const uint8_t *cost, const uint8_t *escape, Py_ssize_t h, Py_ssize_t w, int64_t start_n,
                        int64_t goal_n, double cost_weight, int allow_unknown) {
    const int64_t W = w + 2, H = h + 2;
    const size_t cells = (size_t)(W * H);
    double mult[256];
    for (int c = 0; c < 256; c++)
        mult[c] = 1.0 + (cost_weight * (double)(c < MAX_NON_OBSTACLE ? c : MAX_NON_OBSTACLE)) / MAX_NON_OBSTACLE;
    mult[INSCRIBED] = 1.0 + cost_weight; /* only escape cells of cost 253 are ever entered */
    double *g = ws.g;
    int32_t *parent = ws.parent;
    uint8_t *closed = ws.closed, *cls = ws.cls;
    for (size_t k = 0; k < cells; k++) g[k] = INFINITY;
    memset(closed, 1, (size_t)W);
    memset(closed + (H - 1) * W, 1, (size_t)W);
    memset(cls, 0, (size_t)W);
    memset(cls + (H - 1) * W, 0, (size_t)W);
    for (Py_ssize_t i = 0; i < h; i++) {
        uint8_t *crow = closed + (i + 1) * W, *krow = cls + (i + 1) * W;
        const uint8_t *src = cost + i * w;
        const uint8_t *esc = escape ? escape + i * w : NULL;
        crow[0] = crow[W - 1] = 1;
        krow[0] = krow[W - 1] = 0;
        for (Py_ssize_t j = 0; j < w; j++) {
            uint8_t c = src[j];
            int blocked = c >= INSCRIBED && !(allow_unknown && c == NO_INFORMATION) && !(esc && esc[j]);
            crow[j + 1] = (uint8_t)blocked;
            krow[j + 1] = c;
        }
    }
    const int64_t off[8] = {1, -1, W, -W, W + 1, W - 1, -W + 1, -W - 1};
    const int64_t ox[8] = {1, -1, 0, 0, 1, -1, 1, -1};
    const int64_t oy[8] = {0, 0, 1, -1, 1, 1, -1, -1};
    const double step[8] = {1.0, 1.0, 1.0, 1.0, SQRT2, SQRT2, SQRT2, SQRT2};
    const int64_t gx = goal_n % W, gy = goal_n / W;
    const double k_oct = SQRT2 - 2.0, eps = TIE_BREAK;
    g[start_n] = 0.0;
    parent[start_n] = -1;
    size_t n_open = 0;
    push(&n_open, 0.0, start_n);
    long long expanded = 0;
    while (n_open) {
        const int64_t n = pop(&n_open);
        if (closed[n]) continue;
        closed[n] = 1;
        expanded++;
        if (n == goal_n) break;
        const double gn = g[n];
        const int64_t x = n % W, y = n / W;
        for (int d = 0; d < 8; d++) {
            const int64_t nb = n + off[d];
            if (closed[nb]) continue;
            const double ng = gn + step[d] * mult[cls[nb]];
            if (ng < g[nb]) {
                g[nb] = ng;
                parent[nb] = (int32_t)n;
                int64_t dx = x + ox[d] - gx, dy = y + oy[d] - gy;
                if (dx < 0) dx = -dx;
                if (dy < 0) dy = -dy;
                const double key = ng + (double)dx + (double)dy + k_oct * (double)(dx < dy ? dx : dy) - eps * ng;
                if (push(&n_open, key, nb)) return -1;
            }
        }
    }
    return expanded;
}

static int take_grid(PyObject *obj, Py_buffer *view, Py_ssize_t cells, const char *what) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS) < 0) return -1;
    if (view->len != cells || view->itemsize != 1) {
        PyErr_Format(PyExc_ValueError, "%s must be a C-contiguous uint8 grid of %zd cells", what, cells);
        PyBuffer_Release(view);
        return -1;
    }
    return 0;
}

PyDoc_STRVAR(plan_doc,
             "plan(cost, h, w, start, goal, cost_weight, allow_unknown, escape) -> (cells, g_goal, expanded)\n\n"
             "cost: C-contiguous uint8 (h, w); start, goal: (i, j); escape: uint8 (h, w) or None.\n"
             "cells: bytes of int64 (i, j) pairs from start to goal, or None when the goal was not reached;\n"
             "g_goal: path cost in cell units.");

static PyObject *plan(PyObject *self, PyObject *args) {
    (void)self;
    PyObject *cost_obj, *escape_obj;
    Py_ssize_t h, w, si, sj, gi, gj;
    double cost_weight;
    int allow_unknown;
    if (!PyArg_ParseTuple(args, "Onn(nn)(nn)dpO", &cost_obj, &h, &w, &si, &sj, &gi, &gj, &cost_weight,
                          &allow_unknown, &escape_obj))
        return NULL;
    if (!(cost_weight >= 0.0 && isfinite(cost_weight))) { /* keys must stay finite and >= 0 (see entry) */
        PyErr_Format(PyExc_ValueError, "cost_weight must be a finite number >= 0, got %R", PyTuple_GET_ITEM(args, 5));
        return NULL;
    }
    if (h <= 0 || w <= 0 || si < 0 || si >= h || sj < 0 || sj >= w || gi < 0 || gi >= h || gj < 0 || gj >= w) {
        PyErr_SetString(PyExc_ValueError, "start and goal must be cells of a non-empty grid");
        return NULL;
    }
    Py_buffer cost, escape = {0};
    if (take_grid(cost_obj, &cost, h * w, "cost") < 0) return NULL;
    int has_escape = escape_obj != Py_None;
    if (has_escape && take_grid(escape_obj, &escape, h * w, "escape") < 0) {
        PyBuffer_Release(&cost);
        return NULL;
    }
    const int64_t W = w + 2;
    if ((h + 2) * W > INT32_MAX) {
        PyBuffer_Release(&cost);
        if (has_escape) PyBuffer_Release(&escape);
        PyErr_SetString(PyExc_ValueError, "costmap too large (more than 2^31 cells)");
        return NULL;
    }
    const int64_t start_n = (si + 1) * W + sj + 1, goal_n = (gi + 1) * W + gj + 1;
    long long expanded = -1;
    PyObject *result = NULL;
    Py_BEGIN_ALLOW_THREADS
    PyThread_acquire_lock(ws_lock, WAIT_LOCK);
    if (reserve((size_t)(W * (h + 2))) == 0)
        expanded = search(cost.buf, has_escape ? escape.buf : NULL, h, w, start_n, goal_n, cost_weight,
                          allow_unknown);
    Py_END_ALLOW_THREADS
    PyBuffer_Release(&cost);
    if (has_escape) PyBuffer_Release(&escape);
    if (expanded < 0) {
        PyErr_NoMemory();
    } else if (!(ws.closed[goal_n] && isfinite(ws.g[goal_n]))) {
        result = Py_BuildValue("OdL", Py_None, ws.g[goal_n], expanded);
    } else {
        Py_ssize_t length = 0;
        for (int64_t n = goal_n; n != -1; n = ws.parent[n]) length++;
        PyObject *cells = PyBytes_FromStringAndSize(NULL, length * 2 * (Py_ssize_t)sizeof(int64_t));
        if (cells) {
            int64_t *out = (int64_t *)PyBytes_AS_STRING(cells);
            Py_ssize_t k = length;
            for (int64_t n = goal_n; n != -1; n = ws.parent[n]) {
                k--;
                out[2 * k] = n / W - 1;
                out[2 * k + 1] = n % W - 1;
            }
            result = Py_BuildValue("OdL", cells, ws.g[goal_n], expanded);
            Py_DECREF(cells);
        }
    }
    PyThread_release_lock(ws_lock);
    return result;
}

static PyMethodDef methods[] = {
    {"plan", plan, METH_VARARGS, plan_doc},
    {NULL, NULL, 0, NULL},
};

static struct PyModuleDef module = {
    PyModuleDef_HEAD_INIT, "_astar", "A* search loop of services.nav.astar in C.", -1, methods,
    NULL, NULL, NULL, NULL,
};

PyMODINIT_FUNC PyInit__astar(void) {
    ws_lock = PyThread_allocate_lock();
    if (!ws_lock) return PyErr_NoMemory();
    return PyModule_Create(&module);
}
