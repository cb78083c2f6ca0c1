/*
 * The receive stage's frame decode (firmware_py/core/src/rxdecode.c): the compiled form of
 * coiltrack.protocol.framing.FrameDecoder (feed, _decode, cobs_decode, parse_frame) for the
 * firmware's receive side, and of receive.Receiver._unpack_mag and receive._clipped for the
 * sample messages it unpacks into caller-owned rows.
 */
#ifndef CT_RXDECODE_H
#define CT_RXDECODE_H

#include <stdint.h>

/* the decoder's int64 state: FrameDecoder's counters (same names), then its stream state */
enum {
    CT_RX_FRAMES_OK = 0, CT_RX_CRC_ERRORS, CT_RX_FRAMING_ERRORS, CT_RX_LENGTH_ERRORS, CT_RX_UNKNOWN_IDS,
    CT_RX_OVERFLOWS, CT_RX_REJECTED, CT_RX_SEQ_GAPS, CT_RX_BYTES_IN,
    CT_RX_DROPPING,   /* FrameDecoder._dropping */
    CT_RX_BUFLEN,     /* bytes held in buf (FrameDecoder._buf) */
    CT_RX_POS,        /* where the last call stopped in its data (a full row table stops it) */
    CT_RX_NST
};

/* one decoded message per row of CT_RXR_W int64: its schema id, then per id:
 *   MAG_PACKED: node, t_us (the stamp restored at now_us), x, y, z, flip (bit 0 set/reset,
 *               bit 1 saturated: Receiver._unpack_mag), stamp (the raw 16 bits)
 *   MAG_SAMPLE: node, t_us, x, y, z, flip
 *   IMU_SAMPLE: node, t_us, ax, ay, az, gx, gy, gz, clipped (_clipped)
 *   any other (and a sample whose u64 time does not fit an int64): CT_RXR_OFF the payload's
 *               offset in the payload area, CT_RXR_LEN its length (the caller unpacks it)  */
enum { CT_RXR_ID = 0, CT_RXR_F0 = 1, CT_RXR_CLIP = 9, CT_RXR_STAMP = 7, CT_RXR_OFF = 1, CT_RXR_LEN = 2,
       CT_RXR_KIND = 10, CT_RXR_W = 11 };
/* CT_RXR_KIND: how the row is filled */
enum { CT_RXK_RAW = 0, CT_RXK_MAG_PACKED = 1, CT_RXK_MAG = 2, CT_RXK_IMU = 3 };

/* protocol.schema ids of the messages unpacked here */
enum { CT_ID_MAG_SAMPLE = 0x20, CT_ID_IMU_SAMPLE = 0x21, CT_ID_MAG_PACKED = 0x23 };
#define CT_STAMP_FLIP 32768

struct ct_rx {
    const int64_t *sizes;     /* 256: payload size of each schema id, -1 for an unknown id */
    const int64_t *extras;    /* 256: the id's CRC extra byte */
    int64_t *st;              /* CT_RX_NST */
    int64_t *last_seq;        /* 256: the last sequence number of each source, -1 before its first */
    int64_t *rows;            /* cap x CT_RXR_W */
    uint8_t *pay;             /* cap x max_payload: the payloads of CT_RXK_RAW rows */
    uint8_t *buf;             /* max_encoded: the frame being received */
    uint8_t *raw;             /* max_encoded: scratch, the frame after COBS */
    int cap, max_encoded, max_payload;
};

/* The receive stage's routing of the magnetometer rows (receive.Receiver._step_rows on the compiled
 * core, its MAG_PACKED and MAG_SAMPLE branch: Supervisor.on_message through ct_sup_mag, the packed
 * count, SensorChannel.push through ct_sample_push), for the nodes whose channel is bound here.  A
 * row it does not route whole (another kind, a node without a bound channel, a ring state out of
 * range, a sample ct_sup_mag hands back) goes to the caller, in order, and nothing of it is done;
 * but an IMU_SAMPLE row goes to the caller with the supervisor's part done where ct_sup_imu did it
 * (CT_RXS_SEEN 1). */
struct ct_sup;
enum { CT_RXS_ROWS = 0, CT_RXS_NEXT, CT_RXS_PACKED, CT_RXS_SEEN, CT_RXS_N };   /* the route's int64 state */
struct ct_rx_chan {           /* a sensor channel's ring (SampleRing t, b, flags, hc) and counters */
    int64_t *t;
    double *b;
    uint8_t *flags;
    int64_t cap;
    int64_t *st, *cnt;
};
struct ct_rx_route {
    const struct ct_rx *d;        /* the frame decode whose rows are routed */
    const struct ct_sup *sup;     /* the supervisor's state (NULL: every row goes to the caller) */
    const int64_t *chan;          /* 256: node -> index into ch, -1: the caller routes the node */
    const struct ct_rx_chan *ch;
    int64_t *st;                  /* CT_RXS_N: rows in the table, the next row to route, packed count */
    double lsb;                   /* MAG_LSB_T */
    int64_t limit;                /* frames a tick routes at most (Receiver.frames_per_tick; 0: no limit) */
};
/* ct_rx_step's modes: new data (its frames counted against the limit first), the route resumed after
 * the row handed back, new data already cut to the limit (Receiver._take) */
enum { CT_RX_NEW = 0, CT_RX_RESUME = 1, CT_RX_TAKEN = 2 };
#define CT_RX_OVER_LIMIT (-2)

uint16_t ct_crc16(uint16_t crc, const uint8_t *p, int n);
int ct_rx_cobs_decode(const uint8_t *in, int n, uint8_t *out);
int ct_rx_feed(const struct ct_rx *d, const uint8_t *data, int64_t n, int64_t pos, int64_t now_us);
int64_t ct_rx_route(const struct ct_rx_route *r, int64_t i, int64_t n, int64_t now_us);
int64_t ct_rx_step(const struct ct_rx_route *r, const uint8_t *data, int64_t n, int mode, int64_t now_us);

#endif
