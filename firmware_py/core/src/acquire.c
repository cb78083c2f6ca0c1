/*
 * A pose solve's acquisition, unit by unit: see include/ct_acquire.h.  Each function follows the
 * Python named beside it operation by operation (-ffp-contract=off), so the start, the charges and
 * the decisions are the reference's to the bit (tests/firmware/core/test_core_acquire.py).
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* Python's max(a, b) and min(a, b) of floats: a unless b is greater (smaller) */
static double py_max(double a, double b)
{
    return b > a ? b : a;
}

static double py_min(double a, double b)
{
    return b < a ? b : a;
}

/* Python's x ** y of floats for a base >= 0 or an even integer y (float_pow: libm's pow of |x|;
 * the exponent read through a volatile so that no compiler turns pow(x, 2) into x * x) */
static double py_pow(double x, double y)
{
    volatile double e = y;
    return pow(fabs(x), e);
}

/* SignalModel.fields without the distortion map: n evaluations, counted */
static void aq_fields(const struct ct_acquire *a, double px, double py, double pz, int jac)
{
    ct_signal_fields(a->geom, a->n, px, py, pz, a->cur, jac, a->B, a->J);
    a->st[CT_AQ_EVALS] += 1.0;
}

/* linalg.atb3: out = X^T Y (3x3) for X, Y of rows rows of 3 */
static void aq_atb3(const double *x, const double *y, int rows, double *out)
{
    int i, c, j;
    for (i = 0; i < 3; ++i)
        for (c = 0; c < 3; ++c) {
            double acc = 0.0;
            for (j = 0; j < rows; ++j)
                acc += x[3 * j + i] * y[3 * j + c];
            out[3 * i + c] = acc;
        }
}

/* _Kuipers._moment: coil j's moment at its current (SignalModel.moment_per_amp times the current) */
static void kuipers_moment(const struct ct_acquire *a, int j, double *m)
{
    const double *g = a->geom + j * CT_COIL_STRIDE;
    const double mpa = g[CT_COIL_MPA], c = a->cur[j];
    m[0] = g[CT_COIL_AXIS] * mpa * c;
    m[1] = g[CT_COIL_AXIS + 1] * mpa * c;
    m[2] = g[CT_COIL_AXIS + 2] * mpa * c;
}

/* _Kuipers.pseudo_inverse: M^+ = M^T (M M^T)^-1; 0 if the moments do not span 3-D */
static int ct_kuipers_pseudo_inverse(const struct ct_acquire *a)
{
    double *wk = a->work, *G = wk + CT_AQW_G, *W = wk + CT_AQW_W, *w = wk + CT_AQW_WV;
    double *mp = wk + CT_AQ_WORK_FIXED + a->n * a->n, m[3];
    int i, j, b, c;
    for (i = 0; i < 9; ++i)
        G[i] = 0.0;
    for (j = 0; j < a->n; ++j) {
        kuipers_moment(a, j, m);
        for (i = 0; i < 3; ++i)
            for (b = 0; b < 3; ++b)
                G[3 * i + b] += m[i] * m[b];
    }
    memcpy(W, G, 9 * sizeof(double));
    ct_fin_jacobi_eigh(W, 3, w, wk + CT_AQW_V, 60);      /* the smallest singular value of M */
    if (!(w[0] > 0.0 && sqrt(w[0]) > 1e-9 * sqrt(py_max(w[2], 0.0))))
        return 0;
    if (!ct_spd_inverse(3, G, W, wk + CT_AQW_L, wk + CT_AQW_LM))   /* W = (M M^T)^-1 (chol_inverse) */
        return 0;
    for (j = 0; j < a->n; ++j) {
        kuipers_moment(a, j, m);
        for (c = 0; c < 3; ++c)
            mp[3 * j + c] = m[0] * W[c] + m[1] * W[3 + c] + m[2] * W[6 + c];
    }
    return 1;
}

/* _Kuipers.position: the position from U = (S M^+)^T (S M^+) = k^2 (I + 3 u u^T) on the side of
 * the hemisphere (thesis eqs 5.15-5.17) into p */
static void ct_kuipers_position(const struct ct_acquire *a)
{
    double *wk = a->work, *S3 = wk + CT_AQW_S3, *W = wk + CT_AQW_W, *v = wk + CT_AQW_V, *st = a->st;
    const double *h = st + CT_AQ_H;
    double tr, k, ux, uy, uz, r;
    aq_atb3(a->S, wk + CT_AQ_WORK_FIXED + a->n * a->n, a->n, S3);
    aq_atb3(S3, S3, 3, W);
    tr = W[0] + W[4] + W[8];
    k = py_max(sqrt(py_max(tr / 6.0, 0.0)), 1e-300);
    ct_fin_jacobi_eigh(W, 3, wk + CT_AQW_WV, v, 60);
    ux = v[2];
    uy = v[5];
    uz = v[8];
    if (ux * h[0] + uy * h[1] + uz * h[2] < 0.0) {
        ux = -ux;
        uy = -uy;
        uz = -uz;
    }
    r = py_pow(a->mu0_4pi / k, 1.0 / 3.0);
    st[CT_AQ_KU] = ux;
    st[CT_AQ_KU + 1] = uy;
    st[CT_AQ_KU + 2] = uz;
    st[CT_AQ_KK] = k;
    a->p[0] = r * ux + a->cbar[0];
    a->p[1] = r * uy + a->cbar[1];
    a->p[2] = r * uz + a->cbar[2];
}

/* _Kuipers.rotation: R = polar(A S3^T / k), A = 1.5 u u^T - I (thesis eqs 5.30-5.34) */
static void ct_kuipers_rotation(const struct ct_acquire *a)
{
    double *wk = a->work, *S3 = wk + CT_AQW_S3, *W = wk + CT_AQW_W;
    const double *u = a->st + CT_AQ_KU, k = a->st[CT_AQ_KK];
    int i, c, l;
    for (i = 0; i < 3; ++i)
        for (c = 0; c < 3; ++c) {
            double acc = 0.0;
            for (l = 0; l < 3; ++l)
                acc += (1.5 * u[i] * u[l] - (i == l ? 1.0 : 0.0)) * S3[3 * c + l];
            W[3 * i + c] = acc / k;
        }
    ct_nearest_rotation(W, a->R, wk + CT_AQW_NEAR, a->tol);
}

/* Acquisition._invariants: U = S^T S, its trace and the noise level of its misfit */
static void invariants(const struct ct_acquire *a)
{
    const int n = a->n;
    const double *S = a->S;
    double *U = a->work + CT_AQ_WORK_FIXED, tr = 0.0;
    int i, j;
    for (i = 0; i < n; ++i) {
        for (j = 0; j < n; ++j)
            U[i * n + j] = S[3 * i] * S[3 * j] + S[3 * i + 1] * S[3 * j + 1] + S[3 * i + 2] * S[3 * j + 2];
        tr += U[i * n + i];
    }
    a->st[CT_AQ_TR] = tr;
    a->st[CT_AQ_TOL] = 20.0 * a->st[CT_AQ_SIGMA_RMS] / sqrt(py_max(tr, 1e-300)) + 1e-9;
}

/* Acquisition._invariant_residual: the cost of (U_ij - B_i . B_j) / tr U over i <= j and its
 * normal equations (3x3 A, g = -Jr^T r) */
static double invariant_residual(const struct ct_acquire *a, double px, double py, double pz, double *A, double *g)
{
    const int n = a->n;
    const double *B = a->B, *J = a->J, *U = a->work + CT_AQ_WORK_FIXED;
    const double scale = 1.0 / a->st[CT_AQ_TR];
    double cost = 0.0;
    int i, j;
    aq_fields(a, px, py, pz, 1);
    for (i = 0; i < 9; ++i)
        A[i] = 0.0;
    g[0] = g[1] = g[2] = 0.0;
    for (i = 0; i < n; ++i) {
        const double bi0 = B[3 * i], bi1 = B[3 * i + 1], bi2 = B[3 * i + 2];
        const int oi = 9 * i;
        for (j = i; j < n; ++j) {
            const double bj0 = B[3 * j], bj1 = B[3 * j + 1], bj2 = B[3 * j + 2];
            const double r = (U[i * n + j] - (bi0 * bj0 + bi1 * bj1 + bi2 * bj2)) * scale;
            const int oj = 9 * j;
            double d0, d1, d2;
            cost += r * r;
            d0 = -(J[oi] * bj0 + J[oi + 3] * bj1 + J[oi + 6] * bj2 + bi0 * J[oj] + bi1 * J[oj + 3] +
                   bi2 * J[oj + 6]) * scale;
            d1 = -(J[oi + 1] * bj0 + J[oi + 4] * bj1 + J[oi + 7] * bj2 + bi0 * J[oj + 1] + bi1 * J[oj + 4] +
                   bi2 * J[oj + 7]) * scale;
            d2 = -(J[oi + 2] * bj0 + J[oi + 5] * bj1 + J[oi + 8] * bj2 + bi0 * J[oj + 2] + bi1 * J[oj + 5] +
                   bi2 * J[oj + 8]) * scale;
            A[0] += d0 * d0;
            A[1] += d0 * d1;
            A[2] += d0 * d2;
            A[4] += d1 * d1;
            A[5] += d1 * d2;
            A[8] += d2 * d2;
            g[0] -= d0 * r;
            g[1] -= d1 * r;
            g[2] -= d2 * r;
        }
    }
    A[3] = A[1];
    A[6] = A[2];
    A[7] = A[5];
    return cost;
}

/* Acquisition.evaluate, trial, accept, small: the invariant fit as the LM's problem */
static double aq_evaluate(void *ctx, double *A, double *g)
{
    const struct ct_acquire *a = (const struct ct_acquire *)ctx;
    const double *ip = a->work + CT_AQW_IP;
    return invariant_residual(a, ip[0], ip[1], ip[2], A, g);
}

static double aq_trial(void *ctx, const double *d, double *A, double *g)
{
    const struct ct_acquire *a = (const struct ct_acquire *)ctx;
    const double *ip = a->work + CT_AQW_IP;
    double *tp = a->work + CT_AQW_TP;
    tp[0] = ip[0] + d[0];
    tp[1] = ip[1] + d[1];
    tp[2] = ip[2] + d[2];
    return invariant_residual(a, tp[0], tp[1], tp[2], A, g);
}

static void aq_accept(void *ctx)
{
    const struct ct_acquire *a = (const struct ct_acquire *)ctx;
    memcpy(a->work + CT_AQW_IP, a->work + CT_AQW_TP, 3 * sizeof(double));
}

static int aq_small(void *ctx, const double *d)
{
    const struct ct_acquire *a = (const struct ct_acquire *)ctx;
    const double *tp = a->work + CT_AQW_TP;
    return sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]) <= 1e-9 * sqrt(tp[0] * tp[0] + tp[1] * tp[1] + tp[2] * tp[2]);
}

static void aq_problem(struct ct_lm_problem *pr, const struct ct_acquire *a)
{
    pr->k = 3;
    pr->ctx = (void *)a;
    pr->evaluate = aq_evaluate;
    pr->trial = aq_trial;
    pr->accept = aq_accept;
    pr->small = aq_small;
    pr->solve = ct_damped_spd_solve_3;
}

/* Acquisition._trace_at: sum of B's squares at p (n evaluations) */
static double trace_at(const struct ct_acquire *a, double px, double py, double pz)
{
    const double *B = a->B;
    double tr = 0.0;
    int q;
    aq_fields(a, px, py, pz, 0);
    for (q = 0; q < 3 * a->n; ++q)
        tr += B[q] * B[q];
    return tr > 0.0 ? tr : 0.0;
}

/* Acquisition._misfit_at: |U - B(p)^T B(p)|_F / tr U (n evaluations) */
static double misfit_at(const struct ct_acquire *a, double px, double py, double pz)
{
    const int n = a->n;
    const double *B = a->B, *U = a->work + CT_AQ_WORK_FIXED;
    double mis = 0.0;
    int i, j;
    aq_fields(a, px, py, pz, 0);
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            const double e = B[3 * i] * B[3 * j] + B[3 * i + 1] * B[3 * j + 1] + B[3 * i + 2] * B[3 * j + 2] -
                             U[i * n + j];
            mis += e * e;
        }
    return sqrt(mis) / a->st[CT_AQ_TR];
}

/* Acquisition._keep_candidate: into the short list of the best grid points (sorted) */
static void keep_candidate(const struct ct_acquire *a, double mis, double px, double py, double pz)
{
    double *cm = a->work + CT_AQW_CAND_M, *cp = a->work + CT_AQW_CAND_P;
    int c = CT_AQ_GRID_CANDIDATES - 1;
    if (!(mis < cm[c]))
        return;
    while (c > 0 && mis < cm[c - 1]) {
        cm[c] = cm[c - 1];
        cp[3 * c] = cp[3 * c - 3];
        cp[3 * c + 1] = cp[3 * c - 2];
        cp[3 * c + 2] = cp[3 * c - 1];
        --c;
    }
    cm[c] = mis;
    cp[3 * c] = px;
    cp[3 * c + 1] = py;
    cp[3 * c + 2] = pz;
}

/* Acquisition._next_candidate: refine the next candidate, or the orientation */
static int next_candidate(const struct ct_acquire *a)
{
    const int c = (int)a->st[CT_AQ_CAND];
    if (c < CT_AQ_GRID_CANDIDATES && isfinite(a->work[CT_AQW_CAND_M + c])) {
        memcpy(a->work + CT_AQW_IP, a->work + CT_AQW_CAND_P + 3 * c, 3 * sizeof(double));
        return CT_AQ_REFINE_START;
    }
    return CT_AQ_ORIENT;
}

/* Acquisition._seek_direction: _k advanced to the next grid direction in the hemisphere */
static int seek_direction(const struct ct_acquire *a)
{
    double *st = a->st;
    const double hx = st[CT_AQ_H], hy = st[CT_AQ_H + 1], hz = st[CT_AQ_H + 2], *g = a->grid;
    const int use_h = hx != 0.0 || hy != 0.0 || hz != 0.0;
    int k = (int)st[CT_AQ_K];
    while (k < CT_AQ_GRID_DIRECTIONS && use_h && g[3 * k] * hx + g[3 * k + 1] * hy + g[3 * k + 2] * hz < 0.0)
        ++k;
    st[CT_AQ_K] = k;
    if (k < CT_AQ_GRID_DIRECTIONS) {
        st[CT_AQ_RAD] = st[CT_AQ_R0];
        st[CT_AQ_RSTEP] = 0.0;
        return CT_AQ_RADIUS;
    }
    st[CT_AQ_CAND] = 0.0;
    return next_candidate(a);
}

/* Acquisition._start_grid */
static int start_grid(const struct ct_acquire *a)
{
    int c;
    for (c = 0; c < CT_AQ_GRID_CANDIDATES; ++c)
        a->work[CT_AQW_CAND_M + c] = INFINITY;
    a->st[CT_AQ_K] = 0.0;
    return seek_direction(a);
}

/* Acquisition._refined: keep the better fit; the next candidate, the grid or the orientation */
static int refined(const struct ct_acquire *a)
{
    double *st = a->st;
    const double m = sqrt(a->lm->st[CT_LM_COST]);
    if (st[CT_AQ_CAND] < 0.0 || m < st[CT_AQ_BEST_M]) {
        st[CT_AQ_BEST_M] = m;
        memcpy(a->work + CT_AQW_BEST, a->work + CT_AQW_IP, 3 * sizeof(double));
    }
    if (st[CT_AQ_CAND] >= 0.0) {
        st[CT_AQ_CAND] += 1.0;
        return next_candidate(a);
    }
    if (m <= st[CT_AQ_TOL])
        return CT_AQ_ORIENT;
    return start_grid(a);
}

/* Acquisition._unit_kuipers_rotation: Kuipers' orientation, then the near-field refinement or done */
static int unit_kuipers_rotation(const struct ct_acquire *a)
{
    double *st = a->st, *ip = a->work + CT_AQW_IP;
    const double *p = a->p, *c = a->cbar;
    double r0;
    ct_kuipers_rotation(a);
    r0 = sqrt(py_pow(p[0] - c[0], 2.0) + py_pow(p[1] - c[1], 2.0) + py_pow(p[2] - c[2], 2.0));
    if (!(r0 < a->near))
        return CT_AQ_NONE;
    st[CT_AQ_R0] = r0;
    invariants(a);
    memcpy(ip, p, 3 * sizeof(double));
    st[CT_AQ_CAND] = -1.0;
    return CT_AQ_REFINE_START;
}

/* Acquisition._unit_radius: one power-law step of direction _k's radius (n evaluations) */
static int unit_radius(const struct ct_acquire *a)
{
    double *st = a->st;
    const double *g = a->grid + 3 * (int)st[CT_AQ_K], *c = a->cbar, r0 = st[CT_AQ_R0];
    double rad = st[CT_AQ_RAD], f;
    f = py_pow(trace_at(a, c[0] + g[0] * rad, c[1] + g[1] * rad, c[2] + g[2] * rad) / st[CT_AQ_TR], 1.0 / 6.0);
    rad = isfinite(f) ? rad * f : rad;
    st[CT_AQ_RAD] = isfinite(rad) ? py_min(py_max(rad, 0.25 * r0), 4.0 * r0) : 0.25 * r0;
    st[CT_AQ_RSTEP] += 1.0;
    return st[CT_AQ_RSTEP] == 2.0 ? CT_AQ_MISFIT : CT_AQ_RADIUS;
}

/* Acquisition._unit_misfit: direction _k scored at its radius (n evaluations), go on */
static int unit_misfit(const struct ct_acquire *a)
{
    double *st = a->st;
    const int k = (int)st[CT_AQ_K];
    const double *g = a->grid + 3 * k, *c = a->cbar, rad = st[CT_AQ_RAD];
    const double px = c[0] + g[0] * rad, py = c[1] + g[1] * rad, pz = c[2] + g[2] * rad;
    const double mis = misfit_at(a, px, py, pz);
    if (isfinite(mis))
        keep_candidate(a, mis, px, py, pz);
    st[CT_AQ_K] = k + 1;
    return seek_direction(a);
}

/* Acquisition._unit_orient: p = the best point, R = polar(B(p) S^T) (n evaluations) */
static int unit_orient(const struct ct_acquire *a)
{
    const double *b = a->work + CT_AQW_BEST;
    double *M = a->work + CT_AQW_MO;
    memcpy(a->p, b, 3 * sizeof(double));
    aq_fields(a, b[0], b[1], b[2], 0);
    aq_atb3(a->B, a->S, a->n, M);
    ct_nearest_rotation(M, a->R, a->work + CT_AQW_NEAR, a->tol);
    return CT_AQ_NONE;
}

void ct_acquire_bind(struct ct_acquire *a, struct ct_lm *lm)
{
    double *wk = a->work;
    lm->lam0 = 1e-3;
    lm->lam_max = 1e8;
    lm->cost_tol = 0.0;
    lm->step_sigma2 = 0.0;
    lm->iters = CT_AQ_INV_ITERS;
    lm->A[0] = wk + CT_AQW_A0;
    lm->g[0] = wk + CT_AQW_G0;
    lm->A[1] = wk + CT_AQW_A1;
    lm->g[1] = wk + CT_AQW_G1;
    lm->d = wk + CT_AQW_D;
    lm->st = wk + CT_AQW_LMST;
    a->lm = lm;
}

/* Acquisition.begin */
void ct_acquire_begin(const struct ct_acquire *a, double hx, double hy, double hz, double sigma_rms)
{
    double *st = a->st;
    st[CT_AQ_H] = hx;
    st[CT_AQ_H + 1] = hy;
    st[CT_AQ_H + 2] = hz;
    st[CT_AQ_SIGMA_RMS] = sigma_rms;
    st[CT_AQ_OK] = 0.0;
    st[CT_AQ_UNIT] = CT_AQ_MOMENTS;
}

/* the units of Acquisition: _unit_moments, _unit_kuipers_position, _unit_kuipers_rotation,
 * _unit_refine_start, _unit_refine_step, _unit_radius, _unit_misfit, _unit_orient */
int ct_acquire_unit(const struct ct_acquire *a)
{
    double *st = a->st;
    struct ct_lm_problem pr;
    int unit = (int)st[CT_AQ_UNIT];
    switch (unit) {
    case CT_AQ_MOMENTS:
        unit = ct_kuipers_pseudo_inverse(a) ? CT_AQ_KUIPERS_POSITION : CT_AQ_NONE;
        break;
    case CT_AQ_KUIPERS_POSITION:
        ct_kuipers_position(a);
        st[CT_AQ_OK] = 1.0;
        unit = CT_AQ_KUIPERS_ROTATION;
        break;
    case CT_AQ_KUIPERS_ROTATION:
        unit = unit_kuipers_rotation(a);
        break;
    case CT_AQ_REFINE_START:
        aq_problem(&pr, a);
        ct_lm_start(a->lm, &pr);
        unit = CT_AQ_REFINE_STEP;
        break;
    case CT_AQ_REFINE_STEP:
        aq_problem(&pr, a);
        if (ct_lm_iterate(a->lm, &pr) != CT_LM_RUNNING)
            unit = refined(a);
        break;
    case CT_AQ_RADIUS:
        unit = unit_radius(a);
        break;
    case CT_AQ_MISFIT:
        unit = unit_misfit(a);
        break;
    case CT_AQ_ORIENT:
        unit = unit_orient(a);
        break;
    default:
        unit = CT_AQ_NONE;
    }
    st[CT_AQ_UNIT] = unit;
    return unit;
}
