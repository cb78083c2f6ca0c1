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
#include <string.h>

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

static void predict_24_dense(const double *restrict A, double *restrict P, const double *restrict Q,
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

/* The reference's sums restricted to what they can reach.  With A's non-zero entries all finite and
 * in rows and columns < M (16): T's columns >= M are never read (P = T A^T reads T[i, k] at A's non-zero
 * k only), T's rows >= M are zeros, so P's rows >= M are sums of (+0.0) * a from 0.0, which are +0.0,
 * and P's columns >= M sums of nothing, +0.0 as well.  So T = A P is formed on its first M columns and
 * P = T A^T on its first M rows and columns, each element with the reference's terms in the
 * reference's order (a product's two factors commute exactly): the same bits.  Column j of P is
 * row j of W = (T A^T)^T, summed over the rows of U = T^T, so that every inner loop runs along
 * contiguous rows of a fixed length the compiler can pair.  (The ch. 6 transition, eq 6.17, has its
 * white states QM, PSI, XI last: rows and columns 15-23 of A are zero.)  Any other A (an entry
 * beyond, inf or NaN: 0 * inf is not 0) takes the dense loops. */
#define M 16
void ct_covariance_predict_24(const double *restrict A, double *restrict P, const double *restrict Q,
                              double *restrict T)
{
    double U[M * M], W[M * M];
    uint64_t beyond = 0, special = 0, b;
    int nz[M * M], cnt[M];                     /* each row's non-zero columns, increasing */
    int i, j, k, c;
    for (i = 0; i < M; ++i) {                  /* A's bits: inf or NaN in the block (exponent all ones: */
        const double *Ai = A + i * N;          /* adding one to it carries into the top bit), */
        for (k = 0; k < M; ++k) {
            memcpy(&b, Ai + k, sizeof b);
            special |= ((b & 0x7ff0000000000000u) + 0x0010000000000000u) & 0x8000000000000000u;
        }
        for (k = M; k < N; ++k) {              /* non-zero beyond it (-0.0 is zero) */
            memcpy(&b, Ai + k, sizeof b);
            beyond |= b << 1;
        }
    }
    for (i = M * N; i < N * N; ++i) {
        memcpy(&b, A + i, sizeof b);
        beyond |= b << 1;
    }
    if (beyond != 0 || special != 0) {
        predict_24_dense(A, P, Q, T);
        return;
    }
    for (i = 0; i < M; ++i) {                          /* (without a branch per entry) */
        const double *Ai = A + i * N;
        c = 0;
        for (k = 0; k < M; ++k) {
            nz[i * M + c] = k;
            c += Ai[k] != 0.0;
        }
        cnt[i] = c;
    }
    for (i = 0; i < M; ++i) {                          /* T = A P, rows and columns < M */
        const double *Ai = A + i * N;
        double *Ti = T + i * N;
        for (j = 0; j < M; ++j)
            Ti[j] = 0.0;
        for (c = 0; c < cnt[i]; ++c) {
            const double a = Ai[nz[i * M + c]];
            const double *Pk = P + nz[i * M + c] * N;
            for (j = 0; j < M; ++j)
                Ti[j] += a * Pk[j];
        }
    }
    for (i = 0; i < M; ++i)                            /* U = T^T */
        for (k = 0; k < M; ++k)
            U[k * M + i] = T[i * N + k];
    for (j = 0; j < M; ++j) {                          /* W[j, i] = P[i, j] = sum_k T[i, k] A[j, k] */
        const double *Aj = A + j * N;
        double *Wj = W + j * M;
        for (i = 0; i < M; ++i)
            Wj[i] = 0.0;
        for (c = 0; c < cnt[j]; ++c) {
            const double a = Aj[nz[j * M + c]];
            const double *Uk = U + nz[j * M + c] * M;
            for (i = 0; i < M; ++i)
                Wj[i] += Uk[i] * a;
        }
    }
    for (i = 0; i < M; ++i) {                          /* P = W^T + Q, 0.0 + Q beyond */
        double *Pi = P + i * N;
        const double *Qi = Q + i * N;
        for (j = 0; j < M; ++j)
            Pi[j] = W[j * M + i] + Qi[j];
        for (j = M; j < N; ++j)
            Pi[j] = 0.0 + Qi[j];
    }
    for (i = M * N; i < N * N; ++i)
        P[i] = 0.0 + Q[i];
}
#undef M
