/*
 * A burst's opening for many sensors (actuate.burst.BurstActuation._open): every sensor channel's
 * new burst and every sensor's fusion snapshot scheduled at the burst's reference instant, the
 * operations of the Python reference in its order.  Same names (ct_ prefix).
 */
#ifndef CT_BURST_OPEN_H
#define CT_BURST_OPEN_H

#include <stdint.h>

/* ------------------------------------------------------------ channel
 * measure.windows.SensorChannel.new_burst: done[0..n) = 0, flags[0..n) = 0 (n coils), then the
 * channel's counters cnt = samples, changes (SensorChannel.cnt): changes += 1. */
void ct_new_burst(int64_t n, uint8_t *done, int64_t *flags, int64_t *cnt);

/* ------------------------------------------------------------ sensor
 * track.burst_fusion.SensorInertial.schedule with estimate.fusion_snapshot.Snapshot.schedule: the
 * sensor's reference instant tr[0] = t_ref, its snapshot's sq = t, pending, valid (Snapshot.sq)
 * = t_ref, 1, 0. */
void ct_schedule(int64_t *tr, int64_t *sq, int64_t t_ref);

#endif
