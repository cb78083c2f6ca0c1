/*
 * A pulsed-DC pose solve in two compiled calls (its acquisition's units through acquire.c): see
 * include/ct_solve.h.  Each function follows the Python named beside it operation by operation
 * (-ffp-contract=off), so the results, the charges and the decisions are the reference's to the
 * bit (tests/firmware/core/test_core_solve.py, test_core_acquire.py).
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* PoseSolver._start_acquisition: the compiled acquisition begun on the hemisphere and sigma's rms of
 * the solve's begin (CT_PH_ACQ_UNITS), or the Python's (CT_PH_ACQUIRE) */
static int solve_start_acquisition(const struct ct_solve *s)
{
    const double *st = s->st;
    if (s->acq == NULL)
        return CT_PH_ACQUIRE;
    ct_acquire_begin(s->acq, st[CT_SV_HEMI], st[CT_SV_HEMI + 1], st[CT_SV_HEMI + 2], st[CT_SV_SIGMA_RMS]);
    return CT_PH_ACQ_UNITS;
}

/* PoseSolver._unit_acquire: one unit of the acquisition; finished, its start into the fit and the
 * LM's start next, or no start (the status) */
static int solve_unit_acquire(const struct ct_solve *s)
{
    const struct ct_acquire *a = s->acq;
    const struct ct_posefit *f = s->f;
    double *st = s->st;
    if (ct_acquire_unit(a) != CT_AQ_NONE)
        return CT_PH_ACQ_UNITS;
    if (a->st[CT_AQ_OK] != 0.0) {
        memcpy(f->p, a->p, 3 * sizeof(double));          /* _PoseFit.set */
        memcpy(f->R, a->R, 9 * sizeof(double));
        return CT_PH_LM_START;
    }
    st[CT_SV_STATUS] = CT_SOLVE_NO_START | (st[CT_SV_REACQUIRED] != 0.0 ? CT_SOLVE_REACQUIRED : 0);
    return CT_PH_NONE;
}

/* PoseSolver.begin with _load (ct_solve_load), _load_hemisphere and _load_x0 */
int ct_solve_begin(const struct ct_solve *s, const double *S, const double *sigma, int64_t rs, int64_t cs,
                   const double *cur, int64_t cstride, const double *hemi, const double *x0p, const double *x0R)
{
    const struct ct_posefit *f = s->f;
    double *st = s->st;
    int i;
    st[CT_SV_PHASE] = CT_PH_NONE;
    st[CT_SV_STATUS] = CT_SOLVE_BAD_INPUT;
    if (!ct_solve_load(s->n, S, sigma, rs, cs, cur, cstride, (double *)f->S, (double *)f->w, (double *)f->cur,
                       st + CT_SV_SIGMA_RMS))
        return CT_SOLVE_BAD_INPUT;
    /* _load_hemisphere */
    st[CT_SV_CHECK_HEMI] = hemi != NULL;
    if (hemi == NULL) {
        st[CT_SV_HEMI] = 1.0;
        st[CT_SV_HEMI + 1] = 0.0;
        st[CT_SV_HEMI + 2] = 0.0;
    } else {
        st[CT_SV_HEMI] = hemi[0];
        st[CT_SV_HEMI + 1] = hemi[1];
        st[CT_SV_HEMI + 2] = hemi[2];
        if (!(isfinite(hemi[0]) && isfinite(hemi[1]) && isfinite(hemi[2])))
            return CT_SOLVE_BAD_INPUT;
    }
    /* _load_x0 */
    st[CT_SV_WARM] = x0p != NULL;
    if (x0p != NULL) {
        for (i = 0; i < 9; ++i) {
            s->m9[i] = x0R[i];
            if (!isfinite(x0R[i]))
                return CT_SOLVE_BAD_INPUT;
        }
        if (!(isfinite(x0p[0]) && isfinite(x0p[1]) && isfinite(x0p[2])))
            return CT_SOLVE_BAD_INPUT;
        f->p[0] = x0p[0];
        f->p[1] = x0p[1];
        f->p[2] = x0p[2];
        ct_nearest_rotation(s->m9, f->R, s->work, s->tol);
    }
    st[CT_SV_REACQUIRED] = 0.0;
    st[CT_SV_STATUS] = CT_SOLVE_RUNNING;
    st[CT_SV_PHASE] = x0p != NULL ? CT_PH_LM_START : solve_start_acquisition(s);
    return CT_SOLVE_RUNNING;
}

/* PoseSolver._publish_pose: the fit's rotation re-orthonormalised into rot, its position into pos */
static void solve_publish_pose(const struct ct_solve *s)
{
    const struct ct_posefit *f = s->f;
    memcpy(s->m9, f->R, 9 * sizeof(double));
    ct_nearest_rotation(s->m9, s->rot, s->work, s->tol);
    s->pos[0] = f->p[0];
    s->pos[1] = f->p[1];
    s->pos[2] = f->p[2];
}

/* PoseSolver._unit_finish (its compiled form, _unit_finish_compiled): the next phase */
static int solve_unit_finish(const struct ct_solve *s)
{
    const struct ct_lm *lm = s->lm;
    double *st = s->st, *lst = lm->st;
    struct ct_warmcheck w;
    int state = (int)lst[CT_LM_STATE], r, status;
    w.n = s->n;
    w.gate = s->gate;
    w.check_hemi = st[CT_SV_CHECK_HEMI] != 0.0;
    memcpy(w.cbar, s->cbar, 3 * sizeof(double));
    memcpy(w.hemi, st + CT_SV_HEMI, 3 * sizeof(double));
    r = ct_solve_finish(&w, st[CT_SV_WARM] != 0.0 && st[CT_SV_REACQUIRED] == 0.0, state, lst[CT_LM_COST], s->f->p,
                        lm->A[(int)lst[CT_LM_CUR]], s->cov, s->work);
    if (r < 0) {
        st[CT_SV_REACQUIRED] = 1.0;
        return solve_start_acquisition(s);
    }
    solve_publish_pose(s);
    st[CT_SV_ITERATIONS] = lst[CT_LM_IT];
    st[CT_SV_COST] = lst[CT_LM_COST];
    st[CT_SV_CONVERGED] = state == CT_LM_CONVERGED;
    status = state == CT_LM_CONVERGED ? CT_SOLVE_OK : CT_SOLVE_NOT_CONVERGED;
    if (!r)
        status |= CT_SOLVE_NONFINITE;
    if (st[CT_SV_REACQUIRED] != 0.0)
        status |= CT_SOLVE_REACQUIRED;
    st[CT_SV_STATUS] = status;
    return CT_PH_NONE;
}

/* staged.run_units over PoseSolver's units _unit_acquire, _unit_lm_start, _unit_lm_step and _unit_finish */
int ct_solve_run(const struct ct_solve *s, int64_t *spent, int64_t budget)
{
    const struct ct_lm *lm = s->lm;
    double *st = s->st;
    const int64_t cost = s->n;
    int phase = (int)st[CT_SV_PHASE];
    while (phase == CT_PH_LM_START || phase == CT_PH_LM_STEPS || phase == CT_PH_FINISH || phase == CT_PH_ACQ_UNITS) {
        if (*spent > 0 && *spent + cost > budget)
            break;
        if (phase == CT_PH_ACQ_UNITS) {
            phase = solve_unit_acquire(s);
        } else if (phase == CT_PH_LM_START) {
            ct_lm_pose_start(lm, s->f);
            phase = (int)lm->st[CT_LM_STATE] == CT_LM_RUNNING ? CT_PH_LM_STEPS : CT_PH_FINISH;
        } else if (phase == CT_PH_LM_STEPS) {
            if (ct_lm_pose_iterate(lm, s->f) != CT_LM_RUNNING)
                phase = CT_PH_FINISH;
        } else {
            phase = solve_unit_finish(s);
        }
        *spent += cost;
    }
    st[CT_SV_PHASE] = phase;
    return phase;
}
