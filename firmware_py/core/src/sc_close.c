/*
 * The single-coil window close's health check (include/ct_sc_close.h): Health.suspect on the
 * supervisor's state arrays (the suspect intervals of a node: CT_SUP_SUSPECT (t0, t1) pairs, an open
 * one flagged), for a sensor and the coil driver in one call.
 */
#include <stdint.h>

#include "coiltrack_core.h"

#define CT_SCC_NONE (-((int64_t)1 << 62))      /* health._NONE */

int ct_scc_suspect(const struct ct_sup *s, int64_t node, int64_t t0, int64_t t1)
{
    const int64_t *a, *b;
    int64_t i;
    int k;
    i = (node >= 0 && node < CT_SUP_SLOTS) ? s->slot[node] : -1;      /* self._slot.get(node, -1) */
    if (i < 0)
        return 0;
    if (s->suspect_open[i])
        return 1;
    a = s->susp_t0 + CT_SUP_SUSPECT * i;
    b = s->susp_t1 + CT_SUP_SUSPECT * i;
    for (k = 0; k < CT_SUP_SUSPECT; ++k)
        if (a[k] != CT_SCC_NONE && a[k] <= t1 && b[k] >= t0)
            return 1;
    return 0;
}

int ct_scc_suspect_either(const struct ct_sup *s, int64_t node, int64_t other, int64_t t0, int64_t t1)
{
    return ct_scc_suspect(s, node, t0, t1) || ct_scc_suspect(s, other, t0, t1);
}

