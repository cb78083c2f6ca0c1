/*
 * The measure stage of AC excitation: coiltrack.firmware.measure.ac_blocks.ACBlockMeasurement's
 * tick after its plan check (_tick): each channel's demodulator steps (ct_demod_step, src/demod.c:
 * the feed, or the block it completed solved at the drive's phases of now, Raab et al. 1979,
 * seeds/004_86267342cd7488ce.txt, sec. II), the solved block's bookkeeping (_feed), and the block
 * handed to the tracker as every channel's burst once every channel has solved it (_assemble).
 * The same operations in the same order as the Python.
 */
#include "coiltrack_core.h"

#include <string.h>

/* Python's floor division a // 2 */
static int64_t half_floor(int64_t a)
{
    int64_t q = a / 2;
    if ((a % 2) != 0 && a < 0)
        q -= 1;
    return q;
}

/* ACBlockMeasurement._feed for channel i; 1 when it solved a block with signal (its DC term to the earth ring) */
static int acb_feed(const struct ct_ac_blocks *a, int i, const int64_t *rs)
{
    const struct ct_ac_channel *c = &a->ch[i];
    const struct ct_demod *d = c->dm;
    int r = ct_demod_step(d, a->phase, c->rt, c->rb, c->rf, c->cap, rs[2 * i], rs[2 * i + 1],
                          a->st[CT_ACB_MAX_SAMPLES], a->fs[CT_ACBF_SIGNAL_GATE], a->fs[CT_ACBF_RATIO_MAX],
                          a->fs[CT_ACBF_Q_GATE]);
    if (!r)
        return 0;
    a->solved_k[i] = d->st[CT_DM_BLOCK_K];
    if (r & CT_DMS_NO_SIGNAL) {
        a->st[CT_ACB_NO_SIGNAL] += 1;
        return 0;
    }
    if (r & CT_DMS_SOLVED) {
        int dist = (r & CT_DMS_DISTORTED) != 0;
        a->quad_ratio[i] = d->out[CT_DMO_QUAD_RATIO];
        a->distorted[i] = dist;
        if (dist)
            a->st[CT_ACB_DISTORTED] += 1;
        return 1;
    }
    return 0;
}

/* SensorChannel.load_block without its change count (the caller's): S, var, every window's flags, done,
 * the middle */
static void acb_load(const struct ct_ac_channel *c, int n, int64_t flags, int64_t mid)
{
    const struct ct_demod *d = c->dm;
    int j;
    memcpy(c->S, d->S, (size_t)(3 * n) * sizeof(double));
    memcpy(c->var, d->var, (size_t)(3 * n) * sizeof(double));
    for (j = 0; j < n; ++j) {
        c->flags[j] = flags;
        c->done[j] = 1;
        c->pulse_mid[j] = mid;
    }
}

/* ACBlockMeasurement._assemble: 1 when block k went to the channels */
static int acb_assemble(const struct ct_ac_blocks *a)
{
    int64_t *st = a->st;
    double *fs = a->fs;
    int64_t k = a->solved_k[0], start, end, mid;
    const struct ct_demod *d0 = a->ch[0].dm;
    int i, j, n = a->n, bad = 0;
    if (k < 0 || k == st[CT_ACB_BLOCK_K])
        return 0;
    for (i = 1; i < a->nch; ++i)
        if (a->solved_k[i] != k)
            return 0;
    if (st[CT_ACB_COMPLETE]) {
        st[CT_ACB_SKIPPED] += 1;
        st[CT_ACB_BLOCK_K] = k;
        return 0;
    }
    st[CT_ACB_BLOCK_K] = k;
    start = d0->st[CT_DM_T0] + k * d0->hop_us;
    end = start + d0->window_us;
    mid = half_floor(start + end);
    for (j = 0; j < n; ++j) {               /* PulseSchedule.ac_block */
        a->sched_start[j] = start;
        a->sched_end[j] = j < n - 1 ? end + d0->window_us : end;
        a->sched_measured[j] = a->amplitude[j];
    }
    for (i = 0; i < a->nch; ++i) {
        const struct ct_demod *d = a->ch[i].dm;
        int64_t fl = d->st[CT_DM_BLOCK_FLAGS];
        acb_load(&a->ch[i], n, fl, mid);
        if (fl)
            bad = 1;
        fs[CT_ACBF_QUAD_SUM] += a->quad_ratio[i];
        if (a->quad_ratio[i] > fs[CT_ACBF_QUAD_MAX])
            fs[CT_ACBF_QUAD_MAX] = a->quad_ratio[i];
        fs[CT_ACBF_RESID_SUM] += d->out[CT_DMO_RESID];
    }
    st[CT_ACB_BLOCKS] += 1;
    if (bad)
        st[CT_ACB_BAD] += 1;
    st[CT_ACB_T_REF] = mid;
    st[CT_ACB_COMPLETE] = 1;
    return 1;
}

int64_t ct_ac_blocks_step(const struct ct_ac_blocks *a, const int64_t *rs)
{
    int64_t r = 0;
    int i;
    for (i = 0; i < a->nch; ++i)
        if (acb_feed(a, i, rs))
            r |= (int64_t)2 << i;
    if (acb_assemble(a))
        r |= 1;
    return r;
}
