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

/* KalmanUpdate.update: the one update of every filter (innovation variance, chi-square gate,
 * gain, Joseph form P = (I - K H) P (I - K H)^T + K R K^T; thesis eqs 2.19-2.25 / 6.6-6.7),
 * the structural zeros of H skipped.  Returns the health flags; *nis receives the NIS (inf when
 * S is not positive definite); dx is zeroed on a rejection. */
int ct_kalman_update(const struct ct_kalman *u, double *P, double gate, double *nis_out)
{
    int n = u->n, m = u->m, i, j, k, r, c;
    const double *H = u->H, *R = u->R, *y = u->y;
    double *PHt = u->PHt, *S = u->S, *Si = u->Sinv, *K = u->K, *dx = u->dx, *w = u->w;
    double *T = u->T, *TH = u->TH, *X = u->X, *KR = u->KR;
    double nis;
    int ok;

    /* PHt = P H^T, S = H PHt + R */
    mul_ht(n, m, P, H, PHt);
    for (r = 0; r < m; ++r)
        for (c = 0; c < m; ++c) {
            double s = 0.0;
            for (k = 0; k < n; ++k) {
                double h = H[r * n + k];
                if (h != 0.0)
                    s += h * PHt[k * m + c];
            }
            S[r * m + c] = s + R[r * m + c];
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
        for (c = 0; c < m; ++c) {
            double s = 0.0;
            for (r = 0; r < m; ++r)
                s += PHt[i * m + r] * Si[r * m + c];
            K[i * m + c] = s;
        }
        for (c = 0; c < m; ++c)
            d += K[i * m + c] * y[c];
        dx[i] = d;
    }
    /* T = P - K (H P), with H P = PHt^T (P symmetric) */
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            double s = 0.0;
            for (r = 0; r < m; ++r)
                s += K[i * m + r] * PHt[j * m + r];
            T[i * n + j] = P[i * n + j] - s;
        }
    /* TH = T H^T (H's zeros skipped), X = TH K^T, P = T - X */
    mul_ht(n, m, T, H, TH);
    /* KR = K R */
    for (i = 0; i < n; ++i)
        for (c = 0; c < m; ++c) {
            double s = 0.0;
            for (r = 0; r < m; ++r)
                s += K[i * m + r] * R[r * m + c];
            KR[i * m + c] = s;
        }
    /* P = T - TH K^T + KR K^T */
    for (i = 0; i < n; ++i)
        for (j = 0; j < n; ++j) {
            double x1 = 0.0, x2 = 0.0;
            for (r = 0; r < m; ++r) {
                x1 += TH[i * m + r] * K[j * m + r];
                x2 += KR[i * m + r] * K[j * m + r];
            }
            X[i * n + j] = x2;
            P[i * n + j] = (T[i * n + j] - x1) + x2;
        }
    return CT_EKF_OK;
}
