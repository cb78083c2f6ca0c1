/*
 * The pose solver's Levenberg-Marquardt step with its cost: the compiled form of
 * coiltrack.firmware.pose.lm.LevenbergMarquardt (start, iterate, _step, _metric2,
 * _raise_damping) over a problem's callbacks (ct_lm_problem: evaluate, trial, accept, small and
 * its size's damped solve), for the problem coiltrack.firmware.pose.solver._PoseFit (evaluate,
 * trial, accept, small, _cost) and the acquisition's invariant fit (acquire.c).
 *
 * The cost is sum ((S - h(p, R)) w)^2 with h and its Jacobian H from the signal model (Schepers &
 * Veltink seeds/000_e46ec0e8bf7ea271.txt eqs 5-11) and the normal equations a = H^T W H,
 * g = H^T W (S - h) accumulated in the Python's order.  Each step solves (a + lam diag a) d = g
 * (linalg.damped_spd_solve(6), generated straight-line into linalg_gen.c), tries
 * (p + d_p, R exp([d_theta]x)) and accepts it if the cost does not grow.  Same operations in the
 * same order as the Python (the trial rotation's 3x3 product included), so with -ffp-contract=off
 * the same result to the bit.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* _PoseFit._cost: weighted cost at (p, R) and the normal equations a (6x6 row-major), g (6) */
double ct_pose_cost(const struct ct_posefit *f, const double *p, const double *R, double *a, double *g)
{
    double g0 = 0.0, g1 = 0.0, g2 = 0.0, g3 = 0.0, g4 = 0.0, g5 = 0.0;
    double a00 = 0.0, a01 = 0.0, a02 = 0.0, a03 = 0.0, a04 = 0.0, a05 = 0.0, a11 = 0.0, a12 = 0.0;
    double a13 = 0.0, a14 = 0.0, a15 = 0.0, a22 = 0.0, a23 = 0.0, a24 = 0.0, a25 = 0.0, a33 = 0.0;
    double a34 = 0.0, a35 = 0.0, a44 = 0.0, a45 = 0.0, a55 = 0.0;
    double cost = 0.0;
    const double *h = f->h, *H = f->H, *S = f->S, *w = f->w;
    int q, m = 3 * f->n;

    ct_signal_fields(f->geom, f->n, p[0], p[1], p[2], f->cur, 1, f->B, f->J);
    ct_signal_project_jac(f->n, R, f->B, f->J, f->h, f->H);
    for (q = 0; q < m; ++q) {
        double wq = w[q];
        double w2 = wq * wq;
        double e = S[q] - h[q];
        double rr = e * w2;
        const double *Hq = H + 6 * q;
        double h0 = Hq[0], h1 = Hq[1], h2 = Hq[2], h3 = Hq[3], h4 = Hq[4], h5 = Hq[5];
        double b0, b1, b2, b3, b4;
        cost += e * e * w2;
        g0 += h0 * rr;
        g1 += h1 * rr;
        g2 += h2 * rr;
        g3 += h3 * rr;
        g4 += h4 * rr;
        g5 += h5 * rr;
        b0 = h0 * w2;
        b1 = h1 * w2;
        b2 = h2 * w2;
        b3 = h3 * w2;
        b4 = h4 * w2;
        a00 += b0 * h0;
        a01 += b0 * h1;
        a02 += b0 * h2;
        a03 += b0 * h3;
        a04 += b0 * h4;
        a05 += b0 * h5;
        a11 += b1 * h1;
        a12 += b1 * h2;
        a13 += b1 * h3;
        a14 += b1 * h4;
        a15 += b1 * h5;
        a22 += b2 * h2;
        a23 += b2 * h3;
        a24 += b2 * h4;
        a25 += b2 * h5;
        a33 += b3 * h3;
        a34 += b3 * h4;
        a35 += b3 * h5;
        a44 += b4 * h4;
        a45 += b4 * h5;
        a55 += h5 * h5 * w2;
    }
    g[0] = g0; g[1] = g1; g[2] = g2; g[3] = g3; g[4] = g4; g[5] = g5;
    a[0] = a00; a[1] = a01; a[2] = a02; a[3] = a03; a[4] = a04; a[5] = a05;
    a[6] = a01; a[7] = a11; a[8] = a12; a[9] = a13; a[10] = a14; a[11] = a15;
    a[12] = a02; a[13] = a12; a[14] = a22; a[15] = a23; a[16] = a24; a[17] = a25;
    a[18] = a03; a[19] = a13; a[20] = a23; a[21] = a33; a[22] = a34; a[23] = a35;
    a[24] = a04; a[25] = a14; a[26] = a24; a[27] = a34; a[28] = a44; a[29] = a45;
    a[30] = a05; a[31] = a15; a[32] = a25; a[33] = a35; a[34] = a45; a[35] = a55;
    return cost;
}

/* _PoseFit.trial: the cost at (p + d_p, R exp([d_theta]x)), kept aside in p_t, R_t */
static double ct_pose_trial(const struct ct_posefit *f, const double *d, double *a, double *g)
{
    double E[9];
    const double *R = f->R;
    double *Rt = f->R_t;
    int i, j;
    f->p_t[0] = f->p[0] + d[0];
    f->p_t[1] = f->p[1] + d[1];
    f->p_t[2] = f->p[2] + d[2];
    ct_exp_rotvec(d[3], d[4], d[5], E);
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            Rt[3 * i + j] = R[3 * i] * E[j] + R[3 * i + 1] * E[3 + j] + R[3 * i + 2] * E[6 + j];
    return ct_pose_cost(f, f->p_t, f->R_t, a, g);
}

/* _PoseFit.small: a step below the fit's resolution */
int ct_pose_small(const struct ct_posefit *f, const double *d)
{
    const double *p = f->p;
    double pn = sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]);
    double tol = f->step_tol;
    double lim = 1e-3 > pn ? 1e-3 : pn;      /* Python's max(pn, 1e-3) */
    return sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) <= tol * lim &&
           sqrt(d[3] * d[3] + d[4] * d[4] + d[5] * d[5]) <= tol;
}

/* _PoseFit's evaluate, trial, accept and small as the LM's problem (ct_lm_problem) */
static double pose_evaluate(void *ctx, double *a, double *g)
{
    const struct ct_posefit *f = (const struct ct_posefit *)ctx;
    return ct_pose_cost(f, f->p, f->R, a, g);
}

static double pose_trial(void *ctx, const double *d, double *a, double *g)
{
    return ct_pose_trial((const struct ct_posefit *)ctx, d, a, g);
}

static void pose_accept(void *ctx)
{
    const struct ct_posefit *f = (const struct ct_posefit *)ctx;
    memcpy(f->p, f->p_t, 3 * sizeof(double));
    memcpy(f->R, f->R_t, 9 * sizeof(double));
}

static int pose_small(void *ctx, const double *d)
{
    return ct_pose_small((const struct ct_posefit *)ctx, d);
}

static void pose_problem(struct ct_lm_problem *pr, const struct ct_posefit *f)
{
    pr->k = 6;
    pr->ctx = (void *)f;
    pr->evaluate = pose_evaluate;
    pr->trial = pose_trial;
    pr->accept = pose_accept;
    pr->small = pose_small;
    pr->solve = ct_damped_spd_solve_6;
}

/* LevenbergMarquardt.start: one evaluation of the problem at its current parameters */
void ct_lm_start(const struct ct_lm *lm, const struct ct_lm_problem *pr)
{
    double *st = lm->st;
    st[CT_LM_CUR] = 0.0;
    st[CT_LM_COST] = pr->evaluate(pr->ctx, lm->A[0], lm->g[0]);
    st[CT_LM_LAM] = lm->lam0;
    st[CT_LM_IT] = 0.0;
    st[CT_LM_STATE] = lm->iters > 0 ? CT_LM_RUNNING : CT_LM_STOPPED;
    st[CT_LM_EVALS] += 1.0;
}

/* LevenbergMarquardt._raise_damping */
static void ct_lm_raise_damping(double *st, double lam_max)
{
    st[CT_LM_LAM] *= 10.0;
    if (st[CT_LM_LAM] > lam_max)
        st[CT_LM_STATE] = CT_LM_STOPPED;
}

/* LevenbergMarquardt._metric2: d^T A d of the step just solved, as d^T g - lam d^T D d */
static double ct_lm_metric2(const struct ct_lm *lm, int k, int c)
{
    const double *d = lm->d, *g = lm->g[c], *a = lm->A[c];
    double dg = 0.0, dd = 0.0, lam = lm->st[CT_LM_LAM];
    int i;
    for (i = 0; i < k; ++i) {
        double di = d[i];
        double da = a[i * (k + 1)];
        dg += di * g[i];
        dd += (da > 0.0 ? da : 1.0) * di * di;
    }
    return dg - lam * dd;
}

/* LevenbergMarquardt._step */
static void ct_lm_step(const struct ct_lm *lm, const struct ct_lm_problem *pr, int c)
{
    double *st = lm->st, cost = st[CT_LM_COST], cost_t, den;
    const double *d = lm->d;
    int i, small;
    for (i = 0; i < pr->k; ++i) {
        if (!isfinite(d[i])) {
            st[CT_LM_STATE] = CT_LM_STOPPED;
            return;
        }
    }
    cost_t = pr->trial(pr->ctx, d, lm->A[1 - c], lm->g[1 - c]);
    st[CT_LM_EVALS] += 1.0;
    small = pr->small(pr->ctx, d) || (lm->step_sigma2 > 0.0 && ct_lm_metric2(lm, pr->k, c) < lm->step_sigma2);
    den = 1e-300 > cost ? 1e-300 : cost;         /* max(cost, 1e-300) */
    if (isfinite(cost_t) && cost_t <= cost) {
        double rel = (cost - cost_t) / den, lam = st[CT_LM_LAM] * 0.1;
        pr->accept(pr->ctx);
        st[CT_LM_CUR] = (double)(1 - c);
        st[CT_LM_COST] = cost_t;
        st[CT_LM_LAM] = 1e-12 > lam ? 1e-12 : lam;  /* max(lam * 0.1, _LAM_MIN) */
        if (small || rel < lm->cost_tol)
            st[CT_LM_STATE] = CT_LM_CONVERGED;
    } else if (small || (cost_t - cost) < lm->cost_tol * den) {
        st[CT_LM_STATE] = CT_LM_CONVERGED;        /* the cost is flat to its rounding level */
    } else {
        ct_lm_raise_damping(st, lm->lam_max);
    }
}

/* LevenbergMarquardt.iterate: one damped step, at most one evaluation */
int ct_lm_iterate(const struct ct_lm *lm, const struct ct_lm_problem *pr)
{
    double *st = lm->st;
    int c = (int)st[CT_LM_CUR];
    st[CT_LM_IT] += 1.0;
    if (pr->solve(lm->A[c], lm->g[c], lm->d, st[CT_LM_LAM]))
        ct_lm_step(lm, pr, c);
    else
        ct_lm_raise_damping(st, lm->lam_max);
    if (st[CT_LM_STATE] == CT_LM_RUNNING && st[CT_LM_IT] >= lm->iters)
        st[CT_LM_STATE] = CT_LM_STOPPED;
    return (int)st[CT_LM_STATE];
}

/* LevenbergMarquardt.start on the pose fit */
void ct_lm_pose_start(const struct ct_lm *lm, const struct ct_posefit *f)
{
    struct ct_lm_problem pr;
    pose_problem(&pr, f);
    ct_lm_start(lm, &pr);
}

/* LevenbergMarquardt.iterate on the pose fit */
int ct_lm_pose_iterate(const struct ct_lm *lm, const struct ct_posefit *f)
{
    struct ct_lm_problem pr;
    pose_problem(&pr, f);
    return ct_lm_iterate(lm, &pr);
}
