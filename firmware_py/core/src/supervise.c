/*
 * The supervisor's per-sample and per-pose work (include/ct_supervise.h): a MAG_SAMPLE's liveness,
 * set/reset state, quiet check, time-stamp check and quiet-field magnitude, as
 * coiltrack.firmware.supervise.supervisor.Supervisor.on_message does them through Health.heard,
 * FlipScheduler.observe, Supervisor._quiet and Health.on_mag (the distortion check: thesis 002 ch. 2,
 * the field magnitude between pulses), and a pose's status bits as Supervisor.pose_status makes them.
 * Every rare case of a sample is left to the Python (return 1 before any
 * write), so the two cores run the same operations on the same values.
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

#define CT_SUP_NONE (-((int64_t)1 << 62))

void ct_sup_bind(struct ct_sup *s, int64_t *si, double *sd, const int64_t *ps, const int64_t *pe)
{
    int64_t n = si[CT_SUP_N];
    int64_t *p = si + CT_SUP_NI + CT_SUP_SLOTS;
    double *q = sd + CT_SUP_ND;
    s->si = si;
    s->sd = sd;
    s->slot = si + CT_SUP_NI;
    s->last_heard = p;
    s->timeout_us = p + n;
    s->lost = p + 2 * n;
    s->last_stamp = p + 3 * n;
    s->suspect_open = p + 4 * n;
    s->suspect_reply_seen = p + 5 * n;
    s->distorted = p + 6 * n;
    s->flip_state = p + 7 * n;
    s->ref_n = p + 8 * n;
    s->dist_state = p + 10 * n;
    s->status_seen = p + 12 * n;
    s->status_faults = s->status_seen + si[CT_SUP_NCOILS];
    s->susp_t0 = s->status_faults + si[CT_SUP_NCOILS];
    s->susp_t1 = s->susp_t0 + CT_SUP_SUSPECT * n;
    s->sent_seq = s->susp_t1 + CT_SUP_SUSPECT * n;
    s->sent_t = s->sent_seq + CT_SUP_HISTORY;
    s->have = s->sent_t + CT_SUP_HISTORY;
    s->last_reply = s->have + n;
    s->hk = s->last_reply + n;
    s->acquired = s->hk + n;
    s->offset = s->acquired + n;
    s->drift = s->offset + n;
    s->rtt = s->drift + n;
    s->rtt_min = s->rtt + n;
    s->replies = s->rtt_min + n;
    s->hist = s->replies + n;
    s->ref_sum = q;
    s->ref_mag = q + 2 * n;
    s->avg_mag = q + 4 * n;
    s->ps = ps;
    s->pe = pe;
}

/* Health.heard of node slot i (not lost): its last time heard, the next check no later than its timeout */
static void ct_sup_heard(const struct ct_sup *s, int64_t i, int64_t now_us)
{
    int64_t due = now_us + s->timeout_us[i];
    s->last_heard[i] = now_us;
    if (due < s->si[CT_SUP_CHECK_US])
        s->si[CT_SUP_CHECK_US] = due;
}

int ct_sup_imu(const struct ct_sup *s, int64_t node, int64_t now_us)
{
    int64_t i;
    if (node < 0 || node >= CT_SUP_SLOTS)
        return 1;
    i = s->slot[node];
    if (i < 0)
        return 0;                                   /* not a node: heard does nothing */
    if (s->lost[i])
        return 1;                                   /* back: the event, the sync kick are the Python's */
    ct_sup_heard(s, i, now_us);
    return 0;
}

/* Supervisor._quiet: no pulse (with its fall and the margin) around t_us */
static int ct_sup_quiet(const struct ct_sup *s, int64_t t_us)
{
    int64_t j, m = s->si[CT_SUP_MARGIN], fall = s->si[CT_SUP_FALL], n = s->si[CT_SUP_NCOILS];
    for (j = 0; j < n; ++j)
        if (s->ps[j] - m <= t_us && t_us <= s->pe[j] + fall + m)
            return 0;
    return 1;
}

int ct_sup_mag(const struct ct_sup *s, int64_t node, int64_t t_us, int64_t x, int64_t y, int64_t z, int64_t flip,
               int64_t now_us)
{
    int64_t *si = s->si;
    const double *sd = s->sd;
    int64_t i, prev, st, learn;
    int quiet, write_avg = 0, ds_new = 0;
    double a = 0.0, m;
    if (node < 0 || node >= CT_SUP_SLOTS)
        return 1;
    i = s->slot[node];
    if (i < 0)
        return 0;                                   /* not a node: heard, observe and on_mag do nothing */
    if (i == si[CT_SUP_DRIVER] || s->lost[i])
        return 1;
    quiet = ct_sup_quiet(s, t_us);
    /* Health.on_mag: the time stamp */
    prev = s->last_stamp[i];
    if (t_us > now_us + si[CT_SUP_FUTURE_TOL])
        return 1;
    if (prev != CT_SUP_NONE) {
        int64_t dt = t_us - prev;
        if (dt > 0) {
            double P = sd[CT_SUP_PERIOD];
            double k = floor((double)dt / P + 0.5);
            if (k < 1.0)
                k = 1.0;
            if (k <= 64.0 && fabs((double)dt - k * P) > (double)si[CT_SUP_INTERVAL_TOL])
                return 1;
        }
    }
    if (s->suspect_open[i] && s->suspect_reply_seen[i] && !(prev != CT_SUP_NONE && t_us - prev <= 0))
        return 1;
    if (flip & 2)
        return 1;                                   /* saturated */
    st = 2 * i + (flip & 1);
    learn = si[CT_SUP_LEARN];
    if (prev == CT_SUP_NONE || t_us - prev > 0) {
        if (quiet && s->ref_n[st] >= learn) {
            /* the exponential average against the reference: a flag that changes is the Python's */
            double bx = (double)x * sd[CT_SUP_LSB], by = (double)y * sd[CT_SUP_LSB], bz = (double)z * sd[CT_SUP_LSB];
            double dev, thr = sd[CT_SUP_THRESHOLD];
            int now_dist;
            m = sqrt(bx * bx + by * by + bz * bz);
            a = s->avg_mag[st] + sd[CT_SUP_ALPHA] * (m - s->avg_mag[st]);
            dev = fabs(a - s->ref_mag[st]);
            ds_new = (int)s->dist_state[st];
            if (dev > thr)
                ds_new = 1;
            else if (dev < 0.5 * thr)
                ds_new = 0;
            now_dist = (st == 2 * i ? ds_new : s->dist_state[2 * i] != 0) ||
                       (st == 2 * i + 1 ? ds_new : s->dist_state[2 * i + 1] != 0);
            if (now_dist != (s->distorted[i] != 0))
                return 1;
            write_avg = 1;
        }
    }
    ct_sup_heard(s, i, now_us);
    /* FlipScheduler.observe (the sensors' slots are the health's) */
    s->flip_state[i] = flip & 1;
    if (prev != CT_SUP_NONE && t_us - prev <= 0)
        return 0;                                   /* a duplicated or delayed frame: skipped */
    s->last_stamp[i] = t_us;
    if (!quiet)
        return 0;
    if (s->ref_n[st] < learn) {
        double bx = (double)x * sd[CT_SUP_LSB], by = (double)y * sd[CT_SUP_LSB], bz = (double)z * sd[CT_SUP_LSB];
        m = sqrt(bx * bx + by * by + bz * bz);
        s->ref_sum[st] += m;
        s->ref_n[st] += 1;
        if (s->ref_n[st] == learn) {
            s->ref_mag[st] = s->ref_sum[st] / (double)s->ref_n[st];
            s->avg_mag[st] = s->ref_mag[st];
        }
        return 0;
    }
    if (write_avg) {
        s->avg_mag[st] = a;
        s->dist_state[st] = ds_new;
    }
    return 0;
}

/* Health.suspect: node slot i's clock suspect anywhere in [t0, t1] */
int ct_sup_suspect(const struct ct_sup *s, int64_t i, int64_t t0, int64_t t1)
{
    const int64_t *a, *b;
    int k;
    if (i < 0)
        return 0;
    if (s->suspect_open[i])
        return 1;
    a = s->susp_t0 + CT_SUP_SUSPECT * i;
    b = s->susp_t1 + CT_SUP_SUSPECT * i;
    for (k = 0; k < CT_SUP_SUSPECT; ++k)
        if (a[k] != CT_SUP_NONE && a[k] <= t1 && b[k] >= t0)
            return 1;
    return 0;
}

int64_t ct_sup_pose_status(const struct ct_sup *s, int64_t node, int64_t window_flags)
{
    const int64_t *si = s->si;
    int64_t bits = 0, veto = 0, t0, t1, i, j, nc = si[CT_SUP_NCOILS];
    int ok = 1, fatal = 0;
    for (j = 0; j < nc; ++j) {                      /* Health.burst_status */
        if (!s->status_seen[j])
            ok = 0;
        if (s->status_faults[j] & si[CT_SUP_FATAL])
            fatal = 1;
    }
    if (!ok || fatal) {
        bits |= si[CT_SUP_BIT_COIL_FAULT];
        veto = 1;
    }
    t0 = s->ps[0];
    t1 = s->pe[0];
    for (j = 1; j < nc; ++j) {
        if (s->ps[j] < t0)
            t0 = s->ps[j];
        if (s->pe[j] > t1)
            t1 = s->pe[j];
    }
    t0 -= si[CT_SUP_BASE_GUARD];
    t1 += si[CT_SUP_FALL_BASE];
    i = (node >= 0 && node < CT_SUP_SLOTS) ? s->slot[node] : -1;
    if (ct_sup_suspect(s, i, t0, t1) || ct_sup_suspect(s, si[CT_SUP_DRIVER], t0, t1)) {
        bits |= si[CT_SUP_BIT_INCONSISTENT];
        veto = 1;
    }
    if (i >= 0 && s->distorted[i])
        bits |= si[CT_SUP_BIT_DISTORTED];
    if (window_flags & si[CT_SUP_SATURATED])
        veto = 1;
    return bits | (veto << 32);
}

static int64_t ct_sup_le(const uint8_t *p, int nbytes)
{
    uint64_t v = 0;
    int k;
    for (k = nbytes - 1; k >= 0; --k)
        v = (v << 8) | p[k];
    return (int64_t)v;
}

/* Python's a // b for b > 0 */
static int64_t ct_sup_floordiv(int64_t a, int64_t b)
{
    int64_t q = a / b;
    return (a % b != 0 && a < 0) ? q - 1 : q;
}

int ct_sup_reply(const struct ct_sup *s, const uint8_t *pay, int64_t now_us)
{
    int64_t *si = s->si;
    int64_t node = pay[0], seq = ct_sup_le(pay + 1, 2);
    int64_t offset = (int32_t)(uint32_t)ct_sup_le(pay + 11, 4), drift = (int32_t)(uint32_t)ct_sup_le(pay + 15, 4);
    int64_t i, k, *hist;
    int acquiring;
    if (si[CT_SUP_BACK])
        return 1;                                   /* the time sync forgets the nodes back first */
    i = s->slot[node];
    if (i < 0)
        return 0;                                   /* not a node: nothing to do */
    if (s->lost[i] || s->suspect_open[i])
        return 1;
    if (s->have[i] && s->acquired[i] >= CT_SUP_ACQUIRE) {   /* TimeSyncMaster.on_reply's step test */
        int64_t dt = now_us - s->last_reply[i], pred, d;
        if (dt > ((int64_t)1 << 31) || dt < -((int64_t)1 << 31))
            return 1;
        pred = s->offset[i] + ct_sup_floordiv(s->drift[i] * dt, 1000000000);
        d = offset - pred;
        if ((d < 0 ? -d : d) > si[CT_SUP_STEP_THRESHOLD])
            return 1;                               /* a clock step */
    }
    ct_sup_heard(s, i, now_us);
    acquiring = s->acquired[i] < CT_SUP_ACQUIRE;
    hist = s->hist + CT_SUP_REPLIES * i;          /* (first_suspect_us matters for a step only) */
    /* TimeSyncMaster.on_reply */
    k = seq % CT_SUP_HISTORY;
    if (s->sent_seq[k] == seq) {
        int64_t rtt = now_us - s->sent_t[k];
        s->rtt[i] = rtt;
        if (s->rtt_min[i] == 0 || rtt < s->rtt_min[i])
            s->rtt_min[i] = rtt;
    }
    s->have[i] = 1;
    s->acquired[i] += 1;
    s->last_reply[i] = now_us;
    hist[s->hk[i]] = now_us;
    s->hk[i] = (s->hk[i] + 1) % CT_SUP_REPLIES;
    s->offset[i] = offset;
    s->drift[i] = drift;
    s->replies[i] += 1;
    /* Health.on_sync_reply: no suspect interval open, no step: nothing; then restart_stamps */
    if (acquiring)
        s->last_stamp[i] = CT_SUP_NONE;
    return 0;
}
