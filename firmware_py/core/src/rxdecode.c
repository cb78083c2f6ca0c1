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
uint16_t ct_crc16(uint16_t crc, const uint8_t *p, int n)
{
    int i, b;
    for (i = 0; i < n; ++i) {
        crc ^= (uint16_t)((uint16_t)p[i] << 8);
        for (b = 0; b < 8; ++b)
            crc = (uint16_t)((crc & 0x8000u) ? (((unsigned)crc << 1) ^ 0x1021u) : ((unsigned)crc << 1));
    }
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
