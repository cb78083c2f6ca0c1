/*
 * The pose solve's glue (py_solve.c) as other glue files use it: the bound solve of a SolveRun.
 */
#ifndef CT_PY_SOLVE_H
#define CT_PY_SOLVE_H

#include <Python.h>

#include "coiltrack_core.h"

/* o's bound solve (its fit, LM and results), or NULL with a TypeError when o is no bound SolveRun */
const struct ct_solve *ct_py_solve_of(PyObject *o);
/* o's bound acquisition (py_acquire.c), or NULL with a TypeError when o is no bound AcquireRun */
const struct ct_acquire *ct_py_acquire_of(PyObject *o);

#endif /* CT_PY_SOLVE_H */
