/*
 * The receive stage's frame decode: the compiled form of coiltrack.protocol.framing.FrameDecoder
 * (feed, _decode, cobs_decode, parse_frame) for the firmware's receive side.  The Python decoder
 * is the reference: the same frames decoded, the same bad frames counted in the same counters
 * (protocol/framing.py's order of checks), the same sequence gaps.  The messages the tick sees
 * at the sample rates (MAG_PACKED, MAG_SAMPLE, IMU_SAMPLE) are unpacked here into caller-owned
 * int64 rows, MAG_PACKED restored as Receiver._unpack_mag restores it and IMU_SAMPLE checked
 * for a clipped axis (_clipped); every other message's payload is copied out for the caller's
 * protocol.codec to unpack.
 *
 * Frame before COBS (little endian, protocol/framing.py): len, flags, seq, src, msg_id, the
 * payload, CRC-16/CCITT-FALSE over header and payload then the id's CRC extra byte, and with
 * flags bit 0 a 13-byte signature; the whole COBS-encoded and ended by one 0x00.
 */
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

enum { RX_HEADER = 5, RX_CRC = 2, RX_SIG = 13, RX_FLAG_SIGNED = 1 };

/* CRC-16/CCITT-FALSE (poly 0x1021, not reflected) continued from crc over n bytes (crcmod's
 * mkCrcFun(0x11021, initCrc=0xFFFF, rev=False)) */
/* CRC-16/CCITT (polynomial 0x1021, MSB first) of each byte value: entry b is the register b << 8
 * shifted through eight steps, so a byte is one look-up instead of eight data-dependent branches (the
 * bit-by-bit loop took ~20 cycles a bit here, its branch mispredicted half the time) */
static const uint16_t ct_crc16_table[256] = {
    0x0000, 0x1021, 0x2042, 0x3063, 0x4084, 0x50A5, 0x60C6, 0x70E7,
    0x8108, 0x9129, 0xA14A, 0xB16B, 0xC18C, 0xD1AD, 0xE1CE, 0xF1EF,
    0x1231, 0x0210, 0x3273, 0x2252, 0x52B5, 0x4294, 0x72F7, 0x62D6,
    0x9339, 0x8318, 0xB37B, 0xA35A, 0xD3BD, 0xC39C, 0xF3FF, 0xE3DE,
    0x2462, 0x3443, 0x0420, 0x1401, 0x64E6, 0x74C7, 0x44A4, 0x5485,
    0xA56A, 0xB54B, 0x8528, 0x9509, 0xE5EE, 0xF5CF, 0xC5AC, 0xD58D,
    0x3653, 0x2672, 0x1611, 0x0630, 0x76D7, 0x66F6, 0x5695, 0x46B4,
    0xB75B, 0xA77A, 0x9719, 0x8738, 0xF7DF, 0xE7FE, 0xD79D, 0xC7BC,
    0x48C4, 0x58E5, 0x6886, 0x78A7, 0x0840, 0x1861, 0x2802, 0x3823,
    0xC9CC, 0xD9ED, 0xE98E, 0xF9AF, 0x8948, 0x9969, 0xA90A, 0xB92B,
    0x5AF5, 0x4AD4, 0x7AB7, 0x6A96, 0x1A71, 0x0A50, 0x3A33, 0x2A12,
    0xDBFD, 0xCBDC, 0xFBBF, 0xEB9E, 0x9B79, 0x8B58, 0xBB3B, 0xAB1A,
    0x6CA6, 0x7C87, 0x4CE4, 0x5CC5, 0x2C22, 0x3C03, 0x0C60, 0x1C41,
    0xEDAE, 0xFD8F, 0xCDEC, 0xDDCD, 0xAD2A, 0xBD0B, 0x8D68, 0x9D49,
    0x7E97, 0x6EB6, 0x5ED5, 0x4EF4, 0x3E13, 0x2E32, 0x1E51, 0x0E70,
    0xFF9F, 0xEFBE, 0xDFDD, 0xCFFC, 0xBF1B, 0xAF3A, 0x9F59, 0x8F78,
    0x9188, 0x81A9, 0xB1CA, 0xA1EB, 0xD10C, 0xC12D, 0xF14E, 0xE16F,
    0x1080, 0x00A1, 0x30C2, 0x20E3, 0x5004, 0x4025, 0x7046, 0x6067,
    0x83B9, 0x9398, 0xA3FB, 0xB3DA, 0xC33D, 0xD31C, 0xE37F, 0xF35E,
    0x02B1, 0x1290, 0x22F3, 0x32D2, 0x4235, 0x5214, 0x6277, 0x7256,
    0xB5EA, 0xA5CB, 0x95A8, 0x8589, 0xF56E, 0xE54F, 0xD52C, 0xC50D,
    0x34E2, 0x24C3, 0x14A0, 0x0481, 0x7466, 0x6447, 0x5424, 0x4405,
    0xA7DB, 0xB7FA, 0x8799, 0x97B8, 0xE75F, 0xF77E, 0xC71D, 0xD73C,
    0x26D3, 0x36F2, 0x0691, 0x16B0, 0x6657, 0x7676, 0x4615, 0x5634,
    0xD94C, 0xC96D, 0xF90E, 0xE92F, 0x99C8, 0x89E9, 0xB98A, 0xA9AB,
    0x5844, 0x4865, 0x7806, 0x6827, 0x18C0, 0x08E1, 0x3882, 0x28A3,
    0xCB7D, 0xDB5C, 0xEB3F, 0xFB1E, 0x8BF9, 0x9BD8, 0xABBB, 0xBB9A,
    0x4A75, 0x5A54, 0x6A37, 0x7A16, 0x0AF1, 0x1AD0, 0x2AB3, 0x3A92,
    0xFD2E, 0xED0F, 0xDD6C, 0xCD4D, 0xBDAA, 0xAD8B, 0x9DE8, 0x8DC9,
    0x7C26, 0x6C07, 0x5C64, 0x4C45, 0x3CA2, 0x2C83, 0x1CE0, 0x0CC1,
    0xEF1F, 0xFF3E, 0xCF5D, 0xDF7C, 0xAF9B, 0xBFBA, 0x8FD9, 0x9FF8,
    0x6E17, 0x7E36, 0x4E55, 0x5E74, 0x2E93, 0x3EB2, 0x0ED1, 0x1EF0,
};

uint16_t ct_crc16(uint16_t crc, const uint8_t *p, int n)
{
    int i;
    for (i = 0; i < n; ++i)
        crc = (uint16_t)(((unsigned)crc << 8) ^ ct_crc16_table[((crc >> 8) ^ p[i]) & 0xFFu]);
    return crc;
}

/* cobs_decode of n bytes (no 0x00 among them) into out (room for n): the decoded length, or -1
 * where a block runs past the end (FramingError) */
int ct_rx_cobs_decode(const uint8_t *in, int n, uint8_t *out)
{
    int i = 0, m = 0;
    while (i < n) {
        int code = in[i], end = i + code;
        if (code == 0 || end > n)
            return -1;
        memcpy(out + m, in + i + 1, (size_t)(code - 1));
        m += code - 1;
        i = end;
        if (code < 0xFF && i < n)
            out[m++] = 0;
    }
    return m;
}

static int64_t u16(const uint8_t *p)
{
    return (int64_t)p[0] | ((int64_t)p[1] << 8);
}

static int64_t i16(const uint8_t *p)
{
    int64_t v = u16(p);
    return v >= 32768 ? v - 65536 : v;
}

/* '<Q' as an int64, or -1 where it does not fit one (the row then goes to the caller raw) */
static int64_t u64(const uint8_t *p)
{
    uint64_t v = 0;
    int k;
    for (k = 7; k >= 0; --k)
        v = (v << 8) | p[k];
    return v > (uint64_t)INT64_MAX ? -1 : (int64_t)v;
}

/* the row of one message (id, payload p of its schema size) */
static void ct_rx_row(const struct ct_rx *d, int64_t *r, int id, const uint8_t *p, int len, int64_t now_us)
{
    int64_t t, k;
    r[CT_RXR_ID] = id;
    if (id == CT_ID_MAG_PACKED) {
        int64_t s = u16(p + 7);
        r[CT_RXR_F0] = p[0];
        r[CT_RXR_F0 + 1] = ct_unwrap_stamp(s & CT_STAMP_MASK, now_us);
        r[CT_RXR_F0 + 2] = i16(p + 1);
        r[CT_RXR_F0 + 3] = i16(p + 3);
        r[CT_RXR_F0 + 4] = i16(p + 5);
        r[CT_RXR_F0 + 5] = ((s & CT_STAMP_FLIP) ? 1 : 0) | ((s & CT_STAMP_SATURATED) ? 2 : 0);
        r[CT_RXR_STAMP] = s;
        r[CT_RXR_KIND] = CT_RXK_MAG_PACKED;
        return;
    }
    t = (id == CT_ID_MAG_SAMPLE || id == CT_ID_IMU_SAMPLE) ? u64(p + 1) : -1;
    if (t >= 0 && id == CT_ID_MAG_SAMPLE) {
        r[CT_RXR_F0] = p[0];
        r[CT_RXR_F0 + 1] = t;
        for (k = 0; k < 3; ++k)
            r[CT_RXR_F0 + 2 + k] = i16(p + 9 + 2 * k);
        r[CT_RXR_F0 + 5] = p[15];
        r[CT_RXR_KIND] = CT_RXK_MAG;
        return;
    }
    if (t >= 0 && id == CT_ID_IMU_SAMPLE) {
        r[CT_RXR_F0] = p[0];
        r[CT_RXR_F0 + 1] = t;
        for (k = 0; k < 6; ++k)
            r[CT_RXR_F0 + 2 + k] = i16(p + 9 + 2 * k);
        r[CT_RXR_CLIP] = ct_imu_clipped(r + CT_RXR_F0 + 2);
        r[CT_RXR_KIND] = CT_RXK_IMU;
        return;
    }
    r[CT_RXR_OFF] = (r - d->rows) / CT_RXR_W * d->max_payload;
    r[CT_RXR_LEN] = len;
    memcpy(d->pay + r[CT_RXR_OFF], p, (size_t)len);
    r[CT_RXR_KIND] = CT_RXK_RAW;
}

/* FrameDecoder._decode of one COBS-encoded frame (enc, n bytes): 1 and its row where it
 * decodes, else 0 with the bad frame counted as the Python counts it */
static int ct_rx_frame(const struct ct_rx *d, const uint8_t *enc, int n, int64_t *row, int64_t now_us)
{
    int64_t *st = d->st;
    uint8_t *raw = d->raw;
    int m = ct_rx_cobs_decode(enc, n, raw);
    int length, flags, id, sig, end;
    int64_t size, last;
    uint16_t crc;
    uint8_t extra;
    if (m < 0 || m < RX_HEADER + RX_CRC) {              /* FramingError */
        st[CT_RX_FRAMING_ERRORS] += 1;
        return 0;
    }
    length = raw[0];
    flags = raw[1];
    id = raw[4];
    size = d->sizes[id];
    if (size < 0) {                                      /* UnknownMessageError */
        st[CT_RX_UNKNOWN_IDS] += 1;
        return 0;
    }
    if (flags & ~RX_FLAG_SIGNED) {                       /* FramingError: unknown flags */
        st[CT_RX_FRAMING_ERRORS] += 1;
        return 0;
    }
    sig = (flags & RX_FLAG_SIGNED) ? RX_SIG : 0;
    if (m != RX_HEADER + length + RX_CRC + sig || length != size) {     /* LengthError */
        st[CT_RX_LENGTH_ERRORS] += 1;
        return 0;
    }
    end = RX_HEADER + length;
    extra = (uint8_t)d->extras[id];
    crc = ct_crc16(ct_crc16(0xFFFF, raw, end), &extra, 1);
    if (crc != (uint16_t)(raw[end] | (raw[end + 1] << 8))) {            /* CrcError */
        st[CT_RX_CRC_ERRORS] += 1;
        return 0;
    }
    last = d->last_seq[raw[3]];
    if (last >= 0 && raw[2] != ((last + 1) & 0xFF))
        st[CT_RX_SEQ_GAPS] += 1;
    d->last_seq[raw[3]] = raw[2];
    st[CT_RX_FRAMES_OK] += 1;
    ct_rx_row(d, row, id, raw + RX_HEADER, length, now_us);
    return 1;
}

/* FrameDecoder.feed of data[pos:n] received at now_us: the number of rows written (at most
 * d->cap; st[CT_RX_POS] says where it stopped: n when all was taken, else the byte after the
 * last frame decoded, where the next call resumes).  bytes_in counts data once, at pos 0. */
int ct_rx_feed(const struct ct_rx *d, const uint8_t *data, int64_t n, int64_t pos, int64_t now_us)
{
    int64_t *st = d->st;
    int rows = 0;
    int64_t start = pos;
    if (pos == 0)
        st[CT_RX_BYTES_IN] += n;
    while (start < n) {
        const uint8_t *z = memchr(data + start, 0, (size_t)(n - start));
        int64_t len;
        if (z == NULL) {
            if (!st[CT_RX_DROPPING]) {
                len = st[CT_RX_BUFLEN] + (n - start);
                if (len > d->max_encoded) {
                    st[CT_RX_OVERFLOWS] += 1;
                    st[CT_RX_BUFLEN] = 0;
                    st[CT_RX_DROPPING] = 1;
                } else {
                    memcpy(d->buf + st[CT_RX_BUFLEN], data + start, (size_t)(n - start));
                    st[CT_RX_BUFLEN] = len;
                }
            }
            start = n;
            break;
        }
        if (st[CT_RX_DROPPING]) {
            st[CT_RX_DROPPING] = 0;
        } else {
            int64_t k = (z - data) - start;
            len = st[CT_RX_BUFLEN] + k;
            if (len > d->max_encoded) {
                st[CT_RX_OVERFLOWS] += 1;
            } else if (len > 0) {
                memcpy(d->buf + st[CT_RX_BUFLEN], data + start, (size_t)k);
                rows += ct_rx_frame(d, d->buf, (int)len, d->rows + (int64_t)rows * CT_RXR_W, now_us);
            }
        }
        st[CT_RX_BUFLEN] = 0;
        start = (z - data) + 1;
        if (rows == d->cap)
            break;
    }
    st[CT_RX_POS] = start;
    return rows;
}

/* Receiver._step_rows's MAG_PACKED / MAG_SAMPLE branch for rows i..n-1 of the table, in order, as far
 * as it goes: the first row it does not route whole (include/ct_rxdecode.h), or n.  Per row the
 * Python's steps: the supervisor's (ct_sup_mag; a rare case handed back leaves everything as it was),
 * the packed count, then the channel's push of the counts times lsb (saturated: flip bit 1, set/reset:
 * bit 0).  An IMU_SAMPLE row stops it too, its first step (the supervisor's, ct_sup_imu) done where
 * it can be: CT_RXS_SEEN says whether. */
int64_t ct_rx_route(const struct ct_rx_route *r, int64_t i, int64_t n, int64_t now_us)
{
    for (; i < n; ++i) {
        const int64_t *q = r->d->rows + i * CT_RXR_W;
        int64_t kind = q[CT_RXR_KIND], node = q[CT_RXR_F0], flip = q[CT_RXR_F0 + 5], c;
        const struct ct_rx_chan *ch;
        if (kind == CT_RXK_IMU) {
            r->st[CT_RXS_SEEN] = r->sup != NULL && ct_sup_imu(r->sup, node, now_us) == 0;
            return i;
        }
        if ((kind != CT_RXK_MAG_PACKED && kind != CT_RXK_MAG) || r->sup == NULL || node < 0 || node > 255)
            return i;
        c = r->chan[node];
        if (c < 0)
            return i;
        ch = &r->ch[c];
        if (ch->st[0] < 0 || ch->st[0] >= ch->cap || ch->st[1] < 0 || ch->st[1] > ch->cap)
            return i;
        if (ct_sup_mag(r->sup, node, q[CT_RXR_F0 + 1], q[CT_RXR_F0 + 2], q[CT_RXR_F0 + 3], q[CT_RXR_F0 + 4], flip,
                       now_us))
            return i;
        if (kind == CT_RXK_MAG_PACKED)
            r->st[CT_RXS_PACKED] += 1;
        ct_sample_push(ch->t, ch->b, ch->flags, ch->cap, ch->st, ch->cnt, q[CT_RXR_F0 + 1],
                       (double)q[CT_RXR_F0 + 2] * r->lsb, (double)q[CT_RXR_F0 + 3] * r->lsb,
                       (double)q[CT_RXR_F0 + 4] * r->lsb, (flip & 2) != 0, (int)(flip & 1));
    }
    return n;
}

/* Receiver._step_rows's test of new data against the frame limit: whether it holds limit frames or
 * more (its 0x00 delimiters, data.count(b"\x00") >= frames_per_tick) */
static int ct_rx_over_limit(const struct ct_rx_route *r, const uint8_t *data, int64_t n)
{
    int64_t frames = 0, at = 0;
    const uint8_t *z;
    if (r->limit <= 0)
        return 0;
    while (at < n && (z = memchr(data + at, 0, (size_t)(n - at))) != NULL) {
        if (++frames >= r->limit)
            return 1;
        at = (z - data) + 1;
    }
    return 0;
}

/* Receiver._step_rows's loop over one tick's data (n bytes): decoded a table of rows at a time
 * (ct_rx_feed: a full table resumes at the decoder's CT_RX_POS) and routed (ct_rx_route).  Returns
 * the index of the next row the caller must route, or -1 when every row of data is routed; the
 * caller routes that row and calls again in mode CT_RX_RESUME (the same data), which goes on after
 * it.  New data (CT_RX_NEW) of the frame limit or more is not decoded: CT_RX_OVER_LIMIT, the caller
 * cuts it to the limit (Receiver._take) and calls with what it took (CT_RX_TAKEN). */
int64_t ct_rx_step(const struct ct_rx_route *r, const uint8_t *data, int64_t n, int mode, int64_t now_us)
{
    int64_t *s = r->st, i;
    if (mode != CT_RX_RESUME) {
        if (mode == CT_RX_NEW && ct_rx_over_limit(r, data, n))
            return CT_RX_OVER_LIMIT;
        s[CT_RXS_ROWS] = ct_rx_feed(r->d, data, n, 0, now_us);
        s[CT_RXS_NEXT] = 0;
    }
    for (;;) {
        i = ct_rx_route(r, s[CT_RXS_NEXT], s[CT_RXS_ROWS], now_us);
        if (i < s[CT_RXS_ROWS]) {
            s[CT_RXS_NEXT] = i + 1;
            return i;
        }
        s[CT_RXS_NEXT] = i;
        if (s[CT_RXS_ROWS] < r->d->cap || r->d->st[CT_RX_POS] >= n)
            return -1;
        s[CT_RXS_ROWS] = ct_rx_feed(r->d, data, n, r->d->st[CT_RX_POS], now_us);
        s[CT_RXS_NEXT] = 0;
    }
}
