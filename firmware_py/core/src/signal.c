/*
 * The one measurement model: the compiled form of
 * coiltrack.firmware.model.signal.SignalModel (fields, predict, measure).
 *
 * B_j(p) = R_j B_coil(R_j^T (p - c_j)), J_j = R_j J_coil R_j^T (exact loop, Schepers & Veltink
 * seeds/000_e46ec0e8bf7ea271.txt eqs 6-7, or dipole, eq 8 / eq 10); h_j = R^T B_j (eq 5);
 * H_j = [R^T J_j, [h_j]x] (eqs 9-11).  Same operations, same order as the Python
 * (SignalModel._loop, _loop_axes, _dipole, predict, measure).
 */

#include "coiltrack_core.h"

/* SignalModel._loop */
static void ct_signal_loop(const double *g, int j, double px, double py, double pz, double current,
                           int jac, double *B, double *J)
{
    const double *c = g + CT_COIL_CENTER, *r = g + CT_COIL_ROT;
    double dx = px - c[0], dy = py - c[1], dz = pz - c[2];
    double r00 = r[0], r01 = r[1], r02 = r[2], r10 = r[3], r11 = r[4], r12 = r[5];
    double r20 = r[6], r21 = r[7], r22 = r[8];
    double x = r00 * dx + r10 * dy + r20 * dz;
    double y = r01 * dx + r11 * dy + r21 * dz;
    double z = r02 * dx + r12 * dy + r22 * dz;
    double t[9], bx, by, bz;
    double *Bo = B + 3 * j;

    ct_loop_point(x, y, z, g[CT_COIL_RADIUS], g[CT_COIL_SPA] * current, jac, t);
    bx = t[0];
    by = t[1];
    bz = t[2];
    Bo[0] = r00 * bx + r01 * by + r02 * bz;
    Bo[1] = r10 * bx + r11 * by + r12 * bz;
    Bo[2] = r20 * bx + r21 * by + r22 * bz;
    if (jac) {
        double jxx = t[3], jyy = t[4], jzz = t[5], jxy = t[6], jxz = t[7], jyz = t[8];
        double t00 = r00 * jxx + r01 * jxy + r02 * jxz;
        double t01 = r00 * jxy + r01 * jyy + r02 * jyz;
        double t02 = r00 * jxz + r01 * jyz + r02 * jzz;
        double t10 = r10 * jxx + r11 * jxy + r12 * jxz;
        double t11 = r10 * jxy + r11 * jyy + r12 * jyz;
        double t12 = r10 * jxz + r11 * jyz + r12 * jzz;
        double t20 = r20 * jxx + r21 * jxy + r22 * jxz;
        double t21 = r20 * jxy + r21 * jyy + r22 * jyz;
        double t22 = r20 * jxz + r21 * jyz + r22 * jzz;
        double *Jo = J + 9 * j;
        Jo[0] = t00 * r00 + t01 * r01 + t02 * r02;
        Jo[1] = t00 * r10 + t01 * r11 + t02 * r12;
        Jo[2] = t00 * r20 + t01 * r21 + t02 * r22;
        Jo[3] = t10 * r00 + t11 * r01 + t12 * r02;
        Jo[4] = t10 * r10 + t11 * r11 + t12 * r12;
        Jo[5] = t10 * r20 + t11 * r21 + t12 * r22;
        Jo[6] = t20 * r00 + t21 * r01 + t22 * r02;
        Jo[7] = t20 * r10 + t21 * r11 + t22 * r12;
        Jo[8] = t20 * r20 + t21 * r21 + t22 * r22;
    }
}

/* SignalModel._loop_axes: R_j a signed permutation, its zero terms skipped */
static void ct_signal_loop_axes(const double *g, int j, double px, double py, double pz,
                                double current, int jac, double *B, double *J)
{
    const double *c = g + CT_COIL_CENTER, *pm = g + CT_COIL_PERM;
    double d[3];
    int i0 = (int)pm[0], i1 = (int)pm[2], i2 = (int)pm[4];
    double s0 = pm[1], s1 = pm[3], s2 = pm[5];
    double t[9];
    double *Bo = B + 3 * j;

    d[0] = px - c[0];
    d[1] = py - c[1];
    d[2] = pz - c[2];
    ct_loop_point(s0 * d[i0], s1 * d[i1], s2 * d[i2], g[CT_COIL_RADIUS], g[CT_COIL_SPA] * current,
                  jac, t);
    Bo[i0] = s0 * t[0];
    Bo[i1] = s1 * t[1];
    Bo[i2] = s2 * t[2];
    if (jac) {
        double *Jo = J + 9 * j;
        int r0 = 3 * i0, r1 = 3 * i1, r2 = 3 * i2;
        Jo[r0 + i0] = t[3];
        Jo[r1 + i1] = t[4];
        Jo[r2 + i2] = t[5];
        Jo[r0 + i1] = Jo[r1 + i0] = s0 * s1 * t[6];
        Jo[r0 + i2] = Jo[r2 + i0] = s0 * s2 * t[7];
        Jo[r1 + i2] = Jo[r2 + i1] = s1 * s2 * t[8];
    }
}

/* SignalModel._dipole */
static void ct_signal_dipole(const double *g, int j, double px, double py, double pz, double current,
                             int jac, double *B, double *J)
{
    const double *c = g + CT_COIL_CENTER, *ax = g + CT_COIL_AXIS;
    double m = g[CT_COIL_MPA] * current;
    double t[9];
    double *Bo = B + 3 * j;

    ct_dipole_point(px - c[0], py - c[1], pz - c[2], ax[0] * m, ax[1] * m, ax[2] * m, jac, t);
    Bo[0] = t[0];
    Bo[1] = t[1];
    Bo[2] = t[2];
    if (jac) {
        double *Jo = J + 9 * j;
        Jo[0] = t[3];
        Jo[4] = t[4];
        Jo[8] = t[5];
        Jo[1] = Jo[3] = t[6];
        Jo[2] = Jo[6] = t[7];
        Jo[5] = Jo[7] = t[8];
    }
}

/* SignalModel.fields (without the distortion map, which the caller adds) */
void ct_signal_fields(const double *geom, int n, double px, double py, double pz, const double *cur,
                      int jac, double *B, double *J)
{
    int j;
    for (j = 0; j < n; ++j) {
        const double *g = geom + CT_COIL_STRIDE * j;
        int kind = (int)g[CT_COIL_KIND];
        if (kind == CT_KIND_LOOP_AXES)
            ct_signal_loop_axes(g, j, px, py, pz, cur[j], jac, B, J);
        else if (kind == CT_KIND_LOOP)
            ct_signal_loop(g, j, px, py, pz, cur[j], jac, B, J);
        else
            ct_signal_dipole(g, j, px, py, pz, cur[j], jac, B, J);
    }
}

/* SignalModel.predict after the fields: h_j = R^T B_j (Schepers eq 5) */
void ct_signal_project(int n, const double *R, const double *B, double *h)
{
    double r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5];
    double r20 = R[6], r21 = R[7], r22 = R[8];
    int j;
    for (j = 0; j < n; ++j) {
        int o = 3 * j;
        double bx = B[o], by = B[o + 1], bz = B[o + 2];
        h[o] = r00 * bx + r10 * by + r20 * bz;
        h[o + 1] = r01 * bx + r11 * by + r21 * bz;
        h[o + 2] = r02 * bx + r12 * by + r22 * bz;
    }
}

/* SignalModel.measure after the fields: h_j and H_j = [R^T J_j, [h_j]x] (eqs 9-11) */
void ct_signal_project_jac(int n, const double *R, const double *B, const double *J, double *h,
                           double *H)
{
    double r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5];
    double r20 = R[6], r21 = R[7], r22 = R[8];
    int j;
    for (j = 0; j < n; ++j) {
        int o = 3 * j, g = 9 * j, q = 18 * j;
        double bx = B[o], by = B[o + 1], bz = B[o + 2];
        double hx = r00 * bx + r10 * by + r20 * bz;
        double hy = r01 * bx + r11 * by + r21 * bz;
        double hz = r02 * bx + r12 * by + r22 * bz;
        double j00 = J[g], j01 = J[g + 1], j02 = J[g + 2];
        double j10 = J[g + 3], j11 = J[g + 4], j12 = J[g + 5];
        double j20 = J[g + 6], j21 = J[g + 7], j22 = J[g + 8];
        h[o] = hx;
        h[o + 1] = hy;
        h[o + 2] = hz;
        H[q] = r00 * j00 + r10 * j10 + r20 * j20;
        H[q + 1] = r00 * j01 + r10 * j11 + r20 * j21;
        H[q + 2] = r00 * j02 + r10 * j12 + r20 * j22;
        H[q + 6] = r01 * j00 + r11 * j10 + r21 * j20;
        H[q + 7] = r01 * j01 + r11 * j11 + r21 * j21;
        H[q + 8] = r01 * j02 + r11 * j12 + r21 * j22;
        H[q + 12] = r02 * j00 + r12 * j10 + r22 * j20;
        H[q + 13] = r02 * j01 + r12 * j11 + r22 * j21;
        H[q + 14] = r02 * j02 + r12 * j12 + r22 * j22;
        H[q + 3] = 0.0;
        H[q + 4] = -hz;
        H[q + 5] = hy;
        H[q + 9] = hz;
        H[q + 10] = 0.0;
        H[q + 11] = -hx;
        H[q + 15] = -hy;
        H[q + 16] = hx;
        H[q + 17] = 0.0;
    }
}
