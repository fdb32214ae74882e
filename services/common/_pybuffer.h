/* Shared by the C extensions (setup.py puts services/common on their include path): a C-contiguous buffer of the
 * expected dimensions, item size and struct format, or a ValueError naming the calling function and the argument.
 *
 * get_buffer(obj, view, ndim, itemsize, format, what) -> 0, or -1 with the exception set (``format`` NULL: any
 * format of that item size). Release the view with PyBuffer_Release.
 */
#ifndef ZAGV_PYBUFFER_H
#define ZAGV_PYBUFFER_H

#include <Python.h>

#include <string.h>

static int zagv_get_buffer(PyObject *obj, Py_buffer *view, int ndim, Py_ssize_t itemsize, const char *format,
                           const char *caller, const char *what) {
    if (PyObject_GetBuffer(obj, view, PyBUF_C_CONTIGUOUS | PyBUF_FORMAT | PyBUF_ND) < 0) {
        return -1;
    }
    if (view->ndim != ndim || view->itemsize != itemsize || (format && strcmp(view->format, format) != 0)) {
        PyBuffer_Release(view);
        PyErr_Format(PyExc_ValueError, "%s: %s must be C-contiguous, %d-D, %s", caller, what, ndim,
                     format ? format : "1-byte");
        return -1;
    }
    return 0;
}

#define get_buffer(obj, view, ndim, itemsize, format, what) \
    zagv_get_buffer(obj, view, ndim, itemsize, format, __func__, what)

#endif
