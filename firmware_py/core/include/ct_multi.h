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

/* ------------------------------------------------------------ solver weights
 * measure.windows.SensorChannel.sigma_from: sig[k] = sqrt(max(var[k], floor)) over the n items of a
 * channel's (3, coils) variances (a NaN variance gives the floor, as the Python's comparison does);
 * sig may be var. */
void ct_sigma_from(int64_t n, const double *var, double *sig, double floor);

#endif
