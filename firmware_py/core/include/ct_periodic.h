/*
 * The firmware's periodic frames: the TIME_SYNC broadcast (coiltrack.firmware.supervise.timesync
 * TimeSyncMaster.step through Transmitter.time_sync), the HEARTBEAT (Transmitter.step) and the
 * FAULT_EVENT report (Transmitter.event), built as protocol.framing.encode_frame builds them: the
 * header (len, flags 0, seq, src, msg_id), the payload little endian, CRC-16/CCITT-FALSE over header
 * and payload then the message's CRC extra byte, COBS (ct_cobs_encode) and one 0x00.  Each returns
 * the frame's length, or -1 for a field out of its range (struct.pack's refusal: the Python counts a
 * tx error).  The schema constants are checked against protocol.schema at start-up (transmit.py).
 */
#ifndef CT_PERIODIC_H
#define CT_PERIODIC_H

#include <stdint.h>

/* TIME_SYNC (payload "<QH": master_time_us, sync_seq) */
enum { CT_SYNC_ID = 0x02, CT_SYNC_PAYLOAD = 10, CT_SYNC_CRC_EXTRA = 0x25,
       CT_SYNC_FRAME_RAW = 5 + 10 + 2, CT_SYNC_FRAME_MAX = 5 + 10 + 2 + 2 + 1 };
int ct_sync_frame(uint8_t *out, int seq, int src, uint64_t master_time_us, int64_t sync_seq);

/* HEARTBEAT (payload "<BBBBIH": node, role, state, proto_version, schema_hash, errors) */
enum { CT_HEARTBEAT_ID = 0x01, CT_HEARTBEAT_PAYLOAD = 10, CT_HEARTBEAT_CRC_EXTRA = 0x65,
       CT_HEARTBEAT_FRAME_RAW = 5 + 10 + 2, CT_HEARTBEAT_FRAME_MAX = 5 + 10 + 2 + 2 + 1 };
int ct_heartbeat_frame(uint8_t *out, int seq, int src, int64_t node, int64_t role, int64_t state,
                       int64_t proto_version, int64_t schema_hash, int64_t errors);

/* FAULT_EVENT (payload "<BQHI": node, t_us, code, detail) */
enum { CT_EVENT_ID = 0x50, CT_EVENT_PAYLOAD = 15, CT_EVENT_CRC_EXTRA = 0x77,
       CT_EVENT_FRAME_RAW = 5 + 15 + 2, CT_EVENT_FRAME_MAX = 5 + 15 + 2 + 2 + 1 };
int ct_event_frame(uint8_t *out, int seq, int src, int64_t node, uint64_t t_us, int64_t code, int64_t detail);

#endif
