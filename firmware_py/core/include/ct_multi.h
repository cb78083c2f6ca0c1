/*
 * The per-sensor work of many sensors sharing one tick: the compiled form of what the window
 * closer (coiltrack.firmware.measure.windows) does for each of a burst's windows on each sensor
 * channel.  Same names (ct_ prefix), same operations in the same order as the Python reference.
 */
#ifndef CT_MULTI_H
#define CT_MULTI_H

#include <stdint.h>

/* ------------------------------------------------------------ PULSE_WINDOW
 * coiltrack.firmware.transmit.Transmitter.pulse_window with protocol.framing.encode_frame: one
 * PULSE_WINDOW frame (payload "<BBHQQBBB": node, coil, pulse_id, first_us, last_us, n_used, n_base,
 * flags), COBS-encoded and delimited, into out (at least CT_WINDOW_FRAME_MAX bytes); returns its
 * length, or -1 for a field out of its range (struct.pack's refusal).  The schema constants are
 * checked against protocol.schema at start-up (transmit.py). */
enum { CT_WINDOW_ID = 0x31, CT_WINDOW_PAYLOAD = 23, CT_WINDOW_CRC_EXTRA = 0xB7,
       CT_WINDOW_FRAME_RAW = 5 + 23 + 2, CT_WINDOW_FRAME_MAX = 5 + 23 + 2 + 2 + 1 };
int ct_window_frame(uint8_t *out, int seq, int src, int64_t node, int64_t coil, int64_t pulse_id, uint64_t first_us,
                    uint64_t last_us, int64_t n_used, int64_t n_base, int64_t flags);

/* ------------------------------------------------------------ MAG_FLIP_CMD
 * coiltrack.firmware.transmit.Transmitter.mag_flip with protocol.framing.encode_frame: one
 * MAG_FLIP_CMD frame (payload "<BQB": node, at_us, state) as ct_window_frame makes a PULSE_WINDOW;
 * -1 for a field out of its range. */
enum { CT_FLIP_ID = 0x22, CT_FLIP_PAYLOAD = 10, CT_FLIP_CRC_EXTRA = 0x51,
       CT_FLIP_FRAME_RAW = 5 + 10 + 2, CT_FLIP_FRAME_MAX = 5 + 10 + 2 + 2 + 1 };
int ct_flip_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t at_us, int64_t state);

/* ------------------------------------------------------------ solver weights
 * measure.windows.SensorChannel.sigma_from: sig[k] = sqrt(max(var[k], floor)) over the n items of a
 * channel's (3, coils) variances (a NaN variance gives the floor, as the Python's comparison does);
 * sig may be var. */
void ct_sigma_from(int64_t n, const double *var, double *sig, double floor);

/* ------------------------------------------------------------ window column
 * measure.windows.SensorChannel.close_window: PulseExtractor.extract (ct_pulse_extract, include/
 * ct_window.h) of the window [start, end] into the extractor's res (amp 3, var 3) and ires (flags,
 * n_pulse, n_base, n_rec), then, as the Python does after it, the amplitude into the channel's amp
 * and amp_var and into column coil of its burst (S, var: 3 x n row-major; flags, done, pulse_mid),
 * its middle the mean of the first and the last used sample times (floored, as Python's //) or,
 * with none, of start and end; info = n_used, n_base, first, last.  Returns the window flags. */
struct ct_sample_ring;
struct ct_pulse;
struct ct_window_column {
    int64_t n;                      /* coils: the burst's columns */
    double *res;                    /* the extractor's result buffers (ct_pulse_extract's amp, var) */
    int64_t *ires;                  /* ... and its out[4] */
    double *amp, *amp_var;          /* the channel's last window (3 each) */
    double *S, *V;                  /* the channel's burst amplitudes and variances (3 x n) */
    int64_t *flags, *pulse_mid;     /* (n) */
    uint8_t *done;                  /* (n) */
    int64_t *info;                  /* (4): n_used, n_base, first, last */
};
int64_t ct_window_column(const struct ct_window_column *c, const struct ct_pulse *x, const struct ct_sample_ring *r,
                         int64_t start, int64_t end, int64_t coil);

/* ------------------------------------------------------------ a run of windows
 * measure.windows.WindowCloser.close_run: one pulse's window [start, end] closed on channels c0..c1-1
 * in their order, each as SensorChannel.close_window does on the compiled core (its ring's head and
 * count read from hc[i] = SampleRing.hc, then ct_window_column into column coil, then the channel's
 * changes counted: cnt[i][1] += 1, SensorChannel.cnt); each window's flags into flags_out[i].  Returns
 * how many windows were flagged (WindowCloser.flagged). */
int64_t ct_window_run(const struct ct_window_column *const *c, const struct ct_pulse *const *x,
                      struct ct_sample_ring *const *r, const int64_t *const *hc, int64_t *const *cnt, int64_t *flags_out,
                      int64_t c0, int64_t c1, int64_t start, int64_t end, int64_t coil);

/* ------------------------------------------------------------ sample push
 * measure.windows.SensorChannel.push with measure.pulse.SampleRing.push: one magnetometer sample
 * (its field already scaled to tesla, as the Python's msg.x * lsb) into the ring's t, b (cap x 3),
 * flags, its state st = head, count, latest, rejected (SampleRing.hc) and the channel's counters
 * cnt = samples, changes (SensorChannel.cnt).  A time not later than the latest or a field that is
 * not finite is refused and counted (st[3]); the counters count every sample.  Returns 1 (pushed)
 * or 0 (refused). */
int ct_sample_push(int64_t *t, double *b, uint8_t *flags, int64_t cap, int64_t *st, int64_t *cnt, int64_t t_us,
                   double x, double y, double z, int saturated, int flip);

#endif
