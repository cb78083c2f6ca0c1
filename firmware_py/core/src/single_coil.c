/*
 * The single-coil error-state EKF: the compiled form of coiltrack.firmware.estimate.single_coil
 * (SchepersEKF), estimate.clones (PoseClones) and estimate.single_coil_update (SingleCoilUpdate).
 *
 * Schepers & Veltink 2010 (seeds/000_e46ec0e8bf7ea271.txt) sec. 2.1: inertial propagation
 * between single-coil magnetic updates, y = I R^T B_c(p) + v (eq 5), linearised with eqs 9-11,
 * corrected with eq 4; the strapdown error model of the thesis' complementary filter
 * (seeds/002_cd7f1fdb7fc67471.txt eqs 6.10-6.17) for a sensor-frame orientation error:
 *
 *     R_mid = R exp([w dt/2]x),  a = R_mid f - f_ref,  p += v dt + a dt^2/2,  v += a dt,
 *     R = R_mid exp([w dt/2]x),  P <- F P F^T + diag(q)
 *
 * The scalar steps are the reference's operations in the same order; the products the reference
 * hands to BLAS (F P F^T, P H^T, H P H^T, H dx, R dR) are summed here in increasing index order
 * with F's and H's structural zeros skipped, so they agree to rounding, not bit for bit.
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* SchepersEKF._fill_q: the core block's diagonal process noise over dt (s) */
void ct_sc_fill_q(const struct ct_sc *s, double *q, double dt)
{
    double qp = s->qa * dt * dt * dt / 3.0 + s->qpos * dt;
    double qv = s->qa * dt;
    double qo = s->qg * dt;
    double qba = s->qba * dt;
    double qbg = s->qbg * dt;
    int i;
    for (i = 0; i < 3; ++i) {
        q[CT_POS + i] = qp;
        q[CT_VEL + i] = qv;
        q[CT_ORI + i] = qo;
        q[CT_ACC + i] = qba;
        q[CT_GYR + i] = qbg;
    }
}

/* strapdown._put: A[r0:r0+3, c0:c0+3] = s R (A n x n) */
static void put3(double *A, int n, int r0, int c0, double s, const double *R)
{
    int i;
    for (i = 0; i < 3; ++i) {
        double *a = A + (r0 + i) * n + c0;
        a[0] = s * R[3 * i];
        a[1] = s * R[3 * i + 1];
        a[2] = s * R[3 * i + 2];
    }
}

/* SchepersEKF._build_F: strapdown.transition_static (ka = kg = 1) and transition_sensor into the
 * core block of F (n x n, n >= 15; the other entries untouched) and _fill_q into q (15) */
void ct_sc_build_F(const struct ct_sc *s, double *F, int n, double *q, double dt)
{
    const double *R = s->R;
    double fx = s->f[0], fy = s->f[1], fz = s->f[2];
    double wx = s->w[0], wy = s->w[1], wz = s->w[2];
    double h2 = -0.5 * dt * dt;
    int i;
    for (i = 0; i < 3; ++i) {                      /* transition_static */
        F[(CT_POS + i) * n + CT_VEL + i] = dt;
        F[(CT_ACC + i) * n + CT_ACC + i] = 1.0;
        F[(CT_GYR + i) * n + CT_GYR + i] = 1.0;
    }
    for (i = 0; i < 3; ++i) {                      /* transition_sensor */
        double r0 = R[3 * i], r1 = R[3 * i + 1], r2 = R[3 * i + 2];
        double m0 = r1 * fz - r2 * fy;
        double m1 = r2 * fx - r0 * fz;
        double m2 = r0 * fy - r1 * fx;
        double *a = F + (CT_POS + i) * n + CT_ORI, *b = F + (CT_VEL + i) * n + CT_ORI;
        a[0] = h2 * m0;
        a[1] = h2 * m1;
        a[2] = h2 * m2;
        b[0] = -dt * m0;
        b[1] = -dt * m1;
        b[2] = -dt * m2;
        F[(CT_ORI + i) * n + CT_GYR + i] = -dt;
    }
    put3(F, n, CT_POS, CT_ACC, h2, R);
    put3(F, n, CT_VEL, CT_ACC, -dt, R);
    ct_exp_rotvec(-wx * dt, -wy * dt, -wz * dt, s->E);
    put3(F, n, CT_ORI, CT_ORI, 1.0, s->E);
    ct_sc_fill_q(s, q, dt);
}

/* F's non-zero entries row by row (n <= NZ_MAXN, at most NZ_ROW a row; the filter's transition
 * has 8): row i's columns are col[i * NZ_ROW .. + cnt[i]) */
#define NZ_MAXN 64
#define NZ_ROW 16
struct nzrows {
    uint8_t cnt[NZ_MAXN];
    uint8_t col[NZ_MAXN * NZ_ROW];
};

/* 1 with the lists filled, 0 when F does not fit them (then ct_congruence_sparse) */
static int nz_rows(int n, const double *F, struct nzrows *z)
{
    int i, k;
    if (n > NZ_MAXN)
        return 0;
    for (i = 0; i < n; ++i) {
        int m = 0;
        for (k = 0; k < n; ++k)
            if (F[i * n + k] != 0.0) {
                if (m == NZ_ROW)
                    return 0;
                z->col[i * NZ_ROW + m++] = (uint8_t)k;
            }
        z->cnt[i] = (uint8_t)m;
    }
    return 1;
}

/* P <- F P F^T (ekf.c ct_congruence_sparse's sums: each element over F's non-zero entries in
 * increasing index order from 0, so the same bits), from F's non-zero lists z; T scratch */
static void congruence_rows(int n, const double *F, const struct nzrows *z, double *P, double *T)
{
    int i, j, m;
    for (i = 0; i < n; ++i) {                      /* T = F P */
        double *Ti = T + i * n;
        const uint8_t *ci = z->col + i * NZ_ROW;
        for (j = 0; j < n; ++j)
            Ti[j] = 0.0;
        for (m = 0; m < z->cnt[i]; ++m) {
            int k = ci[m];
            double a = F[i * n + k];
            const double *Pk = P + k * n;
            for (j = 0; j < n; ++j)
                Ti[j] += a * Pk[j];
        }
    }
    for (i = 0; i < n; ++i) {                      /* P = T F^T */
        const double *Ti = T + i * n;
        for (j = 0; j < n; ++j) {
            const double *Fj = F + j * n;
            const uint8_t *cj = z->col + j * NZ_ROW;
            double x = 0.0;
            for (m = 0; m < z->cnt[j]; ++m) {
                int k = cj[m];
                x += Ti[k] * Fj[k];
            }
            P[i * n + j] = x;
        }
    }
}

/* P <- F P F^T, then P_ii += q_i (n x n; T scratch), F's zero entries skipped */
static void fpf_q(int n, const double *F, double *P, const double *q, double *T)
{
    struct nzrows z = {{0}, {0}};
    int i;
    if (nz_rows(n, F, &z))
        congruence_rows(n, F, &z, P, T);
    else
        ct_congruence_sparse(n, F, P, T);
    for (i = 0; i < n; ++i)
        P[i * n + i] += q[i];
}

/* SchepersEKF._accel: R f - f_ref */
static void accel(const struct ct_sc *s, double *a)
{
    ct_to_nav(s->R, s->f[0], s->f[1], s->f[2], a);
    a[0] = a[0] - s->fref[0];
    a[1] = a[1] - s->fref[1];
    a[2] = a[2] - s->fref[2];
}

/* SchepersEKF._orthonormalize: one Newton step of the polar decomposition, R (3 I - R^T R) / 2 */
static void orthonormalize(struct ct_sc *s)
{
    double *R = s->R, *R2 = s->R2, *dR = s->dR;
    int i, j;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            R2[3 * i + j] = -(R[i] * R[j] + R[3 + i] * R[3 + j] + R[6 + i] * R[6 + j]);
    for (i = 0; i < 3; ++i)
        R2[4 * i] += 3.0;
    for (i = 0; i < 9; ++i)
        R2[i] = R2[i] * 0.5;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            dR[3 * i + j] = R[3 * i] * R2[j] + R[3 * i + 1] * R2[3 + j] + R[3 * i + 2] * R2[6 + j];
    memcpy(R, dR, 9 * sizeof(double));
}

/* SchepersEKF._step: the nominal strapdown step and the covariance propagation over dt (s) */
void ct_sc_step(struct ct_sc *s, double dt, int initialized)
{
    double w0 = s->w[0] * 0.5 * dt, w1 = s->w[1] * 0.5 * dt, w2 = s->w[2] * 0.5 * dt;
    double a[3];
    ct_strapdown_rotate(s->R, w0, w1, w2, s->E);  /* R_mid */
    accel(s, a);
    ct_integrate_pv(s->p, s->v, dt, a, a);
    if (initialized) {
        ct_sc_build_F(s, s->F, s->nx, s->q, dt);
        fpf_q(s->nx, s->F, s->P, s->q, s->T);
    }
    ct_strapdown_rotate(s->R, w0, w1, w2, s->E);
    s->steps += 1;
    if (s->steps % 64 == 0)
        orthonormalize(s);
}

/* PoseClones.take: clone k is the pose now; its rows and columns of P those of POS and ORI */
void ct_sc_take_clone(struct ct_sc *s, int k, int initialized)
{
    int n = s->nx, i, j, d;
    double *P = s->P;
    memcpy(s->cl_p + 3 * k, s->p, 3 * sizeof(double));
    memcpy(s->cl_R + 9 * k, s->R, 9 * sizeof(double));
    s->cl_due[k] = 0;
    s->cl_taken[k] = 1;
    if (!initialized)
        return;
    for (d = 0; d < 2; ++d) {                      /* rows, then columns, as the reference */
        int dst = d ? s->co[k] : s->cp[k], src = d ? CT_ORI : CT_POS;
        for (i = 0; i < 3; ++i)
            memmove(P + (dst + i) * n, P + (src + i) * n, (size_t)n * sizeof(double));
    }
    for (d = 0; d < 2; ++d) {
        int dst = d ? s->co[k] : s->cp[k], src = d ? CT_ORI : CT_POS;
        for (j = 0; j < n; ++j)
            for (i = 0; i < 3; ++i)
                P[j * n + dst + i] = P[j * n + src + i];
    }
}

/* PoseClones.release */
void ct_sc_release_clone(struct ct_sc *s, int k)
{
    int n = s->nx, i, j, d;
    double *P = s->P;
    for (d = 0; d < 2; ++d) {
        int b = d ? s->co[k] : s->cp[k];
        for (i = 0; i < 3; ++i)
            for (j = 0; j < n; ++j) {
                P[(b + i) * n + j] = 0.0;
                P[j * n + b + i] = 0.0;
            }
    }
    s->cl_due[k] = 0;
    s->cl_taken[k] = 0;
}

/* PoseClones.back: clone k as the pose dt seconds before the filter's state, predicted backwards
 * (G = R_now^T R_then, row-major 3x3): p_then = p - v dt, R_then = R G; its rows and columns of P
 * from T P and T P T^T with T = [[I, -dt I, 0, 0], [0, 0, G^T, dt G^T]] over (POS, VEL, ORI, GYR).
 * TP (6 x nx), TPT (6 x 6): scratch. */
void ct_sc_back_clone(struct ct_sc *s, int k, double dt, const double *G, int initialized, double *TP, double *TPT)
{
    int n = s->nx, cp = s->cp[k], co = s->co[k], i, j, r, c;
    double *P = s->P, *cR = s->cl_R + 9 * k;
    for (i = 0; i < 3; ++i)
        s->cl_p[3 * k + i] = s->p[i] - s->v[i] * dt;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            cR[3 * i + j] = s->R[3 * i] * G[j] + s->R[3 * i + 1] * G[3 + j] + s->R[3 * i + 2] * G[6 + j];
    s->cl_due[k] = 0;
    s->cl_taken[k] = 1;
    if (!initialized)
        return;
    for (i = 0; i < 3; ++i)                        /* TP = T P, T's zeros skipped (k increasing) */
        for (j = 0; j < n; ++j) {
            double a = 0.0, b = 0.0;
            int m;
            a += 1.0 * P[(CT_POS + i) * n + j];
            a += -dt * P[(CT_VEL + i) * n + j];
            for (m = 0; m < 3; ++m)
                b += G[3 * m + i] * P[(CT_ORI + m) * n + j];
            for (m = 0; m < 3; ++m)
                b += dt * G[3 * m + i] * P[(CT_GYR + m) * n + j];
            TP[i * n + j] = a;
            TP[(3 + i) * n + j] = b;
        }
    for (r = 0; r < 6; ++r)                        /* TPT = TP T^T */
        for (c = 0; c < 3; ++c) {
            const double *t = TP + r * n;
            double a = 0.0, b = 0.0;
            int m;
            a += t[CT_POS + c] * 1.0;
            a += t[CT_VEL + c] * -dt;
            for (m = 0; m < 3; ++m)
                b += t[CT_ORI + m] * G[3 * m + c];
            for (m = 0; m < 3; ++m)
                b += t[CT_GYR + m] * (dt * G[3 * m + c]);
            TPT[r * 6 + c] = a;
            TPT[r * 6 + 3 + c] = b;
        }
    for (i = 0; i < 3; ++i) {                      /* the clone's rows, then its columns */
        memcpy(P + (cp + i) * n, TP + i * n, (size_t)n * sizeof(double));
        memcpy(P + (co + i) * n, TP + (3 + i) * n, (size_t)n * sizeof(double));
    }
    for (j = 0; j < n; ++j)
        for (i = 0; i < 3; ++i) {
            P[j * n + cp + i] = TP[i * n + j];
            P[j * n + co + i] = TP[(3 + i) * n + j];
        }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            P[(cp + i) * n + cp + j] = TPT[i * 6 + j];
            P[(cp + i) * n + co + j] = TPT[i * 6 + 3 + j];
            P[(co + i) * n + cp + j] = TPT[(3 + i) * 6 + j];
            P[(co + i) * n + co + j] = TPT[(3 + i) * 6 + 3 + j];
        }
}

/* PoseClones.next_due: the clone due in (t, until] soonest (-1: none) */
int ct_sc_next_due(const struct ct_sc *s, int64_t t, int64_t until)
{
    int64_t nxt = until;
    int kk = -1, k;
    for (k = 0; k < s->nc; ++k)
        if (s->cl_due[k] && t < s->cl_t[k] && s->cl_t[k] <= nxt) {
            nxt = s->cl_t[k];
            kk = k;
        }
    return kk;
}

/* SchepersEKF.propagate from the filter's time t0 to the IMU sample at t_us > t0 (raw acc, gyr):
 * the interval's mean inputs, the steps split at the clones due inside it */
void ct_sc_propagate(struct ct_sc *s, int64_t t0, int64_t t_us, const double *acc, const double *gyr,
                     int initialized)
{
    int64_t t = t0;
    int i, k;
    for (i = 0; i < 3; ++i) {
        s->f[i] = (s->acc_prev[i] + acc[i]) * 0.5;
        s->f[i] = s->f[i] - s->ba[i];
        s->w[i] = (s->gyr_prev[i] + gyr[i]) * 0.5;
        s->w[i] = s->w[i] - s->bg[i];
        s->acc_prev[i] = acc[i];
        s->gyr_prev[i] = gyr[i];
    }
    for (;;) {
        int kk = ct_sc_next_due(s, t, t_us);
        int64_t nxt = kk >= 0 ? s->cl_t[kk] : t_us;
        if (nxt > t) {
            ct_sc_step(s, (double)(nxt - t) * 1e-6, initialized);
            t = nxt;
        }
        if (kk >= 0) {
            ct_sc_take_clone(s, kk, initialized);
            continue;
        }
        if (t >= t_us)
            break;
    }
    for (k = 0; k < s->nc; ++k)
        if (s->cl_due[k] && s->cl_t[k] <= t_us)
            ct_sc_take_clone(s, k, initialized);
}

/* SchepersEKF.predict_pose: the core covariance T (s) ahead in n steps with the last inputs held,
 * its pose block into P6 (6 x 6: dp, ori) and the position into pp (3) */
void ct_sc_predict_pose(struct ct_sc *s, double T, int n, double *P6, double *pp)
{
    const int N = CT_SC_CORE;
    double dt = T / n, a[3];
    double *Pc = s->Pc;
    int i, j;
    for (i = 0; i < N; ++i)
        memcpy(Pc + i * N, s->P + i * s->nx, N * sizeof(double));
    if (dt > 0.0) {
        struct nzrows z = {{0}, {0}};
        int k, fits;
        ct_sc_build_F(s, s->Fc, N, s->qc, dt);
        fits = nz_rows(N, s->Fc, &z);              /* the same F for every step */
        for (i = 0; i < n; ++i) {
            if (fits)
                congruence_rows(N, s->Fc, &z, Pc, s->Tc);
            else
                ct_congruence_sparse(N, s->Fc, Pc, s->Tc);
            for (k = 0; k < N; ++k)
                Pc[k * N + k] += s->qc[k];
        }
    }
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            P6[i * 6 + j] = Pc[(CT_POS + i) * N + CT_POS + j];
            P6[i * 6 + 3 + j] = Pc[(CT_POS + i) * N + CT_ORI + j];
            P6[(3 + i) * 6 + j] = Pc[(CT_ORI + i) * N + CT_POS + j];
            P6[(3 + i) * 6 + 3 + j] = Pc[(CT_ORI + i) * N + CT_ORI + j];
        }
    accel(s, a);
    for (i = 0; i < 3; ++i)
        pp[i] = s->p[i] + (s->v[i] + 0.5 * T * a[i]) * T;
}

/* SchepersEKF._inject with PoseClones.inject: the error estimate dx applied to the nominal state
 * and to the taken clones */
void ct_sc_inject(struct ct_sc *s, const double *dx)
{
    int i, k;
    for (i = 0; i < 3; ++i) {
        s->p[i] += dx[CT_POS + i];
        s->v[i] += dx[CT_VEL + i];
        s->ba[i] += dx[CT_ACC + i];
        s->bg[i] += dx[CT_GYR + i];
    }
    ct_strapdown_rotate(s->R, dx[CT_ORI], dx[CT_ORI + 1], dx[CT_ORI + 2], s->E);
    for (k = 0; k < s->nc; ++k)
        if (s->cl_taken[k]) {
            double *cp = s->cl_p + 3 * k;
            int c = s->co[k];
            for (i = 0; i < 3; ++i)
                cp[i] += dx[s->cp[k] + i];
            ct_strapdown_rotate(s->cl_R + 9 * k, dx[c], dx[c + 1], dx[c + 2], s->E);
        }
}

/* SchepersEKF.pose_values: a POSE's values into out (14): position, quaternion, the variances of
 * POS and ORI, POS's trace */
void ct_sc_pose_values(const struct ct_sc *s, double *out)
{
    const double *P = s->P;
    int n = s->nx, b = CT_POS, o = CT_ORI, i;
    out[0] = s->p[0];
    out[1] = s->p[1];
    out[2] = s->p[2];
    ct_quat_from_elements(s->R, out + 3);
    for (i = 0; i < 3; ++i) {
        out[7 + i] = P[(b + i) * n + b + i];
        out[10 + i] = P[(o + i) * n + o + i];
    }
    out[13] = P[b * n + b] + P[(b + 1) * n + b + 1] + P[(b + 2) * n + b + 2];
}

/* ------------------------------------------------------------ the update */

/* max(a, b) as Python's max: a unless b > a */
static double pymax(double a, double b)
{
    return b > a ? b : a;
}

/* SingleCoilUpdate._noise after run's y_pred = I h: the measurement covariance into R (amplitude
 * variances, field-model error, the linearisation margin of Schepers sec. 3.2); keeps |h|^2 and the
 * squared distance to the coil in st */
void ct_scu_noise(struct ct_scu *u, const double *P, const double *p, int cp, const struct ct_scm *m)
{
    const double *yp = u->y_pred, *c = m->centre;
    int n = u->nx, b = cp, i;
    double hn2 = yp[0] * yp[0] + yp[1] * yp[1] + yp[2] * yp[2];
    double sp2 = pymax(pymax(P[b * n + b], P[(b + 1) * n + b + 1]), P[(b + 2) * n + b + 2]);
    double ddx = p[0] - c[0], ddy = p[1] - c[1], ddz = p[2] - c[2];
    double r2 = pymax(ddx * ddx + ddy * ddy + ddz * ddz, 1e-6);
    double lin = 2.0 * sp2 / r2;                  /* _LIN_K */
    double extra = (m->rel_model * m->rel_model + lin * lin) * hn2;
    for (i = 0; i < 9; ++i)
        u->R[i] = 0.0;
    for (i = 0; i < 3; ++i)
        u->R[4 * i] = m->var[i] + extra;
    u->st[CT_SCU_HN2] = hn2;
    u->st[CT_SCU_R2] = r2;
}

/* single_coil_update._nis3: r^T S^-1 r for the symmetric S given by its upper triangle (inf if
 * not positive definite), linalg.inv3_sym and quad3_sym */
static double nis3(const double *S, const double *r)
{
    double s[9], i6[9], x = r[0], y = r[1], z = r[2];
    s[0] = S[0];
    s[3] = S[1];
    s[6] = S[2];
    s[4] = S[4];
    s[7] = S[5];
    s[8] = S[8];
    if (!ct_inv3(s, i6))
        return HUGE_VAL;
    return x * (i6[0] * x + i6[1] * y + i6[2] * z) + y * (i6[1] * x + i6[4] * y + i6[5] * z)
           + z * (i6[2] * x + i6[5] * y + i6[8] * z);
}

/* run's y_pred = I h of the model just evaluated */
void ct_scu_predict(struct ct_scu *u, const struct ct_scm *m)
{
    int i;
    for (i = 0; i < 3; ++i)
        u->y_pred[i] = m->h[i] * m->current;
}

/* SingleCoilUpdate.run up to its first pass's shared update: y_pred, the noise, the prior P0, dx = 0,
 * the linearisation point (pi, Ri) = (p, R), pass 0 */
void ct_scu_begin(struct ct_scu *u, double *P, const double *p, const double *R, int cp, int co,
                  const struct ct_scm *m)
{
    int n = u->nx;
    ct_scu_predict(u, m);
    ct_scu_noise(u, P, p, cp, m);
    memcpy(u->P0, P, (size_t)n * n * sizeof(double));
    memset(u->dx, 0, (size_t)n * sizeof(double));
    memcpy(u->pi, p, 3 * sizeof(double));
    memcpy(u->Ri, R, 9 * sizeof(double));
    ct_scu_pass(u, 0, P, cp, co, m);
}

/* SingleCoilUpdate._pass up to the shared update: H from the coil's per-ampere
 * Jacobian at the clone's rows cp, co, the (pseudo-)innovation, the coil gain's column (m->gain >= 0);
 * pass 0 also the nominal NIS and the monitor's inflation of R; a later pass restores P to the prior */
void ct_scu_pass(struct ct_scu *u, int it, double *P, int cp, int co, const struct ct_scm *m)
{
    int n = u->nx, i, j, k;
    double cur = m->current, *H = u->H;
    for (i = 0; i < 3 * n; ++i)
        H[i] = 0.0;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j) {
            H[i * n + cp + j] = m->Hu[i * 6 + j] * cur;
            H[i * n + co + j] = m->Hu[i * 6 + 3 + j] * cur;
        }
    for (i = 0; i < 3; ++i)
        u->y[i] = m->y[i] - u->y_pred[i];
    if (it) {
        for (i = 0; i < 3; ++i) {
            double s = 0.0;
            for (k = 0; k < n; ++k)
                s += H[i * n + k] * u->dx[k];
            u->Hdx[i] = s;
        }
        for (i = 0; i < 3; ++i)
            u->y[i] = u->y[i] + u->Hdx[i];
    }
    if (m->gain >= 0)                              /* the coil gain's column, left out of H dx */
        for (i = 0; i < 3; ++i)
            H[i * n + m->gain] = m->h[i] * m->gain_current;
    if (it) {
        memcpy(P, u->P0, (size_t)n * n * sizeof(double));
    } else {
        double *PHt = u->PHt, *S = u->S;
        for (i = 0; i < 3 * n; ++i)
            PHt[i] = 0.0;
        for (j = 0; j < 3; ++j)                    /* PHt = P H^T, H's zeros skipped */
            for (k = 0; k < n; ++k) {
                double h = H[j * n + k];
                if (h == 0.0)
                    continue;
                for (i = 0; i < n; ++i)
                    PHt[i * 3 + j] += P[i * n + k] * h;
            }
        for (i = 0; i < 3; ++i)                    /* S = H PHt + R */
            for (j = 0; j < 3; ++j) {
                double s = 0.0;
                for (k = 0; k < n; ++k) {
                    double h = H[i * n + k];
                    if (h != 0.0)
                        s += h * PHt[k * 3 + j];
                }
                S[i * 3 + j] = s;
            }
        for (i = 0; i < 9; ++i)
            S[i] += u->R[i];
        u->st[CT_SCU_NIS_NOMINAL] = nis3(S, u->y);
        if (m->r_scale != 1.0)
            for (i = 0; i < 3; ++i)
                u->R[4 * i] *= m->r_scale;
    }
}

/* SingleCoilUpdate.run after pass it's shared update (flags f, the EKF_* bits): keep its
 * correction and decide on another pass (Gauss-Newton on the eq-4 cost, relinearised at the
 * corrected clone pose; only while the second-order term 6 (dp/r)^2 |h| of Schepers sec. 3.2
 * matters); a later pass that failed leaves the previous pass's P.  Returns 1 when another pass follows (pi, Ri: its linearisation point). */
int ct_scu_after(struct ct_scu *u, int it, int flags, int iterations, double *P, const double *p, const double *R,
                 int cp, int co, const double *var)
{
    int n = u->nx, b = cp, o = co, i, j;
    double step, *dx = u->dx;
    if (it && (flags & (CT_EKF_NOT_PD | CT_EKF_NONFINITE))) {
        memcpy(P, u->Pprev, (size_t)n * n * sizeof(double));   /* keep the previous pass */
        return 0;
    }
    step = pymax(pymax(fabs(u->udx[b] - dx[b]), fabs(u->udx[b + 1] - dx[b + 1])), fabs(u->udx[b + 2] - dx[b + 2]));
    memcpy(dx, u->udx, (size_t)n * sizeof(double));
    if (it == 0) {
        double dp2 = dx[b] * dx[b] + dx[b + 1] * dx[b + 1] + dx[b + 2] * dx[b + 2];
        double so = 6.0 * dp2 / u->st[CT_SCU_R2];
        double noise2 = (var[0] + var[1] + var[2]) / 3.0;
        if (so * so * u->st[CT_SCU_HN2] < 0.01 * noise2)
            return 0;
    }
    if (it + 1 < iterations) {
        memcpy(u->Pprev, P, (size_t)n * n * sizeof(double));
        for (i = 0; i < 3; ++i)
            u->pi[i] = p[i] + dx[b + i];
        ct_exp_rotvec(dx[o], dx[o + 1], dx[o + 2], u->dR);
        for (i = 0; i < 3; ++i)
            for (j = 0; j < 3; ++j)
                u->Ri[3 * i + j] = R[3 * i] * u->dR[j] + R[3 * i + 1] * u->dR[3 + j] + R[3 * i + 2] * u->dR[6 + j];
        if (step < 1e-6)
            return 0;
        return 1;
    }
    return 0;
}
