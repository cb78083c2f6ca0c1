/*
 * Coil field kernels: the compiled form of coiltrack.firmware.model.field's
 * single-point kernels (loop_point with _loop_core, dipole_point).
 *
 * Exact loop: Schepers & Veltink 2010 (seeds/000_e46ec0e8bf7ea271.txt) eqs 6-7
 * in the cancellation-free AGM form derived in field._loop_core, with the
 * forward-mode derivatives propagated through the AGM; dipole: eq 8 and the
 * general form of eq 10.  Same operations in the same order as the Python.
 */
#include <math.h>

#include "coiltrack_core.h"

#define CT_HALF_PI 1.5707963267948966
#define CT_LOOP_MAX_ITER 20
#define CT_AGM_TOL 1e-15
#define CT_TINY 1e-300
#define CT_MU0_4PI 1e-7

/* field._loop_core (scalar path: sqrt = math.sqrt, maximum = max). */
static void ct_loop_core(double u, double z, int jac, double *F_out, double *G_out, double *Fz_out,
                         double *H_out)
{
    double rho = sqrt(u);
    double z2 = z * z;
    double s = 1.0 + u + z2;
    double omr = 1.0 - rho;
    double opr = 1.0 + rho;
    double one_m_u = omr * opr;
    double P = (omr * omr + z2) * (opr * opr + z2);
    double q, a, b, d, S, w;
    double P_u = 0.0, P_z = 0.0, q_u, q_z, a_u = 0.0, a_z = 0.0, b_u = 0.0, b_z = 0.0;
    double d_u = 0.0, d_z = 0.0, S_u = 0.0, S_z = 0.0;
    double M, inv, Nf, F, G;
    int it;

    if (CT_TINY > P)            /* max(P, _TINY): NaN stays NaN */
        P = CT_TINY;
    q = sqrt(P);
    a = sqrt(0.5 * (s + q));
    b = sqrt(q);
    d = 1.0 / (a * a);
    S = 1.0 * d;
    w = 1.0;
    if (jac) {
        P_u = 2.0 * (z2 - one_m_u);
        P_z = 4.0 * z * s;
        q_u = P_u / (2.0 * q);
        q_z = P_z / (2.0 * q);
        a_u = (1.0 + q_u) / (4.0 * a);
        a_z = (2.0 * z + q_z) / (4.0 * a);
        b_u = q_u / (2.0 * b);
        b_z = q_z / (2.0 * b);
        d_u = -2.0 * d * a_u / a;
        d_z = -2.0 * d * a_z / a;
        S_u = 1.0 * d_u;
        S_z = 1.0 * d_z;
    }
    for (it = 0; it < CT_LOOP_MAX_ITER; ++it) {
        double an, bn, r16, dn;
        if (!(fabs(a - b) > CT_AGM_TOL * a))
            break;
        an = 0.5 * (a + b);
        bn = sqrt(a * b);
        r16 = 1.0 / (16.0 * an * an);
        dn = u * d * d * r16;
        if (jac) {
            double an_u = 0.5 * (a_u + b_u);
            double an_z = 0.5 * (a_z + b_z);
            double bn_u = (a_u * b + a * b_u) / (2.0 * bn);
            double bn_z = (a_z * b + a * b_z) / (2.0 * bn);
            double dn_u = (d * d + 2.0 * u * d * d_u) * r16 - 2.0 * dn * an_u / an;
            double dn_z = (2.0 * u * d * d_z) * r16 - 2.0 * dn * an_z / an;
            a_u = an_u;
            a_z = an_z;
            b_u = bn_u;
            b_z = bn_z;
            d_u = dn_u;
            d_z = dn_z;
        }
        a = an;
        b = bn;
        d = dn;
        w *= 2.0;
        S += w * d;
        if (jac) {
            S_u += w * d_u;
            S_z += w * d_z;
        }
    }
    M = 0.5 * (a + b);
    inv = CT_HALF_PI / (M * P);
    Nf = 4.0 - s * S;
    F = z * Nf * inv;
    G = (2.0 * (one_m_u + z2) - (one_m_u - z2) * u * S) * inv;
    *F_out = F;
    *G_out = G;
    if (jac) {
        double M_u = 0.5 * (a_u + b_u);
        double M_z = 0.5 * (a_z + b_z);
        double Nf_u = -(S + s * S_u);
        double Nf_z = -(2.0 * z * S + s * S_z);
        double lu = M_u / M + P_u / P;
        double lz = M_z / M + P_z / P;
        *H_out = 2.0 * z * (Nf_u - Nf * lu) * inv;
        *Fz_out = (Nf + z * (Nf_z - Nf * lz)) * inv;
    }
}

/* field.loop_point */
void ct_loop_point(double x, double y, double z, double radius, double scale, int jac, double *out)
{
    double inv_a = 1.0 / radius;
    double xn = x * inv_a;
    double yn = y * inv_a;
    double zn = z * inv_a;
    double u = xn * xn + yn * yn;
    double F, G, Fz = 0.0, H = 0.0, Fc;

    ct_loop_core(u, zn, jac, &F, &G, &Fz, &H);
    Fc = scale * F;
    out[0] = xn * Fc;
    out[1] = yn * Fc;
    out[2] = scale * G;
    if (jac) {
        double g = scale * inv_a;
        double F2 = F * g, H2 = H * g, Fz2 = Fz * g;
        out[3] = F2 + xn * xn * H2;
        out[4] = F2 + yn * yn * H2;
        out[5] = -2.0 * F2 - u * H2;
        out[6] = xn * yn * H2;
        out[7] = xn * Fz2;
        out[8] = yn * Fz2;
    }
}

/* field.dipole_point (the Python raises ZeroDivisionError at r = 0; this returns non-finite values) */
void ct_dipole_point(double px, double py, double pz, double mx, double my, double mz, int jac,
                     double *out)
{
    double r2 = px * px + py * py + pz * pz;
    double inv_r2 = 1.0 / r2;
    double c = CT_MU0_4PI * inv_r2 / sqrt(r2);
    double mp = mx * px + my * py + mz * pz;
    double k = 3.0 * mp * inv_r2;
    out[0] = c * (k * px - mx);
    out[1] = c * (k * py - my);
    out[2] = c * (k * pz - mz);
    if (jac) {
        double c5 = 3.0 * c * inv_r2;
        double f = 5.0 * mp * inv_r2;
        out[3] = c5 * (2.0 * mx * px + mp - f * px * px);
        out[4] = c5 * (2.0 * my * py + mp - f * py * py);
        out[5] = c5 * (2.0 * mz * pz + mp - f * pz * pz);
        out[6] = c5 * (mx * py + my * px - f * px * py);
        out[7] = c5 * (mx * pz + mz * px - f * px * pz);
        out[8] = c5 * (my * pz + mz * py - f * py * pz);
    }
}
