/*
 * Synchronous demodulation of AC excitation: coiltrack.firmware.measure.demod.Demodulator
 * (Raab et al. 1979, seeds/004_86267342cd7488ce.txt, sec. II and eq 7: the coupling of each
 * coil to each sensor axis by synchronous detection of its carrier).  Per block of T_w the
 * samples are fitted by least squares with b(t) = c0 + c1 tau + sum_k [a_k cos(w_k (t - t_ref))
 * + q_k sin(w_k (t - t_ref))]; the normal equations are accumulated per sample in every block
 * the sample lies in (ct_demod_push), a finished block is solved through one Cholesky
 * factorisation (ct_demod_finish).  The same operations in the same order as the Python.
 */
#include "coiltrack_core.h"

#include <math.h>

static const double TWO_PI = 2.0 * 3.141592653589793;

/* Python's floor division a // b for b > 0 */
static int64_t floordiv(int64_t a, int64_t b)
{
    int64_t q = a / b;
    if ((a % b) != 0 && a < 0)
        q -= 1;
    return q;
}

/* linalg.cholesky: lower factor of the symmetric n x n a into L; 0 when a pivot is not positive / finite */
static int chol(const double *a, int n, double *L)
{
    int i, j, k;
    for (j = 0; j < n; ++j) {
        int jn = j * n;
        double s = a[jn + j], d, inv;
        for (k = 0; k < j; ++k) {
            double v = L[jn + k];
            s -= v * v;
        }
        if (!(s > 0.0) || s == HUGE_VAL)
            return 0;
        d = sqrt(s);
        L[jn + j] = d;
        inv = 1.0 / d;
        for (i = j + 1; i < n; ++i) {
            int inn = i * n;
            s = a[inn + j];
            for (k = 0; k < j; ++k)
                s -= L[inn + k] * L[jn + k];
            L[inn + j] = s * inv;
        }
        for (i = j + 1; i < n; ++i)
            L[jn + i] = 0.0;
    }
    return 1;
}

/* linalg.chol_solve: L L^T x = b */
static void chol_solve(const double *L, int n, const double *b, double *x)
{
    int i, k;
    for (i = 0; i < n; ++i) {
        double s = b[i];
        int inn = i * n;
        for (k = 0; k < i; ++k)
            s -= L[inn + k] * x[k];
        x[i] = s / L[inn + i];
    }
    for (i = n - 1; i >= 0; --i) {
        double s = x[i];
        for (k = i + 1; k < n; ++k)
            s -= L[k * n + i] * x[k];
        x[i] = s / L[i * n + i];
    }
}

/* linalg.chol_inverse: out = a^-1 (L scratch) */
static int chol_inverse(const double *a, int n, double *out, double *L)
{
    int i, j, k;
    if (!chol(a, n, L))
        return 0;
    for (j = 0; j < n; ++j) {
        int jn = j * n;
        L[jn + j] = 1.0 / L[jn + j];
        for (i = j + 1; i < n; ++i) {
            int inn = i * n;
            double s = 0.0;
            for (k = j; k < i; ++k)
                s -= L[inn + k] * L[k * n + j];
            L[inn + j] = s / L[inn + i];
        }
    }
    for (i = 0; i < n; ++i)
        for (j = i; j < n; ++j) {
            double s = 0.0;
            for (k = j; k < n; ++k) {
                int kn = k * n;
                s += L[kn + i] * L[kn + j];
            }
            out[i * n + j] = s;
            out[j * n + i] = s;
        }
    return 1;
}

/* Demodulator._clear */
static void demod_clear(const struct ct_demod *d, int s, int64_t k)
{
    int p = d->p, i;
    double *G = d->G + (long)s * p * p, *R = d->R + (long)s * 3 * p, *BB = d->BB + 3 * s;
    for (i = 0; i < p * p; ++i)
        G[i] = 0.0;
    for (i = 0; i < 3 * p; ++i)
        R[i] = 0.0;
    BB[0] = BB[1] = BB[2] = 0.0;
    d->count[s] = 0;
    d->flags[s] = 0;
    d->kslot[s] = k;
}

int64_t ct_demod_push(const struct ct_demod *d, int64_t t, double bx, double by, double bz, int64_t sample_flags)
{
    int64_t *st = d->st;
    int64_t t0 = st[CT_DM_T0], hop = d->hop_us, W = d->window_us, next_k = st[CT_DM_NEXT_K];
    int64_t done = -1, rel, k_hi, k_lo, k;
    double dt, *ph = d->phi;
    int p = d->p, i, j, sat;
    if (!st[CT_DM_STARTED] || t <= st[CT_DM_LAST_T] || t < t0)
        return -1;
    st[CT_DM_LAST_T] = t;
    if (t >= t0 + next_k * hop + W)
        done = next_k;
    rel = t - t0;
    k_hi = floordiv(rel, hop);
    k_lo = floordiv(rel - W, hop) + 1;
    if (k_lo < 0)
        k_lo = 0;
    if (k_lo < next_k)
        k_lo = next_k;
    ph[0] = 1.0;
    dt = (double)(t - st[CT_DM_REF]) * 1e-6;
    for (j = 0; j < d->n; ++j) {
        double c = d->freqs[j] * dt, a;
        c -= floor(c);
        a = TWO_PI * c;
        ph[2 + 2 * j] = cos(a);
        ph[3 + 2 * j] = sin(a);
    }
    sat = (sample_flags & CT_SAMPLE_SATURATED) ? 1 : 0;
    for (k = k_lo; k <= k_hi; ++k) {
        int s = (int)(k % d->slots);
        double *G, *R, *BB;
        if (d->kslot[s] != k)
            demod_clear(d, s, k);
        ph[1] = (double)(t - t0 - k * hop) / (double)W - 0.5;
        G = d->G + (long)s * p * p;
        R = d->R + (long)s * 3 * p;
        BB = d->BB + 3 * s;
        for (i = 0; i < p; ++i) {
            double pi = ph[i];
            int ip = i * p, i3 = 3 * i;
            for (j = i; j < p; ++j)
                G[ip + j] += pi * ph[j];
            R[i3] += pi * bx;
            R[i3 + 1] += pi * by;
            R[i3 + 2] += pi * bz;
        }
        BB[0] += bx * bx;
        BB[1] += by * by;
        BB[2] += bz * bz;
        d->count[s] += 1;
        if (sat)
            d->flags[s] |= CT_PULSE_SATURATED;
    }
    return done;
}

int ct_demod_feed(const struct ct_demod *d, const int64_t *rt, const double *rb, const uint8_t *rf, int64_t cap,
                  int64_t count, int64_t last, int64_t left)
{
    int64_t head, base, lo, idx, t_min, *st = d->st;
    if (count <= 0)
        return 0;
    head = last + 1 == cap ? 0 : last + 1;
    base = head - count;
    t_min = st[CT_DM_CURSOR] + 1;
    lo = ct_times_index_at_or_after(rt, cap, head, count, t_min);   /* Ring.index_at_or_after */
    for (idx = lo; idx < count && left > 0; ++idx, --left) {
        int64_t s = base + idx, t, k;           /* Ring.slot */
        if (s < 0)
            s += cap;
        else if (s >= cap)
            s -= cap;
        t = rt[s];
        st[CT_DM_CURSOR] = t;
        k = ct_demod_push(d, t, rb[3 * s], rb[3 * s + 1], rb[3 * s + 2], (int64_t)rf[s]);
        if (k >= 0) {
            st[CT_DM_PENDING] = k;
            return 1;
        }
    }
    return 0;
}

/* Demodulator.signal_chi2, quadrature_chi2, quadrature_ratio of the block just solved into out */
static void demod_statistics(const struct ct_demod *d)
{
    int n = d->n, i, ax, j;
    double c = 0.0, ss = 0.0, qq = 0.0;
    for (i = 0; i < 3 * n; ++i)
        c += d->S[i] * d->S[i] / d->var[i];
    d->out[CT_DMO_SIGNAL_CHI2] = c;
    c = 0.0;
    for (ax = 0; ax < 3; ++ax)
        for (j = 0; j < n; ++j) {
            double q = d->Q[ax * n + j];
            c += q * q / d->qvar[j];
        }
    d->out[CT_DMO_QUAD_CHI2] = c;
    for (i = 0; i < 3 * n; ++i) {
        ss += d->S[i] * d->S[i];
        qq += d->Q[i] * d->Q[i];
    }
    d->out[CT_DMO_QUAD_RATIO] = ss > 0.0 ? sqrt(qq / ss) : 0.0;
}

int ct_demod_finish(const struct ct_demod *d, int64_t k)
{
    int64_t *st = d->st, N, dof;
    int p = d->p, n = d->n, s = (int)(k % d->slots), i, j, ax;
    const double *G, *R, *BB;
    double rss = 0.0, *Gf = d->Gf, *X = d->X, *b = d->b, *x = d->x, *Gi = d->Ginv;
    st[CT_DM_NEXT_K] = k + 1;
    st[CT_DM_BLOCK_K] = k;
    if (d->kslot[s] != k || d->count[s] < p + 2) {
        st[CT_DM_BLOCK_FLAGS] = CT_PULSE_TOO_FEW;
        st[CT_DM_BLOCK_SAMPLES] = d->kslot[s] == k ? d->count[s] : 0;
        return 0;
    }
    st[CT_DM_BLOCK_FLAGS] = d->flags[s];
    st[CT_DM_BLOCK_SAMPLES] = N = d->count[s];
    G = d->G + (long)s * p * p;
    R = d->R + (long)s * 3 * p;
    BB = d->BB + 3 * s;
    for (i = 0; i < p; ++i) {
        int ip = i * p;
        for (j = i; j < p; ++j) {
            double v = G[ip + j];
            Gf[ip + j] = v;
            Gf[j * p + i] = v;
        }
    }
    if (!chol(Gf, p, d->L)) {
        st[CT_DM_BLOCK_FLAGS] |= CT_PULSE_TOO_FEW;
        return 0;
    }
    for (ax = 0; ax < 3; ++ax) {
        double fit = 0.0;
        for (i = 0; i < p; ++i)
            b[i] = R[3 * i + ax];
        chol_solve(d->L, p, b, x);
        for (i = 0; i < p; ++i) {
            X[3 * i + ax] = x[i];
            fit += x[i] * b[i];
        }
        rss += BB[ax] - fit;
    }
    dof = N - p;
    d->out[CT_DMO_RESID] = dof > 0 ? sqrt((0.0 > rss ? 0.0 : rss) / (3.0 * (double)dof * d->sigma2)) : 0.0;
    chol_inverse(Gf, p, Gi, d->L);
    for (ax = 0; ax < 3; ++ax)
        d->dc[ax] = X[ax];                  /* tau = 0 at the block's middle */
    for (j = 0; j < n; ++j) {
        int ia = 2 + 2 * j, iq = 3 + 2 * j;
        double hr = d->h[2 * j], hi = d->h[2 * j + 1];
        double er = hr * d->cph[j] - hi * d->sph[j];
        double ei = hr * d->sph[j] + hi * d->cph[j];
        double dd = er * er + ei * ei, gr = er / dd, gi = -ei / dd;
        double vaa = d->sigma2 * Gi[ia * p + ia], vqq = d->sigma2 * Gi[iq * p + iq];
        double vaq = d->sigma2 * Gi[ia * p + iq];
        double v_in = vaa * gr * gr + vqq * gi * gi + 2.0 * vaq * gr * gi;
        d->qvar[j] = vaa * gi * gi + vqq * gr * gr - 2.0 * vaq * gr * gi;
        for (ax = 0; ax < 3; ++ax) {
            double a = X[3 * ia + ax], q = X[3 * iq + ax];
            d->S[ax * n + j] = a * gr + q * gi;
            d->Q[ax * n + j] = a * gi - q * gr;
            d->var[ax * n + j] = v_in;
        }
    }
    demod_statistics(d);
    return 1;
}

int ct_demod_step(const struct ct_demod *d, const double *phase, const int64_t *rt, const double *rb,
                  const uint8_t *rf, int64_t cap, int64_t count, int64_t last, int64_t left, double signal_gate,
                  double ratio_max, double q_gate)
{
    int64_t k = d->st[CT_DM_PENDING];
    int j;
    if (k < 0) {
        ct_demod_feed(d, rt, rb, rf, cap, count, last, left);
        return 0;
    }
    d->st[CT_DM_PENDING] = -1;
    for (j = 0; j < d->n; ++j) {            /* Demodulator.set_currents */
        d->cph[j] = cos(phase[j]);
        d->sph[j] = sin(phase[j]);
    }
    if (!ct_demod_finish(d, k))
        return CT_DMS_FINISHED;
    if (d->out[CT_DMO_SIGNAL_CHI2] < signal_gate) {
        d->st[CT_DM_BLOCK_FLAGS] |= CT_PULSE_TOO_FEW;
        return CT_DMS_FINISHED | CT_DMS_SOLVED | CT_DMS_NO_SIGNAL;
    }
    if (d->out[CT_DMO_QUAD_RATIO] > ratio_max && d->out[CT_DMO_QUAD_CHI2] > q_gate)
        return CT_DMS_FINISHED | CT_DMS_SOLVED | CT_DMS_DISTORTED;
    return CT_DMS_FINISHED | CT_DMS_SOLVED;
}
