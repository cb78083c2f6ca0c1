/*
 * Covariance prediction of every Kalman filter of the firmware: the compiled form of
 * coiltrack.firmware.estimate.ekf.CovariancePredict.predict,
 *
 *     P <- A P A^T + Q          (thesis seeds/002_cd7f1fdb7fc67471.txt eq 2.18 / 6.5, Fig. 4.3)
 *
 * with the structural zeros of the transition A skipped (A is sparse: the error transition of
 * eq 6.17 has about 60 non-zero entries of 576 in the 24-state filter), so the two products cost
 * 2 nnz(A) n multiply-adds instead of 2 n^3.  Each entry is summed over k in increasing order,
 * and Q is added last, as the reference adds it after the product; the reference's products go
 * through BLAS, whose blocking and fused multiply-adds differ by machine, so the two agree to
 * rounding (relative 1e-15 per step), not bit for bit.
 */
#include <math.h>

#include "coiltrack_core.h"

void ct_congruence_sparse(int n, const double *A, double *P, double *T)
{
    int i, j, k;
    /* T = A P, row by row over A's non-zero entries */
    for (i = 0; i < n * n; ++i)
        T[i] = 0.0;
    for (i = 0; i < n; ++i) {
        const double *Ai = A + i * n;
        double *Ti = T + i * n;
        for (k = 0; k < n; ++k) {
            double a = Ai[k];
            const double *Pk = P + k * n;
            if (a == 0.0)
                continue;
            for (j = 0; j < n; ++j)
                Ti[j] += a * Pk[j];
        }
    }
    /* P = T A^T: P[i, j] = sum_k T[i, k] A[j, k], column j over row j of A's non-zero entries */
    for (i = 0; i < n * n; ++i)
        P[i] = 0.0;
    for (j = 0; j < n; ++j) {
        const double *Aj = A + j * n;
        for (k = 0; k < n; ++k) {
            double a = Aj[k];
            if (a == 0.0)
                continue;
            for (i = 0; i < n; ++i)
                P[i * n + j] += T[i * n + k] * a;
        }
    }
}

void ct_covariance_predict(int n, const double *A, double *P, const double *Q, double *T)
{
    int i;
    if (n == CT_COV24_N && ct_cov24_disjoint(A, P, Q, T)) {   /* cov24.c: the same sums at the fixed size */
        ct_covariance_predict_24(A, P, Q, T);
        return;
    }
    ct_congruence_sparse(n, A, P, T);
    for (i = 0; i < n * n; ++i)
        P[i] += Q[i];
}

/* linalg.inv3_sym of the lower triangle of the flat 3x3 s into the flat out (ekf._inv3);
 * 0 when s is not positive definite (Sylvester) or its determinant is not finite. */
int ct_inv3(const double *s, double *out)
{
    double a00 = s[0], a01 = s[3], a02 = s[6], a11 = s[4], a12 = s[7], a22 = s[8];
    double c00 = a11 * a22 - a12 * a12;
    double c01 = a02 * a12 - a01 * a22;
    double c02 = a01 * a12 - a02 * a11;
    double c22 = a00 * a11 - a01 * a01;
    double det = a00 * c00 + a01 * c01 + a02 * c02;
    double inv, c11, c12;
    if (!(a00 > 0.0 && c22 > 0.0 && det > 0.0) || det == HUGE_VAL)
        return 0;
    inv = 1.0 / det;
    c11 = a00 * a22 - a02 * a02;
    c12 = a01 * a02 - a00 * a12;
    out[0] = c00 * inv;
    out[1] = c01 * inv;
    out[2] = c02 * inv;
    out[4] = c11 * inv;
    out[5] = c12 * inv;
    out[8] = c22 * inv;
    out[3] = out[1];
    out[6] = out[2];
    out[7] = out[5];
    return 1;
}

/* linalg.spd_inverse(n) (chol_inverse in the order of its generated straight-line code): the
 * inverse of the SPD matrix whose lower triangle is in a (n x n) into out; L, M: n x n scratch.
 * 0 when a pivot is not positive or infinite. */
int ct_spd_inverse(int n, const double *a, double *out, double *L, double *M)
{
    int i, j, k;
    for (j = 0; j < n; ++j) {
        double s = a[j * n + j], r;
        for (k = 0; k < j; ++k)
            s = s - L[j * n + k] * L[j * n + k];
        if (!(s > 0.0) || s == HUGE_VAL)
            return 0;
        L[j * n + j] = sqrt(s);
        r = 1.0 / L[j * n + j];
        M[j * n + j] = r;               /* r_j, kept as m_jj below */
        for (i = j + 1; i < n; ++i) {
            double t = a[i * n + j];
            for (k = 0; k < j; ++k)
                t = t - L[i * n + k] * L[j * n + k];
            L[i * n + j] = t * r;
        }
    }
    for (j = 0; j < n; ++j) {           /* L^-1: m_ij, i > j */
        for (i = j + 1; i < n; ++i) {
            double t = -(L[i * n + j] * M[j * n + j]);
            for (k = j + 1; k < i; ++k)
                t = t - L[i * n + k] * M[k * n + j];
            M[i * n + j] = t / L[i * n + i];
        }
    }
    for (i = 0; i < n; ++i) {           /* L^-T L^-1 */
        for (j = i; j < n; ++j) {
            double t = M[j * n + i] * M[j * n + j];
            for (k = j + 1; k < n; ++k)
                t = t + M[k * n + i] * M[k * n + j];
            out[i * n + j] = t;
            out[j * n + i] = t;
        }
    }
    return 1;
}

/* out (n x m) = A (n x n) H^T, H (m x n) row-major; H's structural zeros skipped.  The sums run
 * over k in the same order as the reference's, so the result does not depend on the zeros. */
static void mul_ht(int n, int m, const double *A, const double *H, double *out)
{
    int i, k, r;
    for (i = 0; i < n * m; ++i)
        out[i] = 0.0;
    for (r = 0; r < m; ++r)
        for (k = 0; k < n; ++k) {
            double h = H[r * n + k];
            if (h == 0.0)
                continue;
            for (i = 0; i < n; ++i)
                out[i * m + r] += A[i * n + k] * h;
        }
}

/* Row i of T = P - K (H P): out[j] = prow[j] - sum_r krow[r] PHt[j, r], the sum over r in order from
 * 0.0 for every j (the reference's dot products), four j at a time: four independent sums in flight
 * instead of one chain of dependent additions (the same operations in the same order, so the same
 * bits; 2-3x faster on the 24-state fusion update, whose 9-row sums were bound by the adds' latency). */
static void kt_rows(int n, int m, const double *krow, const double *PHt, const double *prow, double *out)
{
    int j = 0, r;
    for (; j + 4 <= n; j += 4) {
        const double *a = PHt + j * m;
        double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
        for (r = 0; r < m; ++r) {
            const double k = krow[r];
            s0 += k * a[r];
            s1 += k * a[m + r];
            s2 += k * a[2 * m + r];
            s3 += k * a[3 * m + r];
        }
        out[j] = prow[j] - s0;
        out[j + 1] = prow[j + 1] - s1;
        out[j + 2] = prow[j + 2] - s2;
        out[j + 3] = prow[j + 3] - s3;
    }
    for (; j < n; ++j) {
        double s = 0.0;
        for (r = 0; r < m; ++r)
            s += krow[r] * PHt[j * m + r];
        out[j] = prow[j] - s;
    }
}

/* Row i of the Joseph form's end: x1 = sum_r th[r] K[j, r], x2 = sum_r kr[r] K[j, r] (each in order
 * from 0.0), xrow[j] = x2, prow[j] = (trow[j] - x1) + x2; four j at a time as kt_rows. */
static void joseph_rows(int n, int m, const double *th, const double *kr, const double *K, const double *trow,
                        double *xrow, double *prow)
{
    int j = 0, r;
    for (; j + 4 <= n; j += 4) {
        const double *a = K + j * m;
        double x10 = 0.0, x11 = 0.0, x12 = 0.0, x13 = 0.0;
        double x20 = 0.0, x21 = 0.0, x22 = 0.0, x23 = 0.0;
        for (r = 0; r < m; ++r) {
            const double t = th[r], q = kr[r];
            const double k0 = a[r], k1 = a[m + r], k2 = a[2 * m + r], k3 = a[3 * m + r];
            x10 += t * k0;
            x20 += q * k0;
            x11 += t * k1;
            x21 += q * k1;
            x12 += t * k2;
            x22 += q * k2;
            x13 += t * k3;
            x23 += q * k3;
        }
        xrow[j] = x20;
        xrow[j + 1] = x21;
        xrow[j + 2] = x22;
        xrow[j + 3] = x23;
        prow[j] = (trow[j] - x10) + x20;
        prow[j + 1] = (trow[j + 1] - x11) + x21;
        prow[j + 2] = (trow[j + 2] - x12) + x22;
        prow[j + 3] = (trow[j + 3] - x13) + x23;
    }
    for (; j < n; ++j) {
        double x1 = 0.0, x2 = 0.0;
        for (r = 0; r < m; ++r) {
            x1 += th[r] * K[j * m + r];
            x2 += kr[r] * K[j * m + r];
        }
        xrow[j] = x2;
        prow[j] = (trow[j] - x1) + x2;
    }
}

/* out[c] = sum_r a[r] B[r, c] (B: len rows of m), the sum over r in order from 0.0 for every c (the
 * reference's dot products; with skip, the terms of a zero a[r] left out, as H's structural zeros
 * are), four c at a time as kt_rows: the same bits. */
static void vec_mat(int len, int m, const double *a, const double *B, double *out, int skip)
{
    int c = 0, r;
    for (; c + 4 <= m; c += 4) {
        double s0 = 0.0, s1 = 0.0, s2 = 0.0, s3 = 0.0;
        for (r = 0; r < len; ++r) {
            const double x = a[r];
            const double *b = B + r * m + c;
            if (skip && x == 0.0)
                continue;
            s0 += x * b[0];
            s1 += x * b[1];
            s2 += x * b[2];
            s3 += x * b[3];
        }
        out[c] = s0;
        out[c + 1] = s1;
        out[c + 2] = s2;
        out[c + 3] = s3;
    }
    for (; c < m; ++c) {
        double s = 0.0;
        for (r = 0; r < len; ++r) {
            const double x = a[r];
            if (skip && x == 0.0)
                continue;
            s += x * B[r * m + c];
        }
        out[c] = s;
    }
}

/* KalmanUpdate.update: the one update of every filter (innovation variance, chi-square gate,
 * gain, Joseph form P = (I - K H) P (I - K H)^T + K R K^T; thesis eqs 2.19-2.25 / 6.6-6.7),
 * the structural zeros of H skipped.  Returns the health flags; *nis receives the NIS (inf when
 * S is not positive definite); dx is zeroed on a rejection. */
int ct_kalman_update(const struct ct_kalman *u, double *P, double gate, double *nis_out)
{
    int n = u->n, m = u->m, i, r, c;
    const double *H = u->H, *R = u->R, *y = u->y;
    double *PHt = u->PHt, *S = u->S, *Si = u->Sinv, *K = u->K, *dx = u->dx, *w = u->w;
    double *T = u->T, *TH = u->TH, *X = u->X, *KR = u->KR;
    double nis;
    int ok;

    /* PHt = P H^T, S = H PHt + R */
    mul_ht(n, m, P, H, PHt);
    for (r = 0; r < m; ++r) {
        vec_mat(n, m, H + r * n, PHt, S + r * m, 1);
        for (c = 0; c < m; ++c)
            S[r * m + c] = S[r * m + c] + R[r * m + c];
    }
    ok = m == 3 ? ct_inv3(S, Si) : ct_spd_inverse(m, S, Si, u->L, u->M);
    if (!ok) {
        for (i = 0; i < n; ++i)
            dx[i] = 0.0;
        *nis_out = HUGE_VAL;
        return CT_EKF_NOT_PD;
    }
    for (r = 0; r < m; ++r) {
        double s = 0.0;
        for (c = 0; c < m; ++c)
            s += Si[r * m + c] * y[c];
        w[r] = s;
    }
    nis = 0.0;
    for (r = 0; r < m; ++r)
        nis += y[r] * w[r];
    *nis_out = nis;
    if (!(nis - nis == 0.0)) {          /* not finite */
        for (i = 0; i < n; ++i)
            dx[i] = 0.0;
        return CT_EKF_NONFINITE;
    }
    if (nis > gate) {
        for (i = 0; i < n; ++i)
            dx[i] = 0.0;
        return CT_EKF_GATED;
    }
    /* K = PHt S^-1, dx = K y */
    for (i = 0; i < n; ++i) {
        double d = 0.0;
        vec_mat(m, m, PHt + i * m, Si, K + i * m, 0);
        for (c = 0; c < m; ++c)
            d += K[i * m + c] * y[c];
        dx[i] = d;
    }
    /* T = P - K (H P), with H P = PHt^T (P symmetric); four columns at a time (kt_rows) */
    for (i = 0; i < n; ++i)
        kt_rows(n, m, K + i * m, PHt, P + i * n, T + i * n);
    /* TH = T H^T (H's zeros skipped), X = TH K^T, P = T - X */
    mul_ht(n, m, T, H, TH);
    /* KR = K R */
    for (i = 0; i < n; ++i)
        vec_mat(m, m, K + i * m, R, KR + i * m, 0);
    /* P = T - TH K^T + KR K^T; four columns at a time (joseph_rows) */
    for (i = 0; i < n; ++i)
        joseph_rows(n, m, TH + i * m, KR + i * m, K, T + i * n, X + i * n, P + i * n);
    return CT_EKF_OK;
}

void ct_kalman_bind(struct ct_kalman *u, int n, int m, double *const *buf)
{
    u->n = n;
    u->m = m;
    u->H = buf[0];
    u->R = buf[1];
    u->y = buf[2];
    u->dx = buf[3];
    u->S = buf[4];
    u->Sinv = buf[5];
    u->K = buf[6];
    u->PHt = buf[7];
    u->T = buf[8];
    u->TH = buf[9];
    u->X = buf[10];
    u->KR = buf[11];
    u->w = buf[12];
    u->L = buf[13];
    u->M = buf[14];
}
