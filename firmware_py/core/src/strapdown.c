/*
 * The strapdown integration and inertial error transition: the compiled form of
 * coiltrack.firmware.estimate.strapdown (Strapdown.rotate, to_nav, integrate_pv,
 * transition_nav), coiltrack.firmware.linalg.exp_rotvec, and the numeric body of
 * coiltrack.firmware.estimate.magnetic_inertial.FusionFilter._propagate.
 *
 * Thesis seeds/002_cd7f1fdb7fc67471.txt: R <- R exp([w T]x) (eqs 2.27, 6.1), a = R f - f_ref
 * (eqs 6.2, 6.8), v <- v + T (a0 + a1)/2 (eq 6.3), p <- p + T v + T^2 (a0/3 + a1/6) (eq 6.4),
 * the error transition of eq 6.17 and P <- A P A^T + Q (eq 6.5).  The scalar steps are the
 * reference's operations in the same order; the 3x3 product of rotate sums k in increasing
 * order where the reference calls BLAS, so the attitude agrees to rounding.
 */
#include <math.h>

#include "coiltrack_core.h"

/* linalg.exp_rotvec: out = exp([w]x) (Rodrigues), row-major 3x3 */
void ct_exp_rotvec(double wx, double wy, double wz, double *out)
{
    double t2 = wx * wx + wy * wy + wz * wz;
    double a, b;
    if (t2 < 1e-12) {
        a = 1.0 - t2 / 6.0;
        b = 0.5 - t2 / 24.0;
    } else if (t2 == HUGE_VAL) {
        a = b = t2 - t2;            /* NaN, for the caller's finiteness check */
    } else {
        double t = sqrt(t2);
        a = sin(t) / t;
        b = (1.0 - cos(t)) / t2;
    }
    out[0] = 1.0 - b * (wy * wy + wz * wz);
    out[4] = 1.0 - b * (wx * wx + wz * wz);
    out[8] = 1.0 - b * (wx * wx + wy * wy);
    out[1] = b * wx * wy - a * wz;
    out[3] = b * wx * wy + a * wz;
    out[2] = b * wx * wz + a * wy;
    out[6] = b * wx * wz - a * wy;
    out[5] = b * wy * wz - a * wx;
    out[7] = b * wy * wz + a * wx;
}

/* Strapdown.rotate: R <- R exp([u]x); E is 9 doubles of scratch */
void ct_strapdown_rotate(double *R, double ux, double uy, double uz, double *E)
{
    double T[9];
    int i, j;
    ct_exp_rotvec(ux, uy, uz, E);
    for (i = 0; i < 3; ++i)
        for (j = 0; j < 3; ++j)
            T[3 * i + j] = R[3 * i] * E[j] + R[3 * i + 1] * E[3 + j] + R[3 * i + 2] * E[6 + j];
    for (i = 0; i < 9; ++i)
        R[i] = T[i];
}

/* to_nav: out = R (x, y, z) */
void ct_to_nav(const double *R, double x, double y, double z, double *out)
{
    out[0] = R[0] * x + R[1] * y + R[2] * z;
    out[1] = R[3] * x + R[4] * y + R[5] * z;
    out[2] = R[6] * x + R[7] * y + R[8] * z;
}

/* integrate_pv: position and velocity over dt, acceleration linear from a0 to a1 (eqs 6.3-6.4) */
void ct_integrate_pv(double *p, double *v, double dt, const double *a0, const double *a1)
{
    double c0 = dt * dt / 3.0;
    double c1 = dt * dt / 6.0;
    double h;
    p[0] += v[0] * dt + c0 * a0[0] + c1 * a1[0];
    p[1] += v[1] * dt + c0 * a0[1] + c1 * a1[1];
    p[2] += v[2] * dt + c0 * a0[2] + c1 * a1[2];
    h = 0.5 * dt;
    v[0] += h * (a0[0] + a1[0]);
    v[1] += h * (a0[1] + a1[1]);
    v[2] += h * (a0[2] + a1[2]);
}

/* transition_nav: the blocks of eq 6.17 for a navigation-frame orientation error (g = R f);
 * A is n x n, row-major, with the inertial rows at the layout's indices */
void ct_transition_nav(double *A, int n, double dt, const double *R, double gx, double gy, double gz)
{
    double m = -dt;
    int i;
    A[CT_VEL * n + CT_ORI + 1] = dt * gz;
    A[CT_VEL * n + CT_ORI + 2] = -dt * gy;
    A[(CT_VEL + 1) * n + CT_ORI] = -dt * gz;
    A[(CT_VEL + 1) * n + CT_ORI + 2] = dt * gx;
    A[(CT_VEL + 2) * n + CT_ORI] = dt * gy;
    A[(CT_VEL + 2) * n + CT_ORI + 1] = -dt * gx;
    for (i = 0; i < 3; ++i) {
        double a0 = m * R[3 * i], a1 = m * R[3 * i + 1], a2 = m * R[3 * i + 2];
        double *va = A + (CT_VEL + i) * n + CT_ACC, *og = A + (CT_ORI + i) * n + CT_GYR;
        va[0] = a0;
        va[1] = a1;
        va[2] = a2;
        og[0] = a0;
        og[1] = a1;
        og[2] = a2;
    }
}

/* FusionFilter._propagate after its input interpolation (the step's static blocks and Q already
 * written for dt): attitude, position and velocity, offset decay, eq 6.17's blocks and
 * P <- A P A^T + Q.  in[0..17]: f0, f1 (specific force at t0, t1, offsets removed), w (rate),
 * r0, r1 (the source's specific force at t0, t1), each 3; E (9) and T (n x n) scratch. */
void ct_ins_propagate(struct ct_ins *s, double dt, const double *in, double ka, double kg)
{
    const double *f0 = in, *f1 = in + 3, *w = in + 6, *r0 = in + 9, *r1 = in + 12;
    double g0[3], g1[3], a0[3], a1[3];
    ct_to_nav(s->Th, f0[0], f0[1], f0[2], g0);
    ct_strapdown_rotate(s->Th, w[0] * dt, w[1] * dt, w[2] * dt, s->E);
    ct_to_nav(s->Th, f1[0], f1[1], f1[2], g1);
    a0[0] = g0[0] - r0[0];
    a0[1] = g0[1] - r0[1];
    a0[2] = g0[2] - r0[2];
    a1[0] = g1[0] - r1[0];
    a1[1] = g1[1] - r1[1];
    a1[2] = g1[2] - r1[2];
    ct_integrate_pv(s->p, s->v, dt, a0, a1);
    s->ba[0] *= ka;
    s->ba[1] *= ka;
    s->ba[2] *= ka;
    s->bg[0] *= kg;
    s->bg[1] *= kg;
    s->bg[2] *= kg;
    ct_transition_nav(s->A, s->n, dt, s->Th, 0.5 * (g0[0] + g1[0]), 0.5 * (g0[1] + g1[1]),
                      0.5 * (g0[2] + g1[2]));
    ct_covariance_predict(s->n, s->A, s->P, s->Q, s->T);
}
