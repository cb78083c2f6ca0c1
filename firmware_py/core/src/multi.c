/*
 * The per-sensor work of many sensors sharing one tick (include/ct_multi.h): the PULSE_WINDOW frame
 * every closed window sends, the MAG_FLIP_CMD frame each sensor gets per burst and the solver weights
 * of a channel's burst.
 *
 * Frame before COBS (little endian, protocol/framing.py): len, flags (0), seq, src, msg_id, the
 * payload "<BBHQQBBB" (protocol.schema PULSE_WINDOW), CRC-16/CCITT-FALSE over header and payload
 * then the message's CRC extra byte; then Consistent Overhead Byte Stuffing (ct_cobs_encode,
 * src/frame.c) and one 0x00.  An integer out of its field's range is refused (-1), as struct.pack
 * refuses it (the Python counts a tx error).
 */
#include <math.h>
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

static void ct_put_u64(uint8_t *o, uint64_t v)
{
    int i;
    for (i = 0; i < 8; ++i)
        o[i] = (uint8_t)(v >> (8 * i));
}

int ct_window_frame(uint8_t *out, int seq, int src, int64_t node, int64_t coil, int64_t pulse_id, uint64_t first_us,
                    uint64_t last_us, int64_t n_used, int64_t n_base, int64_t flags)
{
    uint8_t raw[CT_WINDOW_FRAME_RAW];
    uint8_t *pl = raw + 5;
    if (node < 0 || node > 0xFF || coil < 0 || coil > 0xFF || pulse_id < 0 || pulse_id > 0xFFFF || n_used < 0 ||
        n_used > 0xFF || n_base < 0 || n_base > 0xFF || flags < 0 || flags > 0xFF)
        return -1;
    pl[0] = (uint8_t)node;
    pl[1] = (uint8_t)coil;
    pl[2] = (uint8_t)pulse_id;
    pl[3] = (uint8_t)(pulse_id >> 8);
    ct_put_u64(pl + 4, first_us);
    ct_put_u64(pl + 12, last_us);
    pl[20] = (uint8_t)n_used;
    pl[21] = (uint8_t)n_base;
    pl[22] = (uint8_t)flags;
    return ct_frame_seal(raw, CT_WINDOW_PAYLOAD, seq, src, CT_WINDOW_ID, CT_WINDOW_CRC_EXTRA, out);
}

int ct_flip_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t at_us, int64_t state)
{
    uint8_t raw[CT_FLIP_FRAME_RAW];
    uint8_t *pl = raw + 5;
    if (node < 0 || node > 0xFF || state < 0 || state > 0xFF)
        return -1;
    pl[0] = (uint8_t)node;
    ct_put_u64(pl + 1, at_us);
    pl[9] = (uint8_t)state;
    return ct_frame_seal(raw, CT_FLIP_PAYLOAD, seq, src, CT_FLIP_ID, CT_FLIP_CRC_EXTRA, out);
}

void ct_sigma_from(int64_t n, const double *var, double *sig, double floor)
{
    int64_t k;
    for (k = 0; k < n; ++k) {
        double v = var[k];
        sig[k] = sqrt(v > floor ? v : floor);
    }
}

/* Python's x // 2 */
static int64_t ct_floor_half(int64_t x)
{
    int64_t q = x / 2;
    return (x % 2 != 0 && x < 0) ? q - 1 : q;
}

int64_t ct_window_column(const struct ct_window_column *c, const struct ct_pulse *x, const struct ct_sample_ring *r,
                         int64_t start, int64_t end, int64_t coil)
{
    int64_t flags, n_used, n_rec, first = 0, last = 0, n = c->n;
    int i;
    flags = ct_pulse_extract(x, r, start, end, c->res, c->res + 3, c->ires);
    n_used = c->ires[1];
    n_rec = c->ires[3];
    if (n_used && n_rec) {
        first = x->used_t[0];
        last = x->used_t[n_rec - 1];
    }
    for (i = 0; i < 3; ++i) {
        c->amp[i] = c->res[i];
        c->amp_var[i] = c->res[3 + i];
    }
    for (i = 0; i < 3; ++i) {
        c->S[i * n + coil] = c->amp[i];
        c->V[i * n + coil] = c->amp_var[i];
    }
    c->flags[coil] = flags;
    c->done[coil] = 1;
    c->pulse_mid[coil] = last ? ct_floor_half(first + last) : ct_floor_half(start + end);
    c->info[0] = n_used;
    c->info[1] = c->ires[2];
    c->info[2] = first;
    c->info[3] = last;
    return flags;
}

int ct_sample_push(int64_t *t, double *b, uint8_t *flags, int64_t cap, int64_t *st, int64_t *cnt, int64_t t_us,
                   double x, double y, double z, int saturated, int flip)
{
    int64_t p, n;
    cnt[0] += 1;
    cnt[1] += 1;
    if (t_us <= st[2] || !(isfinite(x) && isfinite(y) && isfinite(z))) {
        st[3] += 1;
        return 0;
    }
    p = st[0];
    t[p] = t_us;
    n = p + 1;
    st[0] = n == cap ? 0 : n;
    if (st[1] < cap)
        st[1] += 1;
    b[3 * p] = x;
    b[3 * p + 1] = y;
    b[3 * p + 2] = z;
    flags[p] = (uint8_t)((saturated ? CT_SAMPLE_SATURATED : 0) | (flip ? CT_SAMPLE_FLIP : 0));
    st[2] = t_us;
    return 1;
}

int64_t ct_window_run(const struct ct_window_column *const *c, const struct ct_pulse *const *x,
                      struct ct_sample_ring *const *r, const int64_t *const *hc, int64_t *const *cnt, int64_t *flags_out,
                      int64_t c0, int64_t c1, int64_t start, int64_t end, int64_t coil)
{
    int64_t i, f, flagged = 0;
    for (i = c0; i < c1; ++i) {
        r[i]->head = hc[i][0];
        r[i]->count = hc[i][1];
        f = ct_window_column(c[i], x[i], r[i], start, end, coil);
        cnt[i][1] += 1;
        flags_out[i] = f;
        if (f)
            flagged += 1;
    }
    return flagged;
}
