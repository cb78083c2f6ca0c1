/*
 * The end of a pulsed-DC pose solve and its grading: see include/ct_finish.h.  Each function
 * follows the Python named beside it operation by operation (-ffp-contract=off), so the results
 * are the same to the bit (tests/firmware/core/test_core_finish.py).
 */
#include <math.h>
#include <string.h>

#include "coiltrack_core.h"

/* ---------------------------------------------------------------- Jacobi */

/* linalg._sort_eigen: the diagonal of a into w, ascending, the columns of v following */
static void sort_eigen(const double *a, int n, double *w, double *v)
{
    int i, j, k, r;
    for (i = 0; i < n; ++i)
        w[i] = a[i * n + i];
    for (i = 0; i < n - 1; ++i) {
        k = i;
        for (j = i + 1; j < n; ++j)
            if (w[j] < w[k])
                k = j;
        if (k != i) {
            double t = w[i];
            w[i] = w[k];
            w[k] = t;
            for (r = 0; r < n; ++r) {
                t = v[r * n + i];
                v[r * n + i] = v[r * n + k];
                v[r * n + k] = t;
            }
        }
    }
}

/* linalg.jacobi_eigh_loops (cyclic Jacobi, Golub & Van Loan sec. 8.5; jacobi_eigh is its
 * straight-line form, the same bits) */
void ct_fin_jacobi_eigh(double *a, int n, double *w, double *v, int sweeps)
{
    int i, j, p, q, r, sw;
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j)
            v[i * n + j] = i == j ? 1.0 : 0.0;
    for (sw = 0; sw < sweeps; ++sw) {
        double off = 0.0, tot = 0.0;
        for (p = 0; p < n; ++p) {
            tot += a[p * n + p] * a[p * n + p];
            for (q = p + 1; q < n; ++q) {
                double x = a[p * n + q];
                off += x * x;
            }
        }
        tot += 2.0 * off;
        if (off <= 1e-30 * tot || off == 0.0)
            break;
        for (p = 0; p < n - 1; ++p)
            for (q = p + 1; q < n; ++q) {
                const int pn = p * n, qn = q * n;
                double apq = a[pn + q], app, aqq, theta, t, c, s;
                if (apq == 0.0)
                    continue;
                app = a[pn + p];
                aqq = a[qn + q];
                theta = (aqq - app) / (2.0 * apq);
                t = (theta >= 0.0 ? 1.0 : -1.0) / (fabs(theta) + sqrt(theta * theta + 1.0));
                c = 1.0 / sqrt(t * t + 1.0);
                s = t * c;
                a[pn + p] = app - t * apq;
                a[qn + q] = aqq + t * apq;
                a[pn + q] = 0.0;
                a[qn + p] = 0.0;
                for (r = 0; r < n; ++r) {
                    const int rn = r * n;
                    double vrp, vrq;
                    if (r != p && r != q) {
                        const double arp = a[rn + p], arq = a[rn + q];
                        const double nrp = c * arp - s * arq;
                        const double nrq = s * arp + c * arq;
                        a[rn + p] = nrp;
                        a[pn + r] = nrp;
                        a[rn + q] = nrq;
                        a[qn + r] = nrq;
                    }
                    vrp = v[rn + p];
                    vrq = v[rn + q];
                    v[rn + p] = c * vrp - s * vrq;
                    v[rn + q] = s * vrp + c * vrq;
                }
            }
    }
    sort_eigen(a, n, w, v);
}

/* linalg.nearest_rotation: the unit quaternion maximising q^T K q (K from m, below) is the
 * eigenvector of K's largest eigenvalue (the last column of v); its rotation matrix is
 * rotation.matrix_from_quat's */
void ct_nearest_rotation(const double *m, double *out, double *work, double tol)
{
    double *k = work, *w = work + 16, *v = work + 20;
    double qw, qx, qy, qz, nrm;
    if (ct_is_rotation(m, tol)) {
        memcpy(out, m, 9 * sizeof(double));
        return;
    }
    k[0] = m[0] + m[4] + m[8];
    k[1] = k[4] = m[7] - m[5];
    k[2] = k[8] = m[2] - m[6];
    k[3] = k[12] = m[3] - m[1];
    k[5] = m[0] - m[4] - m[8];
    k[6] = k[9] = m[1] + m[3];
    k[7] = k[13] = m[2] + m[6];
    k[10] = -m[0] + m[4] - m[8];
    k[11] = k[14] = m[5] + m[7];
    k[15] = -m[0] - m[4] + m[8];
    ct_fin_jacobi_eigh(k, 4, w, v, 60);
    qw = v[3];
    qx = v[7];
    qy = v[11];
    qz = v[15];
    nrm = sqrt(qw * qw + qx * qx + qy * qy + qz * qz);
    qw /= nrm;
    qx /= nrm;
    qy /= nrm;
    qz /= nrm;
    out[0] = 1.0 - 2.0 * (qy * qy + qz * qz);
    out[1] = 2.0 * (qx * qy - qw * qz);
    out[2] = 2.0 * (qx * qz + qw * qy);
    out[3] = 2.0 * (qx * qy + qw * qz);
    out[4] = 1.0 - 2.0 * (qx * qx + qz * qz);
    out[5] = 2.0 * (qy * qz - qw * qx);
    out[6] = 2.0 * (qx * qz - qw * qy);
    out[7] = 2.0 * (qy * qz + qw * qx);
    out[8] = 1.0 - 2.0 * (qx * qx + qy * qy);
}

/* ------------------------------------------------------------ covariance */

/* Python's max(a, b) of two non-NaN floats: a unless b > a */
static double py_max(double a, double b)
{
    return b > a ? b : a;
}

/* RobustInverse6._floored: the eigenvalues of a floored at max(EIG_FLOOR top, 1 / MAX_VARIANCE) */
static void robust_floored(const double *a, double *cov, double *m, double *w, double *V)
{
    int i, j, k;
    double top, floor;
    memcpy(m, a, 36 * sizeof(double));
    ct_fin_jacobi_eigh(m, 6, w, V, 60);
    top = w[5] > 0.0 ? w[5] : 0.0;
    floor = py_max(CT_EIG_FLOOR * top, 1.0 / CT_MAX_VARIANCE);
    for (k = 0; k < 6; ++k)
        if (w[k] < floor)
            w[k] = floor;
    for (i = 0; i < 6; ++i)
        for (j = i; j < 6; ++j) {
            double acc = 0.0;
            for (k = 0; k < 6; ++k)
                acc += V[i * 6 + k] * V[j * 6 + k] / w[k];
            cov[i * 6 + j] = acc;
            cov[j * 6 + i] = acc;
        }
}

void ct_robust_inverse6(const double *a, double *cov, double *work)
{
    double *L = work, *M = work + 36, *m = work + 72, *V = work + 108, *w = work + 144;
    double tr, floor_hi;
    int i, k;
    for (i = 0; i < 36; ++i)
        if (!isfinite(a[i])) {
            for (k = 0; k < 36; ++k)
                cov[k] = k % 7 == 0 ? CT_MAX_VARIANCE : 0.0;
            return;
        }
    tr = a[0] + a[7] + a[14] + a[21] + a[28] + a[35];
    floor_hi = py_max(CT_EIG_FLOOR * py_max(tr, 0.0), 1.0 / CT_MAX_VARIANCE);
    if (ct_spd_inverse(6, a, cov, L, M)) {
        const double tri = cov[0] + cov[7] + cov[14] + cov[21] + cov[28] + cov[35];
        if (tri > 0.0 && 1.0 / tri >= floor_hi)
            return;
    }
    robust_floored(a, cov, m, w, V);
}

void ct_rotation_margin(double *cov)
{
    const double t00 = cov[21], t01 = cov[22], t02 = cov[23], t11 = cov[28], t12 = cov[29], t22 = cov[35];
    const double tr = t00 + t11 + t22;
    double s3[9], inv[9], i00, i01, i02, i11, i12, i22, s, a, b;
    int i, j;
    if (!(tr > 0.0) || !isfinite(tr))
        return;
    s3[0] = t00; s3[1] = s3[3] = t01; s3[2] = s3[6] = t02;
    s3[4] = t11; s3[5] = s3[7] = t12; s3[8] = t22;
    if (!ct_inv3(s3, inv))                 /* linalg.inv3_sym */
        return;
    i00 = inv[0]; i01 = inv[1]; i02 = inv[2]; i11 = inv[4]; i12 = inv[5]; i22 = inv[8];
    s = tr > CT_MARGIN_MAX_ORI_VAR ? CT_MARGIN_MAX_ORI_VAR / tr : 1.0;
    a = 0.25 * tr * s * s;                 /* of C_pt C_tt^-1 C_tp */
    b = 0.5 * s * s;                       /* of C_pt C_tp */
    for (i = 0; i < 3; ++i) {
        const double c0 = cov[6 * i + 3], c1 = cov[6 * i + 4], c2 = cov[6 * i + 5];
        const double k0 = c0 * i00 + c1 * i01 + c2 * i02;
        const double k1 = c0 * i01 + c1 * i11 + c2 * i12;
        const double k2 = c0 * i02 + c1 * i12 + c2 * i22;
        for (j = i; j < 3; ++j) {
            const double d0 = cov[6 * j + 3], d1 = cov[6 * j + 4], d2 = cov[6 * j + 5];
            const double m = a * (k0 * d0 + k1 * d1 + k2 * d2) + b * (c0 * d0 + c1 * d1 + c2 * d2);
            cov[6 * i + j] += m;
            if (j != i)
                cov[6 * j + i] += m;
        }
    }
}

/* ---------------------------------------------------------------- solver */

/* pose.solver._HEMI_MARGIN */
#define CT_HEMI_MARGIN 0.1

int ct_warm_start_failed(const struct ct_warmcheck *w, int state, double cost, const double *p)
{
    double hx, hy, hz, dx, dy, dz, lim;
    if (w->n < 3)
        return 0;                          /* no acquisition to fall back to */
    if (state != CT_LM_CONVERGED || !(cost <= w->gate))
        return 1;
    if (!w->check_hemi)
        return 0;
    hx = w->hemi[0];
    hy = w->hemi[1];
    hz = w->hemi[2];
    dx = p[0] - w->cbar[0];
    dy = p[1] - w->cbar[1];
    dz = p[2] - w->cbar[2];
    lim = CT_HEMI_MARGIN * sqrt((dx * dx + dy * dy + dz * dz) * (hx * hx + hy * hy + hz * hz));
    return dx * hx + dy * hy + dz * hz < -lim;
}

int ct_solve_finish(const struct ct_warmcheck *w, int check, int state, double cost, const double *p,
                    const double *A, double *cov, double *work)
{
    if (check && ct_warm_start_failed(w, state, cost, p))
        return -1;
    ct_robust_inverse6(A, cov, work);
    ct_rotation_margin(cov);
    return isfinite(p[0]) && isfinite(p[1]) && isfinite(p[2]) && isfinite(cov[0]);
}

/* --------------------------------------------------------------- quality */

int ct_quality_from(double var_trace_m2, double x, double scale_m, double motion_m2)
{
    double e, v;
    int q;
    if (!(isfinite(x) && isfinite(var_trace_m2) && isfinite(motion_m2)) || var_trace_m2 < 0.0 || motion_m2 < 0.0)
        return 0;
    e = sqrt(var_trace_m2 * (x > 1.0 ? x : 1.0) + motion_m2);
    v = 255.0 * scale_m / (scale_m + e) + 0.5;
    if (!(v >= 0.0))                       /* (a scale the configuration refuses) */
        return 0;
    q = v >= 256.0 ? 256 : (int)v;         /* int(): truncation of a positive value */
    return q > 255 ? 255 : q;
}

/* PoseQuality._jacobian: H_j = [R^T J_j, [h_j]x] with h_j the measured column S[:, j] and J_j the
 * dipole gradient (eq 10) written in the field itself */
static void quality_jacobian(const struct ct_quality *qs, const double *p, const double *R, const double *S)
{
    const int n = qs->n;
    double *H = qs->H;
    int j, i;
    for (j = 0; j < n; ++j) {
        const double hx = S[j], hy = S[n + j], hz = S[2 * n + j];
        const double bx = R[0] * hx + R[1] * hy + R[2] * hz;
        const double by = R[3] * hx + R[4] * hy + R[5] * hz;
        const double bz = R[6] * hx + R[7] * hy + R[8] * hz;
        const double *c = qs->centers + 3 * j;
        const double rx = p[0] - c[0], ry = p[1] - c[1], rz = p[2] - c[2];
        double r = sqrt(rx * rx + ry * ry + rz * rz);
        double nx, ny, nz, b, mx, my, mz, mr, k, j00, j11, j22, j01, j02, j12;
        int o;
        if (!(r > 0.0))
            r = 1e-9;
        nx = rx / r;
        ny = ry / r;
        nz = rz / r;
        b = bx * nx + by * ny + bz * nz;
        mx = 1.5 * b * nx - bx;
        my = 1.5 * b * ny - by;
        mz = 1.5 * b * nz - bz;
        mr = 0.5 * b;
        k = 3.0 / r;
        j00 = k * (2.0 * mx * nx + mr - 5.0 * mr * nx * nx);
        j11 = k * (2.0 * my * ny + mr - 5.0 * mr * ny * ny);
        j22 = k * (2.0 * mz * nz + mr - 5.0 * mr * nz * nz);
        j01 = k * (mx * ny + nx * my - 5.0 * mr * nx * ny);
        j02 = k * (mx * nz + nx * mz - 5.0 * mr * nx * nz);
        j12 = k * (my * nz + ny * mz - 5.0 * mr * ny * nz);
        for (i = 0; i < 3; ++i) {
            const double a0 = R[i], a1 = R[3 + i], a2 = R[6 + i];
            o = 6 * (3 * j + i);
            H[o] = a0 * j00 + a1 * j01 + a2 * j02;
            H[o + 1] = a0 * j01 + a1 * j11 + a2 * j12;
            H[o + 2] = a0 * j02 + a1 * j12 + a2 * j22;
        }
        o = 18 * j;
        H[o + 3] = 0.0;
        H[o + 4] = -hz;
        H[o + 5] = hy;
        H[o + 9] = hz;
        H[o + 10] = 0.0;
        H[o + 11] = -hx;
        H[o + 15] = -hy;
        H[o + 16] = hx;
        H[o + 17] = 0.0;
    }
}

/* PoseQuality._motion: motion[0] = |dp_motion|^2, motion[1] = chi2_motion of this burst (both
 * left 0 without a recent previous solution) */
static void quality_motion(const struct ct_quality *qs, const double *st, int64_t t_us, const double *cov,
                           const double *p, const double *R, const double *S, const double *sigma,
                           const int64_t *start, const int64_t *end, double *motion)
{
    const int n = qs->n;
    double *H = qs->H, *u = qs->u, *g = qs->g, *dx = qs->dx, *d = qs->d, *xd = qs->xd;
    double dt_us, inv, a[9], wv[3], m2, c2;
    int j, q, k, i;
    if (st == NULL || st[0] == 0.0)
        return;
    dt_us = (double)t_us - st[1];
    if (!(0.0 < dt_us && dt_us <= qs->max_gap_us))
        return;
    inv = 1e6 / dt_us;
    xd[0] = (p[0] - st[2]) * inv;
    xd[1] = (p[1] - st[3]) * inv;
    xd[2] = (p[2] - st[4]) * inv;
    /* R_prev^T R (sensor frame): element (i, j) = sum_k R_prev[k, i] R[k, j] */
    a[0] = st[5] * R[0] + st[8] * R[3] + st[11] * R[6];
    a[1] = st[5] * R[1] + st[8] * R[4] + st[11] * R[7];
    a[2] = st[5] * R[2] + st[8] * R[5] + st[11] * R[8];
    a[3] = st[6] * R[0] + st[9] * R[3] + st[12] * R[6];
    a[4] = st[6] * R[1] + st[9] * R[4] + st[12] * R[7];
    a[5] = st[6] * R[2] + st[9] * R[5] + st[12] * R[8];
    a[6] = st[7] * R[0] + st[10] * R[3] + st[13] * R[6];
    a[7] = st[7] * R[1] + st[10] * R[4] + st[13] * R[7];
    a[8] = st[7] * R[2] + st[10] * R[5] + st[13] * R[8];
    ct_fusion_rotvec_from_matrix(a, wv);   /* linalg.rotvec_from_matrix */
    xd[3] = wv[0] * inv;
    xd[4] = wv[1] * inv;
    xd[5] = wv[2] * inv;
    for (j = 0; j < n; ++j)
        d[j] = ((double)(start[j] + end[j]) * 0.5 - (double)t_us) * 1e-6;
    quality_jacobian(qs, p, R, S);
    /* u = D H xdot; g = H^T W u */
    for (k = 0; k < 6; ++k)
        g[k] = 0.0;
    for (q = 0; q < 3 * n; ++q) {
        const int o = 6 * q;
        const double s = sigma[(q % 3) * n + q / 3];
        const double w = s > 0.0 ? 1.0 / (s * s) : 0.0;
        const double uq = d[q / 3] * (H[o] * xd[0] + H[o + 1] * xd[1] + H[o + 2] * xd[2]
                                      + H[o + 3] * xd[3] + H[o + 4] * xd[4] + H[o + 5] * xd[5]);
        const double wu = w * uq;
        u[q] = uq;
        for (k = 0; k < 6; ++k)
            g[k] += H[o + k] * wu;
    }
    /* dx = P g */
    for (i = 0; i < 6; ++i) {
        double acc = 0.0;
        for (k = 0; k < 6; ++k)
            acc += cov[6 * i + k] * g[k];
        dx[i] = acc;
    }
    m2 = dx[0] * dx[0] + dx[1] * dx[1] + dx[2] * dx[2];
    /* the residual the motion leaves: u - H dx, weighted */
    c2 = 0.0;
    for (q = 0; q < 3 * n; ++q) {
        const int o = 6 * q;
        const double s = sigma[(q % 3) * n + q / 3];
        if (s > 0.0) {
            const double r = u[q] - (H[o] * dx[0] + H[o + 1] * dx[1] + H[o + 2] * dx[2]
                                     + H[o + 3] * dx[3] + H[o + 4] * dx[4] + H[o + 5] * dx[5]);
            c2 += r * r / (s * s);
        }
    }
    if (isfinite(m2) && isfinite(c2)) {
        motion[0] = m2;
        motion[1] = c2;
    }
}

/* PoseQuality._remember */
static void quality_remember(double *st, int64_t t_us, const double *p, const double *R)
{
    st[0] = 1.0;
    st[1] = (double)t_us;
    st[2] = p[0];
    st[3] = p[1];
    st[4] = p[2];
    memcpy(st + 5, R, 9 * sizeof(double));
}

int ct_grade_burst(const struct ct_quality *qs, double *prev, int64_t t_us, double cost, const double *cov,
                   const double *p, const double *R, const double *S, const double *sigma, const int64_t *start,
                   const int64_t *end, double nis, double quiet, double *motion)
{
    const double var_trace = cov[0] + cov[7] + cov[14];
    double fit, x;
    motion[0] = motion[1] = 0.0;
    if (qs->n) {
        quality_motion(qs, prev, t_us, cov, p, R, S, sigma, start, end, motion);
        if (prev != NULL)
            quality_remember(prev, t_us, p, R);
    }
    fit = cost - motion[1];
    x = (qs->dof > 0 && fit > 0.0 ? fit / qs->dof : 0.0) + nis + quiet;
    return ct_quality_from(var_trace, x, qs->scale, motion[0]);
}

/* ---------------------------------------------------------------- report */

int ct_report_take(const double *p, const double *R, double range_m, double *dst_p, double *dst_R)
{
    if (!(sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2]) <= range_m))
        return 0;
    memcpy(dst_p, p, 3 * sizeof(double));
    memcpy(dst_R, R, 9 * sizeof(double));
    return 1;
}
