/*
 * The per-tick scans over many sensors (include/ct_ahead.h): which sensor's open burst may be solved
 * ahead (the tests of track.magnetic.MagneticTracker._ahead_scan in their order) and how many
 * channels have a window's samples in (measure.windows.WindowCloser.ready_upto); the TIME_SYNC frame
 * of the supervisor's broadcasts (framed as src/multi.c frames a PULSE_WINDOW).
 */
#include <stdint.h>

#include "coiltrack_core.h"

#define CT_AHEAD_FAR ((int64_t)1 << 61)

static int ct_ahead_far(int64_t v)
{
    return v <= -CT_AHEAD_FAR || v >= CT_AHEAD_FAR;
}

int ct_expect_complete(const int64_t *t, const int64_t *hc, int64_t cap, int64_t end, int64_t extra)
{
    int64_t head = hc[0], count = hc[1], latest = hc[2], slot;
    if (count <= 1)                                  /* ring.peek(1): the sample one push old, held */
        return 0;
    slot = head - 1 - 1;
    if (slot < 0)
        slot += cap;
    if (ct_ahead_far(latest) || ct_ahead_far(t[slot]) || ct_ahead_far(end) || ct_ahead_far(extra))
        return CT_AHEAD_ASK;
    return 2 * latest - t[slot] > end + extra;
}

/* _closed_before: every window of done before coil j is closed */
static int ct_closed_before(const uint8_t *done, int64_t j)
{
    int64_t c;
    for (c = 0; c < j; ++c)
        if (!done[c])
            return 0;
    return 1;
}

int64_t ct_ahead_scan(const struct ct_ahead_scan *s, int64_t burst, int64_t j, int64_t start, int64_t end)
{
    int64_t k, c;
    int seen = 1, e;
    (void)start;
    if (j < 0 || j >= s->n || ct_ahead_far(burst))
        return CT_AHEAD_ASK;
    for (k = 0; k < s->nch; ++k) {
        int64_t *st = s->st + 2 * k;
        const uint8_t *done = s->done[k];
        if (st[0] == burst)
            continue;
        if (s->want[k][s->want_at[k]] != 0) {        /* not wanted: its turn is had */
            st[0] = burst;
            st[1] = 0;
            continue;
        }
        seen = 0;
        c = s->cnt[k][1];
        if (s->idle[k] == c)
            continue;                                /* nothing it reads changed since it was asked */
        if (done[j] || !ct_closed_before(done, j)) {
            s->idle[k] = c;
            continue;
        }
        e = ct_expect_complete(s->t[k], s->hc[k], s->cap[k], end, s->extra[k]);
        if (e == CT_AHEAD_ASK)
            return CT_AHEAD_ASK;
        if (!e) {
            s->idle[k] = c;
            continue;
        }
        st[0] = burst;
        st[1] = 0;
        return k;
    }
    return seen ? CT_AHEAD_SEEN : CT_AHEAD_NONE;
}

int64_t ct_ready_upto(const int64_t *const *hc, const int64_t *extra, int64_t nch, int64_t start, int64_t end,
                      int64_t now, int64_t first, int64_t fall, int64_t baseline, int64_t timeout)
{
    int64_t i;
    (void)start;
    if (first < 0 || ct_ahead_far(end) || ct_ahead_far(now) || ct_ahead_far(fall) || ct_ahead_far(baseline) ||
        ct_ahead_far(timeout) || ct_ahead_far(fall + baseline + timeout))
        return CT_AHEAD_ASK;
    if (now > end + fall + baseline + timeout)
        return nch;
    for (i = first; i < nch; ++i) {
        if (ct_ahead_far(extra[i]))
            return CT_AHEAD_ASK;
        if (!(hc[i][2] > end + extra[i]))          /* PulseExtractor.ready: a sample after the window */
            return i;
    }
    return nch;
}
