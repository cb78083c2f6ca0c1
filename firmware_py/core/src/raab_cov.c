/*
 * The covariance of Raab's tracker (Raab et al. 1979, seeds/004_86267342cd7488ce.txt, eqs 3-5):
 * coiltrack.firmware.pose.raab_covariance.RaabCovariance (rows, publish with _carry_too_far,
 * _cov_form, _cov_carry, _published_sigmas) and the Cholesky path of
 * pose.covariance.RobustInverse6.into (ct_spd_inverse).  The same operations in the same order
 * as the Python, except the information A = (q K)^T (q K), which the reference forms through
 * numpy's matmul (the machine's BLAS): here the sums run over the rows in increasing order
 * (1e-12 relative).  Where RobustInverse6 would take its eigenvalue floor (a near-singular
 * information: the Cholesky inverse fails or breaks the floor), ct_raab_cov_publish changes no
 * state and returns 0: the caller runs the Python reference for that publication.
 */
#include "coiltrack_core.h"

#include <math.h>
#include <string.h>

/* Python's min(a, b) / max(a, b): b only when b < a / b > a */
static double pymin(double a, double b)
{
    return b < a ? b : a;
}

static double pymax(double a, double b)
{
    return b > a ? b : a;
}

/* raab_covariance.mul3: o = a b of two 3x3 (row-major); o must not alias a or b */
static void mul3(const double *a, const double *b, double *o)
{
    o[0] = a[0] * b[0] + a[1] * b[3] + a[2] * b[6];
    o[1] = a[0] * b[1] + a[1] * b[4] + a[2] * b[7];
    o[2] = a[0] * b[2] + a[1] * b[5] + a[2] * b[8];
    o[3] = a[3] * b[0] + a[4] * b[3] + a[5] * b[6];
    o[4] = a[3] * b[1] + a[4] * b[4] + a[5] * b[7];
    o[5] = a[3] * b[2] + a[4] * b[5] + a[5] * b[8];
    o[6] = a[6] * b[0] + a[7] * b[3] + a[8] * b[6];
    o[7] = a[6] * b[1] + a[7] * b[4] + a[8] * b[7];
    o[8] = a[6] * b[2] + a[7] * b[5] + a[8] * b[8];
}

/* raab_covariance.block: the 3x3 block at row r, column k of a 6x6 */
static void block(const double *c, int r, int k, double *o)
{
    int s = 6 * r + k;
    o[0] = c[s]; o[1] = c[s + 1]; o[2] = c[s + 2];
    o[3] = c[s + 6]; o[4] = c[s + 7]; o[5] = c[s + 8];
    o[6] = c[s + 12]; o[7] = c[s + 13]; o[8] = c[s + 14];
}

void ct_raab_cov_rows(const struct ct_raab_cov *c, const double *Bv, const double *Jv)
{
    int j;
    double *K = c->K;
    for (j = 0; j < c->n; ++j) {
        int o = 3 * j, g = 9 * j, k = 18 * j;
        double Bx = Bv[o], By = Bv[o + 1], Bz = Bv[o + 2];
        K[k] = Jv[g]; K[k + 1] = Jv[g + 1]; K[k + 2] = Jv[g + 2]; K[k + 3] = 0.0; K[k + 4] = -Bz; K[k + 5] = By;
        K[k + 6] = Jv[g + 3]; K[k + 7] = Jv[g + 4]; K[k + 8] = Jv[g + 5]; K[k + 9] = Bz; K[k + 10] = 0.0;
        K[k + 11] = -Bx;
        K[k + 12] = Jv[g + 6]; K[k + 13] = Jv[g + 7]; K[k + 14] = Jv[g + 8]; K[k + 15] = -By; K[k + 16] = Bx;
        K[k + 17] = 0.0;
    }
}

/* A = (q rows)^T (q rows), rows (3 n, 6), q (3 n): np.multiply then np.matmul of the reference */
static void information(int n, const double *rows, const double *q, double *A)
{
    int i, k, r;
    for (i = 0; i < 6; ++i)
        for (k = i; k < 6; ++k) {
            double acc = 0.0;
            for (r = 0; r < 3 * n; ++r)
                acc += (rows[6 * r + i] * q[r]) * (rows[6 * r + k] * q[r]);
            A[6 * i + k] = acc;
            A[6 * k + i] = acc;
        }
}

/* pose.covariance.RobustInverse6.into without its eigenvalue floor: 1 when out holds the
 * robust inverse of a, 0 when the floored eigen-decomposition is needed (out then undefined) */
static int robust_inverse(const double *par, const double *a, double *out, double *L, double *M)
{
    int i;
    double tr, floor_hi, tri;
    for (i = 0; i < 36; ++i)
        if (!isfinite(a[i])) {
            for (i = 0; i < 36; ++i)
                out[i] = i % 7 == 0 ? par[CT_RCP_MAX_VARIANCE] : 0.0;
            return 1;
        }
    tr = a[0] + a[7] + a[14] + a[21] + a[28] + a[35];
    floor_hi = pymax(par[CT_RCP_EIG_FLOOR] * pymax(tr, 0.0), 1.0 / par[CT_RCP_MAX_VARIANCE]);
    if (ct_spd_inverse(6, a, out, L, M)) {
        tri = out[0] + out[7] + out[14] + out[21] + out[28] + out[35];
        if (tri > 0.0 && 1.0 / tri >= floor_hi)
            return 1;
    }
    return 0;
}

/* RaabCovariance._carry_too_far */
static int carry_too_far(const struct ct_raab_cov *c, const double *pm, double rel, const double *point, double rho)
{
    const double *pc = c->pc, *par = c->par;
    double lim, dx, dy, dz;
    if (pc[0] == pm[0] && pc[1] == pm[1] && pc[2] == pm[2])
        return 0;
    lim = rel > 0.0 ? pymin(par[CT_RCP_CARRY_MAX], par[CT_RCP_COV_TOL] / (15.0 * rel)) : par[CT_RCP_CARRY_MAX];
    dx = point[0] - pc[0];
    dy = point[1] - pc[1];
    dz = point[2] - pc[2];
    return dx * dx + dy * dy + dz * dz > pow(lim * rho, 2.0);
}

/* RaabCovariance._cov_carry: C_s carried to the estimate x (rotation R) times scale, into cov */
static void cov_carry(const struct ct_raab_cov *c, double scale, const double *x, const double *R)
{
    const double *cb_ = c->cbar, *pm = c->pc, *Cs = c->Cs;
    double *cov = c->cov;
    double mx = pm[0] - cb_[0], my = pm[1] - cb_[1], mz = pm[2] - cb_[2], rm;
    double ca = cos(x[0]), sa = sin(x[0]), cb = cos(x[1]), sb = sin(x[1]);
    double ux, uy, uz, wx, wy, wz, h, Q[9], Qt[9], M[9], Mt[9], t, t2, t6, f8, f7, B[9], T[9];
    double pp[9], pt[9], tt[9];
    int i, k;
    rm = sqrt(mx * mx + my * my + mz * mz);
    mx = mx / rm;
    my = my / rm;
    mz = mz / rm;
    ux = cb * ca;
    uy = cb * sa;
    uz = -sb;
    wx = my * uz - mz * uy;
    wy = mz * ux - mx * uz;
    wz = mx * uy - my * ux;
    h = 1.0 / (1.0 + mx * ux + my * uy + mz * uz);
    Q[0] = 1.0 - h * (wy * wy + wz * wz);
    Q[4] = 1.0 - h * (wx * wx + wz * wz);
    Q[8] = 1.0 - h * (wx * wx + wy * wy);
    Q[1] = h * wx * wy - wz;
    Q[3] = h * wx * wy + wz;
    Q[2] = h * wx * wz + wy;
    Q[6] = h * wx * wz - wy;
    Q[5] = h * wy * wz - wx;
    Q[7] = h * wy * wz + wx;
    for (i = 0; i < 3; ++i)
        for (k = 0; k < 3; ++k)
            Qt[3 * i + k] = Q[3 * k + i];
    mul3(Qt, R, M);                             /* M = Q^T R */
    for (i = 0; i < 3; ++i)
        for (k = 0; k < 3; ++k)
            Mt[3 * i + k] = M[3 * k + i];
    t = x[2] / rm;
    t2 = t * t;
    t6 = t2 * t2 * t2 * scale;
    block(Cs, 0, 0, B);
    mul3(Q, B, T);
    mul3(T, Qt, pp);
    block(Cs, 0, 3, B);
    mul3(Q, B, T);
    mul3(T, M, pt);
    block(Cs, 3, 3, B);
    mul3(Mt, B, T);
    mul3(T, M, tt);
    f8 = t6 * t2;
    f7 = t6 * t;
    for (i = 0; i < 3; ++i)
        for (k = 0; k < 3; ++k) {
            double v;
            cov[6 * i + k] = f8 * pp[3 * i + k];
            v = f7 * pt[3 * i + k];
            cov[6 * i + 3 + k] = v;
            cov[6 * (3 + k) + i] = v;
            cov[6 * (3 + i) + 3 + k] = t6 * tt[3 * i + k];
        }
}

/* RaabCovariance._published_sigmas into st */
static void published_sigmas(const struct ct_raab_cov *c)
{
    const double *cov = c->cov;
    double vp = pymin(pymin(cov[0], cov[7]), cov[14]), vo = pymin(pymin(cov[21], cov[28]), cov[35]);
    c->st[CT_RCS_SIG_P] = vp > 0.0 && isfinite(vp) ? sqrt(vp) : 0.0;
    c->st[CT_RCS_SIG_O] = vo > 0.0 && isfinite(vo) ? sqrt(vo) : 0.0;
}

/* the sensor-frame form of RaabCovariance._cov_form (weights differing between a coil's axes)
 * into T; 1 when inverted without the floor */
static int form_sensor(const struct ct_raab_cov *c, const double *R, const double *w, const double *cur)
{
    int n = c->n, j, i, k;
    const double *K = c->K;
    double *q = c->q, *H = c->H;
    for (j = 0; j < n; ++j)
        for (i = 0; i < 3; ++i) {
            double r0 = R[i], r1 = R[3 + i], r2 = R[6 + i];     /* row i of R^T */
            int o = 18 * j + 6 * i;
            q[3 * j + i] = w[3 * j + i] * cur[j];
            for (k = 0; k < 6; ++k)
                H[o + k] = r0 * K[18 * j + k] + r1 * K[18 * j + 6 + k] + r2 * K[18 * j + 12 + k];
        }
    information(n, H, q, c->A);
    return robust_inverse(c->par, c->A, c->T, c->L, c->M);
}

int ct_raab_cov_publish(const struct ct_raab_cov *c, const double *x, const double *R, const double *w,
                        const double *cur, const double *pm, double rel)
{
    int n = c->n, j, iso = 1, cs_ok;
    double scale = 1.0, point[3], ca, sa, cb, sb;
    double *q = c->q, *qm = c->qm;
    for (j = 0; j < n; ++j) {
        double w0 = w[3 * j], tol = c->par[CT_RCP_ISO_TOL] * w0;
        if (fabs(w[3 * j + 1] - w0) > tol || fabs(w[3 * j + 2] - w0) > tol) {
            iso = 0;
            break;
        }
    }
    if (!iso) {
        if (!form_sensor(c, R, w, cur))
            return 0;
        c->st[CT_RCS_CS_OK] = 0.0;
        memcpy(c->cov, c->T, 36 * sizeof(double));
        published_sigmas(c);
        return 1;
    }
    /* raab_update.point(x, cbar) */
    ca = cos(x[0]);
    sa = sin(x[0]);
    cb = cos(x[1]);
    sb = sin(x[1]);
    point[0] = c->cbar[0] + x[2] * cb * ca;
    point[1] = c->cbar[1] + x[2] * cb * sa;
    point[2] = c->cbar[2] - x[2] * sb;
    cs_ok = c->st[CT_RCS_CS_OK] != 0.0;
    if (cs_ok && carry_too_far(c, pm, rel, point, x[2]))
        cs_ok = 0;
    if (cs_ok) {
        double num = 0.0, den = 0.0, s2, lo = 1.0 - 2.0 * c->par[CT_RCP_Q_TOL], hi = 1.0 + 2.0 * c->par[CT_RCP_Q_TOL];
        for (j = 0; j < n; ++j) {
            double qj = w[3 * j] * cur[j];
            num += qj * qj;
            den += qm[j] * qm[j];
        }
        if (den == 0.0)
            return 0;                           /* the reference divides by zero */
        s2 = num / den;
        for (j = 0; j < n; ++j) {
            double qj = w[3 * j] * cur[j], d = qm[j] * qm[j] * s2, r;
            if (d == 0.0)
                return 0;
            r = qj * qj / d;
            if (!(lo <= r && r <= hi)) {
                cs_ok = 0;
                break;
            }
        }
        if (s2 == 0.0)
            return 0;
        scale = 1.0 / s2;
    }
    if (!cs_ok) {
        for (j = 0; j < n; ++j) {
            double qj = w[3 * j] * cur[j];
            q[3 * j] = q[3 * j + 1] = q[3 * j + 2] = qj;
        }
        information(n, c->K, q, c->A);
        if (!robust_inverse(c->par, c->A, c->T, c->L, c->M))
            return 0;
        for (j = 0; j < n; ++j)
            qm[j] = q[3 * j];
        memcpy(c->Cs, c->T, 36 * sizeof(double));
        c->pc[0] = pm[0];
        c->pc[1] = pm[1];
        c->pc[2] = pm[2];
        scale = 1.0;
    }
    c->st[CT_RCS_CS_OK] = 1.0;
    cov_carry(c, scale, x, R);
    published_sigmas(c);
    return 1;
}
