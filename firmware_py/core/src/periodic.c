/*
 * The firmware's periodic frames (include/ct_periodic.h): TIME_SYNC, HEARTBEAT and FAULT_EVENT as
 * protocol.framing.encode_frame builds them, so the supervisor's periodic broadcast and the
 * transmitter's heartbeat leave a tick in one short call instead of the Python encoder's ~30 us
 * (a cold encode_frame: struct packing, crcmod, COBS over bytes.split).
 */
#include <stdint.h>
#include <string.h>

#include "coiltrack_core.h"

static void ct_put_le(uint8_t *o, uint64_t v, int n)
{
    int i;
    for (i = 0; i < n; ++i)
        o[i] = (uint8_t)(v >> (8 * i));
}

int ct_sync_frame(uint8_t *out, int seq, int src, uint64_t master_time_us, int64_t sync_seq)
{
    uint8_t raw[CT_SYNC_FRAME_RAW];
    uint8_t *pl = raw + 5;
    if (sync_seq < 0 || sync_seq > 0xFFFF)
        return -1;
    ct_put_le(pl, master_time_us, 8);
    ct_put_le(pl + 8, (uint64_t)sync_seq, 2);
    return ct_frame_seal(raw, CT_SYNC_PAYLOAD, seq, src, CT_SYNC_ID, CT_SYNC_CRC_EXTRA, out);
}

int ct_heartbeat_frame(uint8_t *out, int seq, int src, int64_t node, int64_t role, int64_t state,
                       int64_t proto_version, int64_t schema_hash, int64_t errors)
{
    uint8_t raw[CT_HEARTBEAT_FRAME_RAW];
    uint8_t *pl = raw + 5;
    if (node < 0 || node > 0xFF || role < 0 || role > 0xFF || state < 0 || state > 0xFF || proto_version < 0 ||
        proto_version > 0xFF || schema_hash < 0 || schema_hash > 0xFFFFFFFFLL || errors < 0 || errors > 0xFFFF)
        return -1;
    pl[0] = (uint8_t)node;
    pl[1] = (uint8_t)role;
    pl[2] = (uint8_t)state;
    pl[3] = (uint8_t)proto_version;
    ct_put_le(pl + 4, (uint64_t)schema_hash, 4);
    ct_put_le(pl + 8, (uint64_t)errors, 2);
    return ct_frame_seal(raw, CT_HEARTBEAT_PAYLOAD, seq, src, CT_HEARTBEAT_ID, CT_HEARTBEAT_CRC_EXTRA, out);
}

int ct_event_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, int64_t code, int64_t detail)
{
    uint8_t raw[CT_EVENT_FRAME_RAW];
    uint8_t *pl = raw + 5;
    if (node < 0 || node > 0xFF || code < 0 || code > 0xFFFF || detail < 0 || detail > 0xFFFFFFFFLL)
        return -1;
    pl[0] = (uint8_t)node;
    ct_put_le(pl + 1, t_us, 8);
    ct_put_le(pl + 9, (uint64_t)code, 2);
    ct_put_le(pl + 11, (uint64_t)detail, 4);
    return ct_frame_seal(raw, CT_EVENT_PAYLOAD, seq, src, CT_EVENT_ID, CT_EVENT_CRC_EXTRA, out);
}
