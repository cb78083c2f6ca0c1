/*
 * coiltrack compiled core, AC excitation (Raab et al. 1979, seeds/004_86267342cd7488ce.txt):
 * the synchronous demodulation of coiltrack.firmware.measure.demod.Demodulator (src/demod.c)
 * and one update of Raab's iterative tracker, coiltrack.firmware.pose.raab_update and
 * raab_correction (src/raab.c).  The Python functions are the reference: same names with the
 * ct_ prefix, the same floating-point operations in the same order.
 */
#ifndef CT_AC_H
#define CT_AC_H

#include <stdint.h>

/* ------------------------------------------------------------------ demod
 * The demodulator's integer state, an int64 array st[CT_DM_NST] (Demodulator._st). */
enum { CT_DM_T0 = 0, CT_DM_REF = 1, CT_DM_NEXT_K = 2, CT_DM_LAST_T = 3, CT_DM_STARTED = 4, CT_DM_CURSOR = 5,
       CT_DM_PENDING = 6, CT_DM_BLOCK_K = 7, CT_DM_BLOCK_FLAGS = 8, CT_DM_BLOCK_SAMPLES = 9, CT_DM_NST = 10 };
/* its results besides S, Q, var, qvar, dc: a float64 array out[CT_DMO_N] */
enum { CT_DMO_RESID = 0, CT_DMO_SIGNAL_CHI2 = 1, CT_DMO_QUAD_CHI2 = 2, CT_DMO_QUAD_RATIO = 3, CT_DMO_N = 4 };
/* measure.pulse's flag bits the demodulator sets */
enum { CT_PULSE_TOO_FEW = 1, CT_PULSE_SATURATED = 2, CT_SAMPLE_SATURATED = 1 };

/* one demodulator's caller-owned buffers (n coils, p = 2 + 2 n unknowns, `slots` block accumulators) */
struct ct_demod {
    int n, p, slots;
    int64_t window_us, hop_us;
    double sigma2;
    const double *freqs;            /* n */
    const double *h;                /* 2 n: the magnetometer's response (re, im) per coil */
    const double *cph, *sph;        /* n: cos, sin of the current phases */
    double *G, *R, *BB;             /* slots x p p, slots x 3 p, slots x 3 */
    int64_t *count, *flags, *kslot; /* slots */
    double *phi;                    /* p */
    double *Gf, *L, *Ginv, *x, *b, *X;  /* p p, p p, p p, p, p, 3 p: a block's solve */
    double *S, *Q, *var, *qvar, *dc;    /* 3 n, 3 n, 3 n, n, 3 */
    int64_t *st;                    /* CT_DM_NST */
    double *out;                    /* CT_DMO_N */
};

/* Demodulator.push: one sample; returns the block it completes, or -1 */
int64_t ct_demod_push(const struct ct_demod *d, int64_t t, double bx, double by, double bz, int64_t sample_flags);
/* Demodulator.feed over a measure.pulse.SampleRing (times rt, fields rb (cap x 3), flags rf; `count`
 * entries, the newest in slot `last`): the samples after the cursor, at most `left`, up to the first that
 * completes a block (then st[CT_DM_PENDING] = its index); returns 1 when one did, else 0 */
int ct_demod_feed(const struct ct_demod *d, const int64_t *rt, const double *rb, const uint8_t *rf, int64_t cap,
                  int64_t count, int64_t last, int64_t left);
/* Demodulator.finish: solve block k; 1 when solved (then also signal_chi2, quadrature_chi2 and
 * quadrature_ratio into out) */
int ct_demod_finish(const struct ct_demod *d, int64_t k);

#endif /* CT_AC_H */
