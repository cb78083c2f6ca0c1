/*
 * The start of a burst's fusion update in one compiled call: see include/ct_fuse.h.  Each function
 * follows the Python named beside it operation by operation (-ffp-contract=off), so the compensated
 * signals, the charges and the stages are the reference's to the bit (tests/firmware/core/test_core_fuse.py).
 */
#include <string.h>

#include "coiltrack_core.h"

/* StagedSolve.predict_signals through the compiled solver (SolveRun.predict) */
void ct_fuse_predict(const struct ct_fuse *z, const double *p, const double *R, double *out)
{
    double h[3 * CT_FZ_MAXN];
    const int n = z->n;
    int i, j;
    ct_signal_fields(z->geom, n, p[0], p[1], p[2], z->cur, 0, z->B, z->J);
    ct_signal_project(n, R, z->B, h);
    for (j = 0; j < n; ++j)
        for (i = 0; i < 3; ++i)
            out[i * n + j] = h[3 * j + i];
}

/* SensorInertial.compensate_begin (compiled: _compensate_begin_compiled) */
static int fuse_compensate_begin(const struct ct_fuse *z, int64_t *used)
{
    int64_t *fz = z->fz;
    if (!ct_fusion_comp_begin(z->S, z->S_comp, z->n, z->fs[z->fs_init] != 0, z->P, z->n_st, z->max_sigma, z->ht,
                              z->hd, z->cap, z->hc[0], z->hc[1], z->tr[0], z->p_ref, z->R_ref))
        return 0;
    ct_fuse_predict(z, z->p_ref, z->R_ref, z->h_ref);
    *used += z->n;
    fz[CT_FZ_COMP_J] = 0;
    return 1;
}

/* SensorInertial.compensate_step (compiled: _compensate_step_compiled): 1 all pulses done, 0 some
 * left, -1 the history misses a pulse's time (S_comp = S) */
static int fuse_compensate_step(const struct ct_fuse *z, int64_t budget, int64_t *used)
{
    int64_t *fz = z->fz;
    const int n = z->n;
    int64_t u = 0, j = fz[CT_FZ_COMP_J];
    while (j < n && (u == 0 || u + n <= budget)) {
        if (!ct_fusion_pose_at(z->ht, z->hd, z->cap, z->hc[0], z->hc[1], z->pulse_t[j], z->p_j, z->R_j)) {
            memcpy(z->S_comp, z->S, (size_t)(3 * n) * sizeof(double));
            return -1;
        }
        ct_fuse_predict(z, z->p_j, z->R_j, z->h_j);
        *used += n;
        ct_fusion_comp_add(z->S_comp, z->h_ref, z->h_j, n, (int)j);
        u += n;
        j += 1;
        fz[CT_FZ_COMP_J] = j;
    }
    if (j < n)
        return 0;
    fz[CT_FZ_COMPENSATED] += 1;
    return 1;
}

/* SensorInertial.fuse's loop over _measure_step, the compensation's stages */
int ct_fuse_compensate(const struct ct_fuse *z, int64_t budget, int64_t *used, int *waiting)
{
    int64_t *fz = z->fz;
    const int64_t n = z->n;
    *used = 0;
    *waiting = 0;
    while (fz[CT_FZ_STAGE] == CT_FZ_COMPENSATE || fz[CT_FZ_STAGE] == CT_FZ_COMPENSATE_PULSES) {
        int64_t left = budget - *used;
        if (left < n) {
            *waiting = *used == 0;
            return CT_FZ_STOP;
        }
        if (fz[CT_FZ_STAGE] == CT_FZ_COMPENSATE) {
            fz[CT_FZ_COMP_OK] = 0;
            fz[CT_FZ_STAGE] = CT_FZ_UPDATE_MAG;
            if (z->motion_compensation && fuse_compensate_begin(z, used))
                fz[CT_FZ_STAGE] = CT_FZ_COMPENSATE_PULSES;
        } else {
            int done = fuse_compensate_step(z, left, used);
            if (done < 0)
                fz[CT_FZ_STAGE] = CT_FZ_UPDATE_MAG;
            else if (done)
                return CT_FZ_BEGIN;
        }
    }
    return CT_FZ_ON;
}

/* SensorInertial.on_solution (solved): np.copyto of the three results, the stage */
void ct_fuse_solution(const double *p, const double *R, const double *C, double *mag_p, double *mag_R, double *mag_C,
                      int64_t *fz)
{
    memcpy(mag_p, p, 3 * sizeof(double));
    memcpy(mag_R, R, 9 * sizeof(double));
    memcpy(mag_C, C, 36 * sizeof(double));
    fz[CT_FZ_STAGE] = CT_FZ_COMPENSATE;
}
