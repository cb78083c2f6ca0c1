/*
 * The single-coil window close's health check (coiltrack.firmware.supervise.health.Health.suspect_either,
 * the tracker's track.single_coil_tracker.SingleCoilTracker._close_one): whether a sensor's clock or the
 * coil driver's was suspect anywhere in a window's span, on the supervisor's state arrays (ct_supervise.h's
 * layout, bound with ct_sup_bind).  Same names (ct_ prefix), same operations in the same order as the
 * Python reference.
 */
#ifndef CT_SC_CLOSE_H
#define CT_SC_CLOSE_H

#include <stdint.h>

struct ct_sup;

/* Health.suspect: node's clock suspect anywhere in master time [t0, t1] (0 for a node the slot table
 * does not hold) */
int ct_scc_suspect(const struct ct_sup *s, int64_t node, int64_t t0, int64_t t1);

/* Health.suspect_either: suspect(node, t0, t1) or suspect(other, t0, t1) */
int ct_scc_suspect_either(const struct ct_sup *s, int64_t node, int64_t other, int64_t t0, int64_t t1);

#endif
