/*
 * The single-coil window close's health check (include/ct_sc_close.h): Health.suspect on the
 * supervisor's state arrays (the suspect intervals of a node: CT_SUP_SUSPECT (t0, t1) pairs, an open
 * one flagged), for a sensor and the coil driver in one call.
 */
#include <stdint.h>

#include "coiltrack_core.h"

int ct_scc_suspect(const struct ct_sup *s, int64_t node, int64_t t0, int64_t t1)
{
    int64_t i = (node >= 0 && node < CT_SUP_SLOTS) ? s->slot[node] : -1;      /* self._slot.get(node, -1) */
    return ct_sup_suspect(s, i, t0, t1);
}

int ct_scc_suspect_either(const struct ct_sup *s, int64_t node, int64_t other, int64_t t0, int64_t t1)
{
    return ct_scc_suspect(s, node, t0, t1) || ct_scc_suspect(s, other, t0, t1);
}

