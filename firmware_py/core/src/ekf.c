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
#include "coiltrack_core.h"

void ct_covariance_predict(int n, const double *A, double *P, const double *Q, double *T)
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
    for (i = 0; i < n * n; ++i)
        P[i] += Q[i];
}
