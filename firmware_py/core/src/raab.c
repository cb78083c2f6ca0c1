/*
 * One update of Raab's iterative tracker (Raab et al. 1979, seeds/004_86267342cd7488ce.txt,
 * eqs 7-31): coiltrack.firmware.pose.raab_update (coupling, post_sense, detect, clip,
 * position_update, orientation_update, dcm, euler, wrap) and raab_correction.LoopCorrection
 * (correct, precondition_step with linalg.lu_solve), composed as pose.raab_update.Update.run; and the
 * correction's refresh (with model.field.dipole_polar) and its preconditioner K (precondition, with
 * linalg.lu_factor).
 * The same operations in the same order as the Python.
 */
#include "coiltrack_core.h"

#include <math.h>
#include <string.h>

static const double PI = 3.141592653589793;
static const double TWO_PI = 2.0 * 3.141592653589793;

/* wrap: angle into (-pi, pi] */
static double wrap(double a)
{
    a = fmod(a, TWO_PI);
    if (a > PI)
        a -= TWO_PI;
    else if (a <= -PI)
        a += TWO_PI;
    return a;
}

/* clip: x into [-m, m] */
static double clip(double x, double m)
{
    return x > m ? m : (x < -m ? -m : x);
}

/* Python's max(a, b): b only when b > a */
static double pymax(double a, double b)
{
    return b > a ? b : a;
}

/* dcm: A = T_phi T_theta T_psi (Table II), row-major */
static void dcm(double psi, double theta, double phi, double *a)
{
    double cs = cos(psi), ss = sin(psi), ct = cos(theta), st = sin(theta), cf = cos(phi), sf = sin(phi);
    a[0] = ct * cs;
    a[1] = ct * ss;
    a[2] = -st;
    a[3] = sf * st * cs - cf * ss;
    a[4] = sf * st * ss + cf * cs;
    a[5] = sf * ct;
    a[6] = cf * st * cs + sf * ss;
    a[7] = cf * st * ss - sf * cs;
    a[8] = cf * ct;
}

/* euler: (psi, theta, phi) of A */
static void euler(const double *a, double *e)
{
    double s = -a[2];
    s = s > 1.0 ? 1.0 : (s < -1.0 ? -1.0 : s);
    e[0] = atan2(a[1], a[0]);
    e[1] = asin(s);
    e[2] = atan2(a[5], a[8]);
}

/* position_update (eqs 27-28): the new (alpha, beta) into ab */
static void position_update(double alpha, double beta, double da0, double db0, double pole_cos, double *ab)
{
    double cb = cos(beta), ca, sa, sb, v0, v1, v2, ux, uy, uz, nrm, rxy;
    if (fabs(cb) >= pole_cos) {
        double a = alpha + da0 / cb, b = beta + db0;
        if (b > 0.5 * PI) {
            b = PI - b;
            a = a + PI;
        } else if (b < -0.5 * PI) {
            b = -PI - b;
            a = a + PI;
        }
        ab[0] = wrap(a);
        ab[1] = b;
        return;
    }
    ca = cos(alpha);
    sa = sin(alpha);
    sb = sin(beta);
    v0 = 1.0;
    v1 = da0;
    v2 = -db0;
    ux = cb * ca * v0 - sa * v1 + sb * ca * v2;
    uy = cb * sa * v0 + ca * v1 + sb * sa * v2;
    uz = -sb * v0 + cb * v2;
    nrm = sqrt(ux * ux + uy * uy + uz * uz);
    ux = ux / nrm;
    uy = uy / nrm;
    uz = uz / nrm;
    rxy = hypot(ux, uy);
    ab[0] = rxy > 1e-12 ? atan2(uy, ux) : alpha;
    ab[1] = atan2(-uz, rxy);
}

/* orientation_update (eqs 29-31): the new (psi, theta, phi) into e */
static void orientation_update(double alpha, double beta, double psi, double theta, double phi, double dphi0,
                               double dtheta0, double dpsi0, double pole_cos, double *e)
{
    double ca = cos(alpha), sa = sin(alpha), cb = cos(beta), sb = sin(beta);
    double d0 = dphi0, d1 = dtheta0, d2 = dpsi0;
    double wx = cb * ca * d0 - sa * d1 + sb * ca * d2;
    double wy = cb * sa * d0 + ca * d1 + sb * sa * d2;
    double wz = -sb * d0 + cb * d2;
    double ct = cos(theta), A[9], n[9], t2, f, g, e00, e11, e22, e01, e10, e02, e20, e12, e21;
    int i;
    if (fabs(ct) >= pole_cos) {
        double cs = cos(psi), ss = sin(psi);
        double vx = cs * wx + ss * wy, vy = -ss * wx + cs * wy, vz = wz;
        double dphi1 = vx / ct;
        e[0] = wrap(psi + vz + dphi1 * sin(theta));
        e[1] = theta + vy;
        e[2] = wrap(phi + dphi1);
        return;
    }
    dcm(psi, theta, phi, A);
    t2 = wx * wx + wy * wy + wz * wz;
    if (t2 < 1e-12) {
        f = 1.0 - t2 / 6.0;
        g = 0.5 - t2 / 24.0;
    } else {
        double t = sqrt(t2);
        f = sin(t) / t;
        g = (1.0 - cos(t)) / t2;
    }
    e00 = 1.0 - g * (wy * wy + wz * wz);
    e11 = 1.0 - g * (wx * wx + wz * wz);
    e22 = 1.0 - g * (wx * wx + wy * wy);
    e01 = g * wx * wy - f * wz;
    e10 = g * wx * wy + f * wz;
    e02 = g * wx * wz + f * wy;
    e20 = g * wx * wz - f * wy;
    e12 = g * wy * wz - f * wx;
    e21 = g * wy * wz + f * wx;
    for (i = 0; i < 3; ++i) {
        double a0 = A[3 * i], a1 = A[3 * i + 1], a2 = A[3 * i + 2];
        n[3 * i] = a0 * e00 + a1 * e01 + a2 * e02;
        n[3 * i + 1] = a0 * e10 + a1 * e11 + a2 * e12;
        n[3 * i + 2] = a0 * e20 + a1 * e21 + a2 * e22;
    }
    euler(n, e);
}

/* post_sense (eqs 7, 11): (xy, yx, xz, zx, yz, zy) of F_7 = P R F P^T into o */
static void post_sense(const double *x, const double *R, const double *F, double *o)
{
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double p00 = cb * ca, p01 = cb * sa, p02 = -sb, p10 = -sa, p11 = ca, p20 = sb * ca, p21 = sb * sa, p22 = cb;
    double r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5], r20 = R[6], r21 = R[7],
           r22 = R[8];
    double a00 = p00 * r00 + p01 * r10 + p02 * r20, a01 = p00 * r01 + p01 * r11 + p02 * r21,
           a02 = p00 * r02 + p01 * r12 + p02 * r22;
    double a10 = p10 * r00 + p11 * r10, a11 = p10 * r01 + p11 * r11, a12 = p10 * r02 + p11 * r12;
    double a20 = p20 * r00 + p21 * r10 + p22 * r20, a21 = p20 * r01 + p21 * r11 + p22 * r21,
           a22 = p20 * r02 + p21 * r12 + p22 * r22;
    double f0 = F[0], f1 = F[1], f2 = F[2], f3 = F[3], f4 = F[4], f5 = F[5], f6 = F[6], f7 = F[7], f8 = F[8];
    double h0x = f0 * p00 + f1 * p01 + f2 * p02, h1x = f3 * p00 + f4 * p01 + f5 * p02,
           h2x = f6 * p00 + f7 * p01 + f8 * p02;
    double h0y = f0 * p10 + f1 * p11, h1y = f3 * p10 + f4 * p11, h2y = f6 * p10 + f7 * p11;
    double h0z = f0 * p20 + f1 * p21 + f2 * p22, h1z = f3 * p20 + f4 * p21 + f5 * p22,
           h2z = f6 * p20 + f7 * p21 + f8 * p22;
    o[0] = a00 * h0y + a01 * h1y + a02 * h2y;
    o[1] = a10 * h0x + a11 * h1x + a12 * h2x;
    o[2] = a00 * h0z + a01 * h1z + a02 * h2z;
    o[3] = a20 * h0x + a21 * h1x + a22 * h2x;
    o[4] = a10 * h0z + a11 * h1z + a12 * h2z;
    o[5] = a20 * h0y + a21 * h1y + a22 * h2y;
}

/* detect: (d_alpha0, d_beta0, d_rho, d_psi0, d_theta0, d_phi0) into d */
static void detect(const double *x, const double *R, const double *F, double k, double c_raab, double *d)
{
    double f[6], inv = 1.0 / k, fxy, fyx, fxz, fzx, fyz, fzy, rho;
    post_sense(x, R, F, f);
    fxy = f[0] * inv;
    fyx = f[1] * inv;
    fxz = f[2] * inv;
    fzx = f[3] * inv;
    fyz = f[4] * inv;
    fzy = f[5] * inv;
    d[0] = (2.0 / 3.0) * (2.0 * fxy - fyx);
    d[1] = (2.0 / 3.0) * (fzx - 2.0 * fxz);
    d[3] = 2.0 * (fxy - fyx);
    d[4] = 2.0 * (fzx - fxz);
    d[5] = fzy - fyz;
    rho = pow(c_raab / k, 1.0 / 3.0);
    d[2] = rho - x[2];
}

/* LoopCorrection.correct at the estimate; returns 1 when the linear term was dropped */
static int correct(const struct ct_raab *r, double px, double py, double pz)
{
    const double *b = r->b, *G = r->G, *R = r->R, *pm = r->pm, *S = r->S;
    double dx = px - pm[0], dy = py - pm[1], dz = pz - pm[2], lim = r->par[CT_RP_LIN_MAX] * r->x[2];
    int dropped = 0, j;
    if (dx * dx + dy * dy + dz * dz > pow(lim, 2.0)) {
        dx = dy = dz = 0.0;
        dropped = 1;
    }
    for (j = 0; j < r->n; ++j) {
        int o = 3 * j, g = 9 * j;
        double c = r->cur[j];
        double vx = (b[o] + G[g] * dx + G[g + 1] * dy + G[g + 2] * dz) * c;
        double vy = (b[o + 1] + G[g + 3] * dx + G[g + 4] * dy + G[g + 5] * dz) * c;
        double vz = (b[o + 2] + G[g + 6] * dx + G[g + 7] * dy + G[g + 8] * dz) * c;
        r->Sc[o] = S[o] - (R[0] * vx + R[3] * vy + R[6] * vz);
        r->Sc[o + 1] = S[o + 1] - (R[1] * vx + R[4] * vy + R[7] * vz);
        r->Sc[o + 2] = S[o + 2] - (R[2] * vx + R[5] * vy + R[8] * vz);
    }
    return dropped;
}

/* coupling: F = S_c M^+, returns k = |F|_F / sqrt(3/2) */
static double coupling(int n, const double *Sc, const double *mp, double *F)
{
    double f0 = 0.0, f1 = 0.0, f2 = 0.0, f3 = 0.0, f4 = 0.0, f5 = 0.0, f6 = 0.0, f7 = 0.0, f8 = 0.0;
    int j;
    for (j = 0; j < n; ++j) {
        int o = 3 * j;
        double s0 = Sc[o], s1 = Sc[o + 1], s2 = Sc[o + 2], m0 = mp[o], m1 = mp[o + 1], m2 = mp[o + 2];
        f0 += s0 * m0;
        f1 += s0 * m1;
        f2 += s0 * m2;
        f3 += s1 * m0;
        f4 += s1 * m1;
        f5 += s1 * m2;
        f6 += s2 * m0;
        f7 += s2 * m1;
        f8 += s2 * m2;
    }
    F[0] = f0; F[1] = f1; F[2] = f2; F[3] = f3; F[4] = f4; F[5] = f5; F[6] = f6; F[7] = f7; F[8] = f8;
    return sqrt(f0 * f0 + f1 * f1 + f2 * f2 + f3 * f3 + f4 * f4 + f5 * f5 + f6 * f6 + f7 * f7 + f8 * f8) / sqrt(1.5);
}

/* linalg.lu_solve: e <- K^-1 e (n = 6) */
static void lu_solve6(const double *K, const int64_t *perm, double *e)
{
    double y[6], acc;
    int i, j;
    for (i = 0; i < 6; ++i) {
        acc = e[perm[i]];
        for (j = 0; j < i; ++j)
            acc -= K[6 * i + j] * y[j];
        y[i] = acc;
    }
    for (i = 5; i >= 0; --i) {
        acc = y[i];
        for (j = i + 1; j < 6; ++j)
            acc -= K[6 * i + j] * e[j];
        e[i] = acc / K[6 * i + i];
    }
}

/* the signals corrected at the estimate (correct at raab_update.point, or S_c = S without the correction),
 * F and k (coupling) into out[CT_RO_K]; returns 1 when the correction's linear term was dropped */
static int couple(const struct ct_raab *r, double *k)
{
    const double *x = r->x, *c = r->cbar;
    int dropped = 0, i;
    if (r->corr) {
        double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]), q = x[2];
        dropped = correct(r, c[0] + q * cb * ca, c[1] + q * cb * sa, c[2] - q * sb);
    } else {
        for (i = 0; i < 3 * r->n; ++i)
            r->Sc[i] = r->S[i];
    }
    *k = coupling(r->n, r->Sc, r->mp, r->F);
    r->out[CT_RO_K] = *k;
    return dropped;
}

int ct_raab_coupling(const struct ct_raab *r)
{
    double k;
    return couple(r, &k) ? CT_RAAB_LIN_DROPPED : 0;
}

int ct_raab_update(const struct ct_raab *r, int lin, int k_id)
{
    double *x = r->x, *o = r->out, d[6], e[3], ab[2], A[9], k, m, rho;
    const double *par = r->par;
    int ret = 0, i;
    if (couple(r, &k)) {
        ret |= CT_RAAB_LIN_DROPPED;
        lin = 0;
    }
    if (!(k > 0.0 && isfinite(k)))
        return ret;
    detect(x, r->R, r->F, k, par[CT_RP_C], d);
    if (r->corr && lin && !k_id) {
        double big = fabs(d[0]);
        big = pymax(big, fabs(d[1]));
        big = pymax(big, fabs(d[2]) / x[2]);
        big = pymax(big, fabs(d[3]));
        big = pymax(big, fabs(d[4]));
        big = pymax(big, fabs(d[5]));
        if (big < par[CT_RP_LIN_STEP])
            lu_solve6(r->K, r->perm, d);
    }
    {
        double big = fabs(d[0]);
        big = pymax(big, fabs(d[1]));
        big = pymax(big, fabs(d[3]));
        big = pymax(big, fabs(d[4]));
        big = pymax(big, fabs(d[5]));
        o[CT_RO_ACQUIRED] = big < par[CT_RP_ACQUIRED_STEP] ? 1.0 : 0.0;
    }
    m = par[CT_RP_MAX_STEP];
    d[0] = clip(d[0], m);
    d[1] = clip(d[1], m);
    d[3] = clip(d[3], m);
    d[4] = clip(d[4], m);
    d[5] = clip(d[5], m);
    d[2] = clip(d[2], m * x[2]);
    rho = x[2] + d[2];
    orientation_update(x[0], x[1], x[3], x[4], x[5], d[5], d[4], d[3], par[CT_RP_POLE_COS], e);
    position_update(x[0], x[1], d[0], d[1], par[CT_RP_POLE_COS], ab);
    x[0] = ab[0];
    x[1] = ab[1];
    x[2] = rho;
    x[3] = e[0];
    x[4] = e[1];
    x[5] = e[2];
    dcm(x[3], x[4], x[5], A);               /* R = A^T (RaabTracker._sync_rotation) */
    r->R[0] = A[0]; r->R[1] = A[3]; r->R[2] = A[6];
    r->R[3] = A[1]; r->R[4] = A[4]; r->R[5] = A[7];
    r->R[6] = A[2]; r->R[7] = A[5]; r->R[8] = A[8];
    for (i = 0; i < 6; ++i)
        o[i] = d[i];
    return ret | CT_RAAB_OK;
}

/* model.field.dipole_polar with its gradient: (bx, by, bz, jxx, jyy, jzz, jxy, jxz, jyz) into o */
static void dipole_polar(double ux, double uy, double uz, double rho, double mx, double my, double mz, double c_raab,
                         double *o)
{
    double kd = 0.5 * c_raab / (rho * rho * rho), mu = mx * ux + my * uy + mz * uz, kj, f;
    o[0] = kd * (3.0 * mu * ux - mx);
    o[1] = kd * (3.0 * mu * uy - my);
    o[2] = kd * (3.0 * mu * uz - mz);
    kj = kd / rho;
    f = 15.0 * mu;
    o[3] = kj * (6.0 * ux * mx + 3.0 * mu - f * ux * ux);
    o[4] = kj * (6.0 * uy * my + 3.0 * mu - f * uy * uy);
    o[5] = kj * (6.0 * uz * mz + 3.0 * mu - f * uz * uz);
    o[6] = kj * (3.0 * (ux * my + mx * uy) - f * ux * uy);
    o[7] = kj * (3.0 * (ux * mz + mx * uz) - f * ux * uz);
    o[8] = kj * (3.0 * (uy * mz + my * uz) - f * uy * uz);
}

void ct_raab_refresh(const struct ct_raab_corr *c, const double *x, const double *Bv, const double *Jv,
                     const double *mpa, const double *w, const double *cur, const double *dd, int shift_ok,
                     double *out)
{
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double ux = cb * ca, uy = cb * sa, uz = -sb, ddx = dd[0], ddy = dd[1], ddz = dd[2], rel = 0.0, shift = 0.0;
    double *b = c->b, *G = c->G;
    int j, q;
    for (j = 0; j < c->n; ++j) {
        int o = 3 * j, g = 9 * j;
        double dp[9], nx, ny, nz, gg, jj, gxx, gyy, gzz, gxy, gxz, gyz;
        dipole_polar(ux, uy, uz, x[2], mpa[o], mpa[o + 1], mpa[o + 2], c->c_raab, dp);
        gxx = dp[3]; gyy = dp[4]; gzz = dp[5]; gxy = dp[6]; gxz = dp[7]; gyz = dp[8];
        nx = Bv[o] - dp[0];
        ny = Bv[o + 1] - dp[1];
        nz = Bv[o + 2] - dp[2];
        if (shift_ok) {
            double ex = nx - (b[o] + G[g] * ddx + G[g + 1] * ddy + G[g + 2] * ddz);
            double ey = ny - (b[o + 1] + G[g + 3] * ddx + G[g + 4] * ddy + G[g + 5] * ddz);
            double ez = nz - (b[o + 2] + G[g + 6] * ddx + G[g + 7] * ddy + G[g + 8] * ddz);
            double wm = w[o];
            if (w[o + 1] > wm)                  /* Python's max(w[o], w[o + 1], w[o + 2]) */
                wm = w[o + 1];
            if (w[o + 2] > wm)
                wm = w[o + 2];
            wm = wm * cur[j];
            shift += (ex * ex + ey * ey + ez * ez) * wm * wm;
        }
        b[o] = nx;
        b[o + 1] = ny;
        b[o + 2] = nz;
        G[g] = Jv[g] - gxx;
        G[g + 1] = Jv[g + 1] - gxy;
        G[g + 2] = Jv[g + 2] - gxz;
        G[g + 3] = Jv[g + 3] - gxy;
        G[g + 4] = Jv[g + 4] - gyy;
        G[g + 5] = Jv[g + 5] - gyz;
        G[g + 6] = Jv[g + 6] - gxz;
        G[g + 7] = Jv[g + 7] - gyz;
        G[g + 8] = Jv[g + 8] - gzz;
        gg = 0.0;
        for (q = g; q < g + 9; ++q)
            gg += G[q] * G[q];
        jj = gxx * gxx + gyy * gyy + gzz * gzz + 2.0 * (gxy * gxy + gxz * gxz + gyz * gyz);
        if (gg > rel * rel * jj)
            rel = sqrt(gg / jj);
    }
    out[0] = rel;
    out[1] = shift;
}

/* linalg.lu_factor of the 6 x 6 K in place, the permutation into perm; 0 when a pivot is below 1e-12 */
static int lu_factor6(double *K, int64_t *perm)
{
    int i, c, r, j;
    for (i = 0; i < 6; ++i)
        perm[i] = i;
    for (c = 0; c < 6; ++c) {
        int piv = c;
        double best = fabs(K[6 * c + c]), d;
        for (r = c + 1; r < 6; ++r)
            if (fabs(K[6 * r + c]) > best) {
                piv = r;
                best = fabs(K[6 * r + c]);
            }
        if (!(best > 1e-12))
            return 0;
        if (piv != c) {
            int64_t t;
            for (j = 0; j < 6; ++j) {
                double v = K[6 * c + j];
                K[6 * c + j] = K[6 * piv + j];
                K[6 * piv + j] = v;
            }
            t = perm[c];
            perm[c] = perm[piv];
            perm[piv] = t;
        }
        d = K[6 * c + c];
        for (r = c + 1; r < 6; ++r) {
            double f = K[6 * r + c] / d;
            K[6 * r + c] = f;
            for (j = c + 1; j < 6; ++j)
                K[6 * r + j] -= f * K[6 * c + j];
        }
    }
    return 1;
}

int ct_raab_precondition(const struct ct_raab_corr *c, const double *x, const double *mp, const double *cur, double k)
{
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double p00 = cb * ca, p01 = cb * sa, p02 = -sb, p10 = -sa, p11 = ca, p20 = sb * ca, p21 = sb * sa, p22 = cb;
    double rho = x[2], Fk[54], inv;
    const double *b = c->b, *G = c->G;
    double *K = c->K;
    int i, j, e, cc, r;
    for (i = 0; i < 54; ++i)
        Fk[i] = 0.0;
    for (j = 0; j < c->n; ++j) {
        double cj = cur[j], m0, m1, m2, q0, q1, q2, bx, by, bz, t0, t1, t2, cols[3][3], ys[6][3];
        const double E[3][3] = {{p00, p01, p02}, {p10, p11, 0.0}, {p20, p21, p22}};
        int o = 3 * j, g = 9 * j;
        m0 = mp[o];
        m1 = mp[o + 1];
        m2 = mp[o + 2];
        q0 = p00 * m0 + p01 * m1 + p02 * m2;
        q1 = p10 * m0 + p11 * m1;
        q2 = p20 * m0 + p21 * m1 + p22 * m2;
        bx = b[o] * cj;
        by = b[o + 1] * cj;
        bz = b[o + 2] * cj;
        t0 = p00 * bx + p01 * by + p02 * bz;
        t1 = p10 * bx + p11 * by;
        t2 = p20 * bx + p21 * by + p22 * bz;
        for (e = 0; e < 3; ++e) {               /* G_j P^T e_k = G_j (row k of P) */
            double e0 = E[e][0], e1 = E[e][1], e2 = E[e][2];
            double w0 = (G[g] * e0 + G[g + 1] * e1 + G[g + 2] * e2) * cj;
            double w1 = (G[g + 3] * e0 + G[g + 4] * e1 + G[g + 5] * e2) * cj;
            double w2 = (G[g + 6] * e0 + G[g + 7] * e1 + G[g + 8] * e2) * cj;
            cols[e][0] = p00 * w0 + p01 * w1 + p02 * w2;
            cols[e][1] = p10 * w0 + p11 * w1;
            cols[e][2] = p20 * w0 + p21 * w1 + p22 * w2;
        }
        for (i = 0; i < 3; ++i) {
            ys[0][i] = rho * cols[1][i];
            ys[1][i] = -rho * cols[2][i];
            ys[2][i] = cols[0][i];
        }
        ys[3][0] = t1; ys[3][1] = -t0; ys[3][2] = 0.0;
        ys[4][0] = -t2; ys[4][1] = 0.0; ys[4][2] = t0;
        ys[5][0] = 0.0; ys[5][1] = t2; ys[5][2] = -t1;
        for (cc = 0; cc < 6; ++cc) {
            double y0 = ys[cc][0], y1 = ys[cc][1], y2 = ys[cc][2];
            int f = 9 * cc;
            Fk[f] += y0 * q0;
            Fk[f + 1] += y0 * q1;
            Fk[f + 2] += y0 * q2;
            Fk[f + 3] += y1 * q0;
            Fk[f + 4] += y1 * q1;
            Fk[f + 5] += y1 * q2;
            Fk[f + 6] += y2 * q0;
            Fk[f + 7] += y2 * q1;
            Fk[f + 8] += y2 * q2;
        }
    }
    inv = 1.0 / k;
    for (cc = 0; cc < 6; ++cc) {
        int f = 9 * cc;
        double fxy = Fk[f + 1] * inv, fyx = Fk[f + 3] * inv, fxz = Fk[f + 2] * inv, fzx = Fk[f + 6] * inv,
               fyz = Fk[f + 5] * inv, fzy = Fk[f + 7] * inv, col[6];
        col[0] = (2.0 / 3.0) * (2.0 * fxy - fyx);
        col[1] = (2.0 / 3.0) * (fzx - 2.0 * fxz);
        col[2] = -(rho / 9.0) * (2.0 * Fk[f] - Fk[f + 4] - Fk[f + 8]) * inv;
        col[3] = 2.0 * (fxy - fyx);
        col[4] = 2.0 * (fzx - fxz);
        col[5] = fzy - fyz;
        for (r = 0; r < 6; ++r)
            K[6 * r + cc] = col[r] + (r == cc ? 1.0 : 0.0);
    }
    return lu_factor6(K, c->perm);
}

/* raab_update.moment_pseudo_inverse: the moments at the currents into mom ([3 j + a]) and M^+ = M^T (M M^T)^-1
 * into mp ([3 j + c]); 0 when the moments do not span 3-D (mom written, mp not) */
int ct_raab_pseudo_inverse(int n, const double *mpa, const double *cur, double *mom, double *mp)
{
    double g00 = 0.0, g01 = 0.0, g02 = 0.0, g11 = 0.0, g12 = 0.0, g22 = 0.0, scale, a[9], inv[9], det;
    double i00, i01, i02, i11, i12, i22;
    int j;
    for (j = 0; j < n; ++j) {
        double c = cur[j], mx = mpa[3 * j] * c, my = mpa[3 * j + 1] * c, mz = mpa[3 * j + 2] * c;
        mom[3 * j] = mx;
        mom[3 * j + 1] = my;
        mom[3 * j + 2] = mz;
        g00 += mx * mx;
        g01 += mx * my;
        g02 += mx * mz;
        g11 += my * my;
        g12 += my * mz;
        g22 += mz * mz;
    }
    scale = g00 + g11 + g22;
    if (!(scale > 0.0))
        return 0;
    a[0] = g00 / scale;
    a[1] = a[3] = g01 / scale;
    a[2] = a[6] = g02 / scale;
    a[4] = g11 / scale;
    a[5] = a[7] = g12 / scale;
    a[8] = g22 / scale;
    det = a[0] * (a[4] * a[8] - a[5] * a[5]) - a[1] * (a[1] * a[8] - a[5] * a[2]) + a[2] * (a[1] * a[5] - a[4] * a[2]);
    if (!(det > 1e-12) || !ct_inv3(a, inv))        /* linalg.inv3_sym */
        return 0;
    i00 = inv[0] / scale;
    i01 = inv[1] / scale;
    i02 = inv[2] / scale;
    i11 = inv[4] / scale;
    i12 = inv[5] / scale;
    i22 = inv[8] / scale;
    for (j = 0; j < n; ++j) {
        double mx = mom[3 * j], my = mom[3 * j + 1], mz = mom[3 * j + 2];
        mp[3 * j] = mx * i00 + my * i01 + mz * i02;
        mp[3 * j + 1] = mx * i01 + my * i11 + mz * i12;
        mp[3 * j + 2] = mx * i02 + my * i12 + mz * i22;
    }
    return 1;
}

/* ------------------------------------------------------------ begin's inputs */

/* raab_update.is_rotation: m (9, row-major) orthonormal by rows to tol with determinant > 0 */
int ct_raab_is_rotation(const double *m, double tol)
{
    double a0 = m[0], a1 = m[1], a2 = m[2], a3 = m[3], a4 = m[4], a5 = m[5], a6 = m[6], a7 = m[7], a8 = m[8];
    if (!(fabs(a0 * a0 + a1 * a1 + a2 * a2 - 1.0) < tol && fabs(a3 * a3 + a4 * a4 + a5 * a5 - 1.0) < tol &&
          fabs(a6 * a6 + a7 * a7 + a8 * a8 - 1.0) < tol && fabs(a0 * a3 + a1 * a4 + a2 * a5) < tol &&
          fabs(a0 * a6 + a1 * a7 + a2 * a8) < tol && fabs(a3 * a6 + a4 * a7 + a5 * a8) < tol))
        return 0;
    return a0 * (a4 * a8 - a5 * a7) - a1 * (a3 * a8 - a5 * a6) + a2 * (a3 * a7 - a4 * a6) > 0.0;
}

/* raab_update.angles_from_pose: (alpha, beta, rho, psi, theta, phi) of p (from the source centre) and
 * R (row-major, sensor -> source) into x */
void ct_raab_angles_from_pose(double px, double py, double pz, const double *R, double *x)
{
    double rho = sqrt(px * px + py * py + pz * pz), rxy = hypot(px, py), a[9], e[3];
    double alpha = rxy > 0.0 ? atan2(py, px) : 0.0, beta = atan2(-pz, rxy);
    a[0] = R[0]; a[1] = R[3]; a[2] = R[6];          /* A = R^T */
    a[3] = R[1]; a[4] = R[4]; a[5] = R[7];
    a[6] = R[2]; a[7] = R[5]; a[8] = R[8];
    euler(a, e);
    x[0] = alpha;
    x[1] = beta;
    x[2] = rho;
    x[3] = e[0];
    x[4] = e[1];
    x[5] = e[2];
}

/* StagedSolve._load: the signals, weights and currents; 0 on a value not finite or a sigma not positive */
static int raab_load(const struct ct_raab_io *in, const double *S, const double *sigma, int64_t rs, int64_t cs,
                     const double *cur, int64_t cstride)
{
    int n = in->n, i, j;
    double ssum = 0.0;
    for (i = 0; i < 3; ++i)
        for (j = 0; j < n; ++j) {
            double s = S[i * rs + j * cs], sg = sigma[i * rs + j * cs];
            if (!(isfinite(s) && isfinite(sg) && sg > 0.0))
                return 0;
            in->Sv[3 * j + i] = s;
            in->wv[3 * j + i] = 1.0 / sg;
            ssum += sg * sg;
        }
    for (j = 0; j < n; ++j) {
        double c = cur[j * cstride];
        if (!isfinite(c))
            return 0;
        in->cur[j] = c;
    }
    *in->sigma_rms = sqrt(ssum / (double)(3 * n));
    return 1;
}

int ct_raab_inputs(const struct ct_raab_io *in, const double *S, const double *sigma, int64_t rs, int64_t cs,
                   const double *cur, int64_t cstride, const double *hemi, const double *x0p, const double *x0R,
                   int x0_pair)
{
    double *h = in->hemi, *m9 = in->m9, *R = in->R;
    int i, j;
    if (!raab_load(in, S, sigma, rs, cs, cur, cstride))
        return CT_RIN_BAD_LOAD;
    if (hemi == NULL) {                                     /* _load_hemisphere */
        h[0] = 1.0;
        h[1] = 0.0;
        h[2] = 0.0;
    } else {
        double hx = hemi[0], hy = hemi[1], hz = hemi[2];
        h[0] = hx;
        h[1] = hy;
        h[2] = hz;
        if (!(isfinite(hx) && isfinite(hy) && isfinite(hz) && (hx * hx + hy * hy + hz * hz) > 0.0))
            return CT_RIN_BAD_HEMI;
    }
    if (!x0_pair)                                           /* _load_x0 */
        return CT_RIN_BAD_X0;
    if (x0p != NULL) {
        double px, py, pz;
        for (i = 0; i < 3; ++i) {
            if (!isfinite(x0p[i]))
                return CT_RIN_BAD_X0;
            for (j = 0; j < 3; ++j) {
                m9[3 * i + j] = x0R[3 * i + j];
                if (!isfinite(m9[3 * i + j]))
                    return CT_RIN_BAD_X0;
            }
        }
        if (!ct_raab_is_rotation(m9, in->tol))              /* load_rotation */
            return CT_RIN_PROJECT;
        memcpy(R, m9, 9 * sizeof(double));
        px = x0p[0] - in->cbar[0];
        py = x0p[1] - in->cbar[1];
        pz = x0p[2] - in->cbar[2];
        if (px * px + py * py + pz * pz <= 0.0)
            return CT_RIN_BAD_X0;
        ct_raab_angles_from_pose(px, py, pz, R, in->x);
    }
    if (!ct_raab_pseudo_inverse(in->n, in->mpa, in->cur, in->mom, in->mp))
        return CT_RIN_NO_START;
    return CT_RIN_OK;
}

/* raab_update.residual_cost: sum ((S_c - R^T h_raab(x)) w)^2, h_raab the dipole (model.field.dipole_polar
 * without its gradient) of the moments mom */
double ct_raab_residual_cost(const struct ct_raab_io *io)
{
    const double *x = io->x, *R = io->R, *Sc = io->Sc, *w = io->wv, *mom = io->mom;
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double ux = cb * ca, uy = cb * sa, uz = -sb, rho = x[2], cost = 0.0;
    int j, i;
    for (j = 0; j < io->n; ++j) {
        int o = 3 * j;
        double mx = mom[o], my = mom[o + 1], mz = mom[o + 2];
        double kd = 0.5 * io->c_raab / (rho * rho * rho), mu = mx * ux + my * uy + mz * uz;
        double bx = kd * (3.0 * mu * ux - mx), by = kd * (3.0 * mu * uy - my), bz = kd * (3.0 * mu * uz - mz);
        for (i = 0; i < 3; ++i) {
            double e = (Sc[o + i] - (R[i] * bx + R[3 + i] * by + R[6 + i] * bz)) * w[o + i];
            cost += e * e;
        }
    }
    return cost;
}

int ct_raab_finish_pose(const struct ct_raab_io *io)
{
    const double *x = io->x, *c = io->cbar;
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]), r = x[2], a[9];
    double px = c[0] + r * cb * ca, py = c[1] + r * cb * sa, pz = c[2] - r * sb, *R = io->R;
    int i;
    io->position[0] = px;
    io->position[1] = py;
    io->position[2] = pz;
    dcm(x[3], x[4], x[5], a);                   /* sync_rotation: R = A^T */
    R[0] = a[0]; R[1] = a[3]; R[2] = a[6];
    R[3] = a[1]; R[4] = a[4]; R[5] = a[7];
    R[6] = a[2]; R[7] = a[5]; R[8] = a[8];
    memcpy(io->rotation, R, 9 * sizeof(double));
    for (i = 0; i < 6; ++i)
        io->angles[i] = x[i];
    return isfinite(px) && isfinite(py) && isfinite(pz);
}

int ct_raab_moved(const struct ct_raab_io *io, double refresh)
{
    const double *x = io->x, *c = io->cbar, *pm = io->pm;
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]), r = x[2];
    double px = c[0] + r * cb * ca, py = c[1] + r * cb * sa, pz = c[2] - r * sb;    /* point */
    double dx = px - pm[0], dy = py - pm[1], dz = pz - pm[2];
    return dx * dx + dy * dy + dz * dz > pow(refresh * x[2], 2.0);
}

int ct_raab_behind(const struct ct_raab_io *io, int acquiring)
{
    const double *x = io->x, *h = acquiring ? io->acq_hemi : io->hemi;
    double hx = h[0], hy = h[1], hz = h[2];
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double ux = cb * ca, uy = cb * sa, uz = -sb, hn = sqrt(hx * hx + hy * hy + hz * hz);
    return ux * hx + uy * hy + uz * hz < -io->margin * hn;
}
