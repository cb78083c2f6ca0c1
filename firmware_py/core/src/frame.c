/*
 * The transmit stage's POSE frame: the compiled form of coiltrack.firmware.transmit.Transmitter.pose
 * with protocol.framing.encode_frame (build_frame, frame_crc, cobs_encode) for the one message
 * the loop sends at the IMU rate.
 *
 * Frame before COBS (little endian, protocol/framing.py): len, flags (0), seq, src, msg_id, the
 * payload "<BQfffffffffffffHB" (protocol.schema POSE: node, t_us, p (3), q (4), the six variances,
 * status, quality), CRC-16/CCITT-FALSE over header and payload then the message's CRC extra byte;
 * then Consistent Overhead Byte Stuffing and one 0x00.  A double that does not fit an f32
 * (finite, beyond its range) or an integer out of its field's range is refused (-1), as
 * struct.pack refuses it (the Python counts a tx error).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

/* struct's '<f': round to the nearest f32; a finite double beyond the f32 range is refused */
static int ct_put_f32(uint8_t *o, double v)
{
    float f = (float)v;
    uint32_t u;
    if (isinf(f) && !isinf(v))
        return -1;
    memcpy(&u, &f, 4);
    o[0] = (uint8_t)u;
    o[1] = (uint8_t)(u >> 8);
    o[2] = (uint8_t)(u >> 16);
    o[3] = (uint8_t)(u >> 24);
    return 0;
}

/* cobs_encode of n bytes into out (room for n + n / 254 + 1), returns the encoded length */
int ct_cobs_encode(const uint8_t *in, int n, uint8_t *out)
{
    int code_at = 0, k = 1, i;
    uint8_t code = 1;
    for (i = 0; i < n; ++i) {
        if (in[i] == 0) {
            out[code_at] = code;
            code_at = k++;
            code = 1;
        } else {
            out[k++] = in[i];
            if (++code == 0xFF) {
                out[code_at] = code;
                code_at = k++;
                code = 1;
            }
        }
    }
    out[code_at] = code;
    return k;
}

/* POSE: the v[13] doubles are px, py, pz, qw, qx, qy, qz and the six variances, each clamped to
 * transmit.F32_MAX (_f32: a NaN too) */
int ct_frame_seal(uint8_t *raw, int len, int seq, int src, int id, uint8_t crc_extra, uint8_t *out)
{
    uint16_t crc;
    int k;
    raw[0] = (uint8_t)len;
    raw[1] = 0;
    raw[2] = (uint8_t)(seq & 0xFF);
    raw[3] = (uint8_t)(src & 0xFF);
    raw[4] = (uint8_t)id;
    crc = ct_crc16(ct_crc16(0xFFFFu, raw, 5 + len), &crc_extra, 1);
    raw[5 + len] = (uint8_t)(crc & 0xFF);
    raw[6 + len] = (uint8_t)(crc >> 8);
    k = ct_cobs_encode(raw, len + 7, out);
    out[k] = 0;
    return k + 1;
}

int ct_pose_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, const double *v, int64_t status,
                  int64_t quality)
{
    uint8_t raw[CT_POSE_FRAME_RAW];
    uint8_t *pl = raw + 5;
    uint64_t t;
    int i;
    if (node < 0 || node > 0xFF || status < 0 || status > 0xFFFF || quality < 0 || quality > 0xFF)
        return -1;
    pl[0] = (uint8_t)node;
    t = t_us;
    for (i = 0; i < 8; ++i)
        pl[1 + i] = (uint8_t)(t >> (8 * i));
    for (i = 0; i < 13; ++i) {
        double x = v[i];
        if (i >= 7 && !(x < CT_F32_MAX))
            x = CT_F32_MAX;
        if (ct_put_f32(pl + 9 + 4 * i, x) < 0)
            return -1;
    }
    pl[61] = (uint8_t)status;
    pl[62] = (uint8_t)(status >> 8);
    pl[63] = (uint8_t)quality;
    return ct_frame_seal(raw, CT_POSE_PAYLOAD, seq, src, CT_POSE_ID, CT_POSE_CRC_EXTRA, out);
}
