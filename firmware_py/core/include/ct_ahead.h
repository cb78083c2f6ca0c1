/*
 * The per-tick scans over many sensors: which sensor's open burst may be solved ahead
 * (track.magnetic.MagneticTracker._ahead_scan, on the state the tracker keeps in arrays) and how
 * many channels have a window's samples in (measure.windows.WindowCloser.ready_upto).  Same names
 * (ct_ prefix), same tests in the same order as the Python reference.
 */
#ifndef CT_AHEAD_H
#define CT_AHEAD_H

#include <stdint.h>

/* the scan's answers besides a channel (track.magnetic AHEAD_NONE, AHEAD_SEEN, AHEAD_ASK) */
enum { CT_AHEAD_NONE = -1, CT_AHEAD_SEEN = -2, CT_AHEAD_ASK = -3 };

/* ------------------------------------------------------------ expect_complete
 * measure.pulse.PulseExtractor.expect_complete on its SampleRing (times t, state hc = head, count,
 * latest, rejected; capacity cap): the ring's sample one push old exists and 2 * latest - its time
 * > end + extra (extra = fall + baseline).  Returns 1 or 0, or CT_AHEAD_ASK where a time lies
 * outside +-2^61 (the reference's integers do not overflow: it answers). */
int ct_expect_complete(const int64_t *t, const int64_t *hc, int64_t cap, int64_t end, int64_t extra);

/* ------------------------------------------------------------ the scan
 * One sensor channel k of nch: done[k] its closed flags (n coils), cnt[k] its counters (samples,
 * changes), t[k], hc[k], cap[k] its ring, extra[k] its extractor's fall + baseline; the sensor is
 * wanted when want[k][want_at[k]] == 0 (MagneticTracker._ahead_wanted); st (nch x 2: burst, done)
 * the turns (_Ahead.burst, .done), idle (nch) the marks (_ahead_unchanged).  Returns the first
 * channel ready (its turn given: st burst = burst, done 0), CT_AHEAD_SEEN when every sensor has had
 * its turn, CT_AHEAD_NONE, or CT_AHEAD_ASK (a time outside +-2^61: what was written is what the
 * reference writes too, and it answers). */
struct ct_ahead_scan {
    int64_t nch, n;
    const uint8_t *const *done;
    const int64_t *const *cnt;
    const int64_t *const *t;
    const int64_t *const *hc;
    const int64_t *cap, *extra;
    const int64_t *const *want;
    const int64_t *want_at;
    int64_t *st, *idle;
};
int64_t ct_ahead_scan(const struct ct_ahead_scan *s, int64_t burst, int64_t j, int64_t start, int64_t end);

/* ------------------------------------------------------------ ready_upto
 * measure.windows.WindowCloser.ready_upto: nch channels whose rings' states are hc[i] (latest at
 * hc[i][2]) and whose extractors read extra[i] = fall + baseline after a window's end
 * (PulseExtractor.ready); fall, baseline, timeout the closer's.  All nch once now > end + fall +
 * baseline + timeout; else, from channel first on, the first i not ready (nch when all are).
 * CT_AHEAD_ASK where a time lies outside +-2^61 (the reference answers). */
int64_t ct_ready_upto(const int64_t *const *hc, const int64_t *extra, int64_t nch, int64_t start, int64_t end,
                      int64_t now, int64_t first, int64_t fall, int64_t baseline, int64_t timeout);

#endif
