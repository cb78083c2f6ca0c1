"""Rules of the link: garbage and corrupted frames, optional messages, time sync, heartbeat
period, sources, frame validity and sequence numbers.

Each rule is a function of the :class:`~coiltrack.protocol.conformance.session.Session`
(``s``); it adds its results to the session."""
from __future__ import annotations

import json

import numpy as np

from ..codec import MSG
from ..framing import build_frame, cobs_encode, encode_frame
from ..schema import ROLE_COIL_DRIVER, ROLE_SENSOR
from .results import FAIL, PASS, SKIP
from .session import Session


def garbage_serial(s: Session) -> bytes:
    rng = s.rng
    good = encode_frame(MSG["TIME_SYNC"](123_456, 0xFFFF), 0, s.o.src)
    parts = [bytes(rng.integers(0, 256, 300, dtype=np.uint8)) + b"\x00"]
    flipped = bytearray(good)
    i = int(rng.integers(0, len(flipped) - 1))
    flipped[i] ^= 0x10
    if b"\x00" in flipped[:-1]:
        flipped[i] ^= 0x30
    parts.append(bytes(flipped))
    parts.append(good[: len(good) // 2] + b"\x00")
    parts.append(bytes(rng.integers(1, 256, 3000, dtype=np.uint8)) + b"\x00")   # longer than any frame
    raw = bytearray(build_frame(MSG["TIME_SYNC"](0, 0), 0, s.o.src))
    raw[0] += 1                                                                    # wrong length byte
    parts.append(cobs_encode(bytes(raw)) + b"\x00")
    raw = bytearray(build_frame(MSG["TIME_SYNC"](0, 0), 0, s.o.src))
    raw[4] = 0xEE                                                                  # unknown id
    parts.append(cobs_encode(bytes(raw)) + b"\x00")
    return b"".join(parts)


def garbage_can(s: Session) -> int:
    import can

    from ..can import (_MSG_BY_BASE, BASE_ID, FUNCTION_MASK, NODE_MASK, build_pdu, can_id, direct_size, ext_id,
                      segment)

    bus = s.link.bus
    rng = s.rng
    src = s.o.src & NODE_MASK
    tsid = can_id(MSG["TIME_SYNC"].ID, src)
    # ISO-TP garbage on the 29-bit identifiers (protocol v3: an 8-byte frame on an 11-bit TIME_SYNC or
    # COIL_PULSE_CMD identifier is that message's bus form, never a segment)
    tsx, pcx = ext_id(tsid), ext_id(can_id(MSG["COIL_PULSE_CMD"].ID, src))
    good = segment(build_pdu(MSG["TIME_SYNC"](0, 0xFFFE), 0, src))
    frames = [
        can.Message(arbitration_id=tsx, is_extended_id=True, data=b"\x21\x01\x02"),     # CF without FF
        can.Message(arbitration_id=tsx, is_extended_id=True, data=good[0]),                # FF ...
        can.Message(arbitration_id=tsx, is_extended_id=True, data=b"\x25" + bytes(7)),    # ... wrong SN
        can.Message(arbitration_id=pcx, is_extended_id=True, data=b"\x1F\xFF" + bytes(6)),  # 4095 bytes
        can.Message(arbitration_id=tsx, is_extended_id=True, data=b"\x71\x02"),           # unknown PCI
        can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"\x01\x02"),           # foreign id
        can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, data=b"\x02\x03"),        # extended id
        can.Message(arbitration_id=tsid, is_extended_id=False, is_remote_frame=True, dlc=2),
        can.Message(arbitration_id=tsid, is_extended_id=False, data=b""),
        can.Message(arbitration_id=tsid, is_extended_id=False, data=bytes(7)),          # bus form one byte short
    ]
    bad_crc = [bytearray(d) for d in good]
    bad_crc[-1][-1] ^= 0x01
    frames += [can.Message(arbitration_id=tsx, is_extended_id=True, data=bytes(d)) for d in bad_crc]
    for _ in range(20):
        arb = (int(rng.choice(list(BASE_ID.values()))) | src) if rng.random() < 0.8 else int(rng.integers(0, 0x800))
        n = int(rng.integers(1, 9))
        mid = _MSG_BY_BASE.get(arb & FUNCTION_MASK)
        if mid is not None and n == direct_size(mid):
            n -= 1                     # a wrong length: never a well-formed single frame or bus form
        frames.append(can.Message(arbitration_id=arb, is_extended_id=False,
                                  data=bytes(rng.integers(0, 256, n, dtype=np.uint8))))
    sent = 0
    for f in frames:
        try:
            bus.send(f, timeout=0.1)
            sent += 1
        except (can.CanError, OSError, ValueError):
            pass
    return sent


def garbage_rules(s: Session, nodes: dict) -> None:
    if not nodes:
        return
    if hasattr(s.link, "bus") and hasattr(s.link, "codec"):
        what = f"{garbage_can(s)} bad CAN frames"
    else:
        g = garbage_serial(s)
        s.send_frame(g)
        what = f"{len(g)} bytes of garbage and bad frames"
    s.run_for(0.05)
    for n in sorted(nodes):
        role = nodes[n]
        if role == ROLE_COIL_DRIVER:
            cmd, mark, _ = s.pulse(n)
            rx = s.await_status(n, cmd, mark, True)
            ok = rx is not None and not rx.msg.faults
            s.add("survives_garbage", PASS if ok else FAIL,
                     f"after {what}: pulse " + ("answered" if ok else "not answered"), n)
        else:
            name = "MAG_SAMPLE" if role == ROLE_SENSOR else "HEARTBEAT"
            mark = len(s.log)
            timeout = 0.5 if role == ROLE_SENSOR else s.o.heartbeat_timeout_s
            rx = s.wait_for(lambda r: r.src == n and r.msg.NAME == name, timeout, mark)
            s.add("survives_garbage", PASS if rx else FAIL,
                     f"after {what}: {name} " + ("still arriving" if rx else "stopped"), n)


def optional_rules(s: Session, nodes: dict) -> None:
    """CONFIG_GET to every node, one wait for all the answers."""
    if not nodes:
        return
    mark = len(s.log)
    for n in sorted(nodes):
        s.send(MSG["CONFIG_GET"](n, 0))
    s.wait_for(lambda r: False, s.o.optional_wait_s, mark)
    for n in sorted(nodes):
        rx = next((r for r in s.log[mark:] if r.src == n and r.msg.NAME == "CONFIG_ACK"), None)
        if rx is None:
            s.add("config_get", SKIP, "no CONFIG_ACK (configuration is optional)", n)
        else:
            s.add("config_get", PASS, f"CONFIG_ACK key {rx.msg.key} result {rx.msg.result}", n)


def time_sync_rule(s: Session, n: int) -> None:
    replies = [r for r in s.log if r.src == n and r.msg.NAME == "TIME_SYNC_REPLY"]
    ours = [r for r in replies if r.msg.sync_seq in s.syncs_sent]
    if not ours:
        s.add("time_sync", FAIL, f"no TIME_SYNC_REPLY to {len(s.syncs_sent)} TIME_SYNC"
                 + (f" ({len(replies)} replies with unknown sync_seq)" if replies else ""), n)
        return
    last = ours[-1].msg
    states = [h.msg.state for h in s.heartbeats.get(n, [])]
    s.add("time_sync", PASS, f"{len(ours)} replies to {len(s.syncs_sent)} TIME_SYNC; last offset "
             f"{last.offset_us} us, drift {last.drift_ppb} ppb; heartbeat states {sorted(set(states))}", n)


def link_rules(s: Session, nodes: dict) -> None:
    o = s.o
    if nodes:   # observe long enough to judge the heartbeat period of every node
        need = max(s.heartbeats[n][0].t for n in nodes) + o.heartbeat_timeout_s + 0.05 - s.clock()
        if need > 0:
            s.run_for(need)
    end = s.clock()
    for n in sorted(nodes):
        hbs = s.heartbeats[n]
        times = [hbs[0].t] + [h.t for h in hbs[1:]] + [end]
        gaps = np.diff(times)
        if end - hbs[0].t < o.heartbeat_timeout_s:
            s.add("heartbeat_period", SKIP, "session too short", n)
        elif gaps.max() > o.heartbeat_timeout_s:
            s.add("heartbeat_period", FAIL, f"{gaps.max():.2f} s without HEARTBEAT", n)
        else:
            s.add("heartbeat_period", PASS, f"{len(hbs)} heartbeats, longest gap {gaps.max():.2f} s", n)
        time_sync_rule(s, n)
        wrong = [rx for rx in s.log if rx.msg.NAME == "HEARTBEAT" and rx.msg.node == n and rx.src != n]
        s.add("src_matches_node", FAIL if wrong else PASS,
                 f"HEARTBEAT of node {n} sent with src {wrong[0].src}" if wrong else "src == node", n)
    d = s.decoder
    can_bad = 0
    re = getattr(s.link, "reassembler", None)
    if re is not None:
        can_bad = re.frames_bad
    bad = d.frames_bad + can_bad
    detail = f"{d.frames_ok} frames, {bad} bad"
    if bad:
        kinds = {k: v for k, v in d.counters().items() if k.endswith(("errors", "ids", "overflows")) and v}
        if re is not None:
            kinds.update({"can_" + k: v for k, v in re.counters().items()
                          if v and k not in ("frames_in", "messages_ok", "frames_bad", "duplicates",
                                             "ignored", "seq_gaps")})
        detail += " " + json.dumps(kinds)
    s.add("frames_valid", FAIL if bad else PASS, detail)
    # on CAN the reassembler judges the gaps: a single frame carries no seq (it is numbered on
    # receipt), so only consecutive PDUs of a sender show one
    gaps = re.seq_gaps if re is not None else d.seq_gaps
    s.add("sequence", FAIL if gaps else PASS,
             f"{gaps} gaps in per-sender sequence numbers" if gaps else "no gaps")
