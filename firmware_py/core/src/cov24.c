/*
 * The covariance prediction P <- A P A^T + Q (thesis seeds/002_cd7f1fdb7fc67471.txt eq 6.5, the
 * transition of eq 6.17; reference coiltrack.firmware.estimate.ekf.CovariancePredict.predict,
 * compiled as ekf.c ct_covariance_predict) at the ch. 6 fusion filter's size, 24 states: every
 * strapdown step of the live state and of a delayed update's replay runs it.
 *
 * The operations and their order are ekf.c ct_congruence_sparse's followed by P += Q: T = A P
 * row by row over A's non-zero entries, each element a sum from 0.0 in increasing k; P = T A^T
 * column by column over the non-zero entries of A's rows, each element from 0.0 in increasing k;
 * then Q added element by element. The size is a constant and the buffers do not alias
 * (restrict), so the compiler runs the element loops two elements at a time; each element's
 * arithmetic is unchanged (no contraction, no reassociation: -ffp-contract=off), so the results
 * are the same bits.
 */
#include <stdint.h>

#include "coiltrack_core.h"

#define N CT_COV24_N

static int apart(const double *x, const double *y)
{
    const uintptr_t a = (uintptr_t)x, b = (uintptr_t)y, len = (uintptr_t)(N * N) * sizeof(double);
    return a + len <= b || b + len <= a;
}

int ct_cov24_disjoint(const double *A, const double *P, const double *Q, const double *T)
{
    return apart(A, P) && apart(A, T) && apart(P, Q) && apart(P, T) && apart(Q, T);
}

void ct_covariance_predict_24(const double *restrict A, double *restrict P, const double *restrict Q,
                              double *restrict T)
{
    int i, j, k;
    for (i = 0; i < N * N; ++i)
        T[i] = 0.0;
    for (i = 0; i < N; ++i) {                          /* T = A P */
        const double *Ai = A + i * N;
        double *Ti = T + i * N;
        for (k = 0; k < N; ++k) {
            const double a = Ai[k];
            const double *Pk = P + k * N;
            if (a == 0.0)
                continue;
            for (j = 0; j < N; ++j)
                Ti[j] += a * Pk[j];
        }
    }
    for (i = 0; i < N * N; ++i)
        P[i] = 0.0;
    for (j = 0; j < N; ++j) {                          /* P = T A^T */
        const double *Aj = A + j * N;
        for (k = 0; k < N; ++k) {
            const double a = Aj[k];
            if (a == 0.0)
                continue;
            for (i = 0; i < N; ++i)
                P[i * N + j] += T[i * N + k] * a;
        }
    }
    for (i = 0; i < N * N; ++i)                        /* + Q */
        P[i] += Q[i];
}
