/*
 * The supervisor's per-sample and per-pose work (coiltrack.firmware.supervise): what
 * Supervisor.on_message does for a MAG_SAMPLE (Health.heard, FlipScheduler.observe, Supervisor._quiet,
 * Health.on_mag), in one call, for the sixteen-sensor receive stage; and Supervisor.pose_status
 * (Health.burst_status, Health.suspect, Health.is_distorted) for each sensor's pose.  Same names (ct_ prefix), same operations in the same
 * order as the Python reference; the rare cases stay the reference's (see ct_sup_mag).
 */
#ifndef CT_SUPERVISE_H
#define CT_SUPERVISE_H

#include <stdint.h>

/* The state lives in two caller-owned arrays (supervise/health.py binds them; the Python's lists
 * become views of them), laid out in this order:
 *   si (int64): CT_SUP_NI header items, the node -> slot table (256 items, -1: not a node), then
 *     n items each of last_heard, timeout_us, lost, last_stamp, suspect_open, suspect_reply_seen,
 *     distorted, flip_state (FlipScheduler.state: the sensors' slots), then 2n each of ref_n and
 *     dist_state, then n_coils each of status_seen and status_faults, then 4n each of susp_t0 and
 *     susp_t1 (row i: node slot i's suspect intervals), then the time sync's (TimeSyncMaster)
 *     CT_SUP_HISTORY each of _sent_seq and _sent_t, n each of have, last_reply_us, _hk, acquired,
 *     offset_us, drift_ppb, rtt_us, rtt_min_us, replies and CT_SUP_REPLIES n of _hist (row i: slot
 *     i's; the time sync's slots are the health's);
 *   sd (float64): CT_SUP_ND header items, then 2n each of ref_sum, ref_mag, avg_mag.
 * n = the nodes (the sensors, then the coil driver). */
enum { CT_SUP_CHECK_US, CT_SUP_N, CT_SUP_DRIVER, CT_SUP_FUTURE_TOL, CT_SUP_INTERVAL_TOL, CT_SUP_LEARN,
       CT_SUP_MARGIN, CT_SUP_FALL, CT_SUP_NCOILS,
       /* pose_status: the span's widening (baseline + guard before, fall + baseline after), the fatal
        * coil faults, the saturated window flag and the POSE_* bits it sets */
       CT_SUP_BASE_GUARD, CT_SUP_FALL_BASE, CT_SUP_FATAL, CT_SUP_SATURATED, CT_SUP_BIT_COIL_FAULT,
       CT_SUP_BIT_INCONSISTENT, CT_SUP_BIT_DISTORTED,
       /* a sync reply: nodes came back that the time sync has not forgotten yet (Health._back), the
        * time sync's step threshold */
       CT_SUP_BACK, CT_SUP_STEP_THRESHOLD, CT_SUP_NI };
enum { CT_SUP_HISTORY = 16, CT_SUP_REPLIES = 5, CT_SUP_ACQUIRE = 4 };  /* timesync._HISTORY, _REPLIES, _ACQUIRE */
enum { CT_SUP_SUSPECT = 4 };             /* suspect intervals per node (health._SUSPECT) */
enum { CT_SUP_PERIOD, CT_SUP_ALPHA, CT_SUP_THRESHOLD, CT_SUP_LSB, CT_SUP_ND = 8 };
enum { CT_SUP_SLOTS = 256 };
/* the items of si and sd for n nodes and nc coils */
#define CT_SUP_SI_LEN(n, nc) (CT_SUP_NI + CT_SUP_SLOTS + 12 * (n) + 2 * (nc) + 2 * CT_SUP_SUSPECT * (n) + \
                              2 * CT_SUP_HISTORY + 9 * (n) + CT_SUP_REPLIES * (n))
#define CT_SUP_SD_LEN(n) (CT_SUP_ND + 6 * (n))

struct ct_sup {
    int64_t *si;
    double *sd;
    const int64_t *slot;                    /* 256 */
    int64_t *last_heard, *timeout_us, *lost, *last_stamp, *suspect_open, *suspect_reply_seen, *distorted;
    int64_t *flip_state, *ref_n, *dist_state;
    int64_t *status_seen, *status_faults, *susp_t0, *susp_t1;
    int64_t *sent_seq, *sent_t, *have, *last_reply, *hk, *acquired, *offset, *drift, *rtt, *rtt_min, *replies, *hist;
    double *ref_sum, *ref_mag, *avg_mag;
    const int64_t *ps, *pe;                 /* the pulse schedule's start and end (n_coils each) */
};

/* the pointers of s from si, sd (n nodes: si[CT_SUP_N]) and the schedule's arrays */
void ct_sup_bind(struct ct_sup *s, int64_t *si, double *sd, const int64_t *ps, const int64_t *pe);

/* Supervisor.on_message for a MAG_SAMPLE (node, t_us, x, y, z counts of MAG_LSB_T, flip bits) received
 * at now_us.  Returns 0 when it did all of it, 1 when the sample is a rare case the Python reference
 * does (the coil driver's sample, a node that was lost, a stamp off the grid or from the future, a
 * suspect interval to close, a saturated sample, a distortion flag that changes): then nothing was
 * changed. */
int ct_sup_mag(const struct ct_sup *s, int64_t node, int64_t t_us, int64_t x, int64_t y, int64_t z, int64_t flip,
               int64_t now_us);

/* Supervisor.on_message for an IMU_SAMPLE of node received at now_us (Health.heard).  Returns 0 when it
 * did all of it, 1 when the node was lost (its return is the Python reference's): then nothing was
 * changed. */
int ct_sup_imu(const struct ct_sup *s, int64_t node, int64_t now_us);

/* Supervisor.on_message for a TIME_SYNC_REPLY whose payload (protocol.schema "<BHQii": node, sync_seq,
 * node_time_us, offset_us, drift_ppb) is at pay (Health.heard, TimeSyncMaster.acquiring,
 * first_suspect_us, on_reply, Health.on_sync_reply, restart_stamps).  Returns 0 when it did all of
 * it, 1 when the reply is a rare case the Python reference does (a node back or lost, a reply that
 * shows a clock step, a suspect interval open, an interval too long for the drift's product):
 * then nothing was changed. */
int ct_sup_reply(const struct ct_sup *s, const uint8_t *pay, int64_t now_us);

/* Health.suspect: node slot i (-1: none) has a clock suspect anywhere in [t0, t1] */
int ct_sup_suspect(const struct ct_sup *s, int64_t i, int64_t t0, int64_t t1);

/* Supervisor.pose_status(node, window_flags): the extra POSE_* bits of node's pose from the current
 * burst, and (bit 32) whether the firmware vetoes it. */
int64_t ct_sup_pose_status(const struct ct_sup *s, int64_t node, int64_t window_flags);

#endif
