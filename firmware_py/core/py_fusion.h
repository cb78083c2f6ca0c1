/*
 * What py_fusion.c's types offer the other glue files (py_fusimu.c's ImuSample.drain): the live
 * state's step split at a pending snapshot, the snapshot taken in it (CompiledReplay.split_take's
 * call of Replay.replay_take), from C.
 */
#ifndef CT_PY_FUSION_H
#define CT_PY_FUSION_H

#include <Python.h>
#include <stdint.h>

/* 1 when o is an ext.Replay bound to its rings' head and count arrays with a snapshot bound
 * (bind_snapshot), else 0 */
int ct_py_replay_takes(PyObject *o);
/* CompiledReplay.split_take's kernel call on the Replay o (ct_py_replay_takes): its io set as split_take
 * sets it (t0: the state's time, pending and snap_t: the snapshot's, pcount: the prediction count), then
 * replay_take(1, xi); io_out[0..3] = the state's time, the prediction count, the steps run, the snapshot
 * still pending (0/1) after it; the kernel's CT_REPLAY_* or -1 with an exception set */
int ct_py_replay_split_take(PyObject *o, int64_t t0, int64_t pending, int64_t snap_t, int64_t pcount, int xi,
                            int64_t *io_out);

#endif /* CT_PY_FUSION_H */
