/*
 * The CPython glue's binding of a pose fit and its Levenberg-Marquardt (struct ct_posefit and
 * struct ct_lm, coiltrack_core.h) to a PoseSolver's buffers, shared by _coremodule.c's PoseLM and
 * py_solve.c's SolveRun. Static inline; outside the firmware core (src/ never includes it).
 */
#ifndef CT_PY_POSEFIT_H
#define CT_PY_POSEFIT_H

#include "coiltrack_core.h"

/* the buffers' order: the fit's, then the LM's (the first CT_PY_POSEFIT_NBUF of a binding's list) */
enum { CT_PY_POSEFIT_NBUF = 18 };

/* f and lm over ptr[0..17] = geom, B, J, S, w, cur, h, H, p, p_t, R, R_t (the fit), A0, g0, A1, g1,
 * d, st (the LM), with the LM's parameters (pose/lm.py LevenbergMarquardt) */
static inline void ct_py_bind_posefit(struct ct_posefit *f, struct ct_lm *lm, int n, double *const *ptr,
                                      double lam0, double lam_max, int iters, double cost_tol, double step_sigma,
                                      double step_tol)
{
    f->n = n;
    f->geom = ptr[0];
    f->B = ptr[1];
    f->J = ptr[2];
    f->S = ptr[3];
    f->w = ptr[4];
    f->cur = ptr[5];
    f->h = ptr[6];
    f->H = ptr[7];
    f->p = ptr[8];
    f->p_t = ptr[9];
    f->R = ptr[10];
    f->R_t = ptr[11];
    f->step_tol = step_tol;
    lm->A[0] = ptr[12];
    lm->g[0] = ptr[13];
    lm->A[1] = ptr[14];
    lm->g[1] = ptr[15];
    lm->d = ptr[16];
    lm->st = ptr[17];
    lm->lam0 = lam0;
    lm->lam_max = lam_max;
    lm->iters = iters;
    lm->cost_tol = cost_tol;
    lm->step_sigma2 = step_sigma * step_sigma;
}

#endif /* CT_PY_POSEFIT_H */
