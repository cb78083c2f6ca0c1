"""Rules of one node by its role: the coil driver (pulses, refusals, signing) and the sensor
(stream, time stamps, the rate grid under late broadcasts).

Each rule is a function of the :class:`~coiltrack.protocol.conformance.session.Session`
(``s``); it adds its results to the session."""
from __future__ import annotations

import numpy as np

from ..codec import MSG
from ..errors import SchemaMismatchError
from ..peer import check_peer
from ..schema import COIL_FAULT_REFUSED, CURRENT_LSB_A
from .results import FAIL, PASS, SKIP
from .session import Session


def check_version(s: Session, n: int) -> None:
    hb = s.heartbeats[n][-1].msg
    try:
        check_peer(hb)
    except SchemaMismatchError as exc:
        s.add("heartbeat_version", FAIL, str(exc), n)
        return
    s.add("heartbeat_version", PASS, f"v{hb.proto_version} schema {hb.schema_hash:#010x}", n)


def judge_pulse(s: Session, n: int, cmd, rx) -> tuple[str, str]:
    o = s.o
    if rx is None:
        hint = "" if s.signer else " (if the node requires signed commands, pass a key)"
        return FAIL, f"no COIL_STATUS for pulse {cmd.pulse_id}{hint}"
    st = rx.msg
    if st.faults:
        return FAIL, f"COIL_STATUS faults {st.faults:#04x} for a valid command"
    problems = []
    if abs(st.start_us - cmd.start_us) > o.edge_tolerance_us:
        problems.append(f"start {st.start_us - cmd.start_us:+d} us off")
    if abs((st.end_us - st.start_us) - cmd.duration_us) > o.edge_tolerance_us:
        problems.append(f"duration {st.end_us - st.start_us} us for {cmd.duration_us} us")
    end_local = s.local_of_master(st.end_us)
    if rx.t < end_local - o.edge_tolerance_us * 1e-6 - 0.005:
        problems.append(f"status arrived {end_local - rx.t:.3f} s before the pulse ended")
    want = cmd.current_ma
    if want and not (st.current_ma * want > 0 and 0.5 <= st.current_ma / want <= 1.2):
        problems.append(f"current {st.current_ma * CURRENT_LSB_A:.3f} A for {want * CURRENT_LSB_A:.3f} A")
    if problems:
        return FAIL, "; ".join(problems)
    return PASS, (f"pulse {cmd.pulse_id}: {st.current_ma * CURRENT_LSB_A:.3f} A, "
                  f"{st.end_us - st.start_us} us, status {rx.t - end_local:+.3f} s after the end")


def driver_rules(s: Session, n: int) -> None:
    o = s.o
    cmd, mark, _ = s.pulse(n)
    rx = s.await_status(n, cmd, mark, True)
    s.add("pulse_status", *judge_pulse(s, n, cmd, rx), node=n)
    for rule, kw, what in (("refuse_over_current", {"current_ma": o.over_current_ma},
                            f"{o.over_current_ma * CURRENT_LSB_A:g} A"),
                           ("refuse_too_long", {"duration_us": o.too_long_us},
                            f"{o.too_long_us / 1e6:g} s")):
        cmd, mark, _ = s.pulse(n, **kw)
        rx = s.wait_for(s.status_for(n, cmd.pulse_id), o.answer_timeout_s, mark)
        if rx is None:
            s.add(rule, FAIL, f"no COIL_STATUS for a {what} command", n)
        elif rx.msg.faults & COIL_FAULT_REFUSED:
            s.add(rule, PASS, f"{what} refused, faults {rx.msg.faults:#04x}", n)
        else:
            s.add(rule, FAIL, f"{what} command not refused (faults {rx.msg.faults:#04x})", n)
    if s.signer is None:
        for rule in ("signed_accepted", "unsigned_rejected", "forged_rejected", "replay_rejected"):
            s.add(rule, SKIP, "no key given", n)
        return
    signing_rules(s, n)


def not_executed(s: Session, n: int, cmd, mark: int):
    """None if no (non-refused) COIL_STATUS for cmd arrived, else that status."""
    rx = s.await_status(n, cmd, mark, False)
    if rx is not None and rx.msg.faults & COIL_FAULT_REFUSED:
        return None
    return rx


def signing_rules(s: Session, n: int) -> None:
    # a correctly signed command runs
    cmd, mark, good_frame = s.pulse(n)
    rx = s.await_status(n, cmd, mark, True)
    st, detail = judge_pulse(s, n, cmd, rx)
    s.add("signed_accepted", st, detail, n)
    # unsigned
    cmd, mark, _ = s.pulse(n, signed=False)
    rx = not_executed(s, n, cmd, mark)
    s.add("unsigned_rejected", PASS if rx is None else FAIL,
             "unsigned command ignored" if rx is None else "node executed an unsigned COIL_PULSE_CMD", n)
    # forged: another key
    wrong = bytes(b ^ 0x5A for b in s.o.key)
    cmd, mark, _ = s.pulse(n, signed=True, key=wrong)
    rx = not_executed(s, n, cmd, mark)
    s.add("forged_rejected", PASS if rx is None else FAIL,
             "forged signature ignored" if rx is None else "node executed a command signed with another key", n)
    # replay: the same signed frame twice, and a new command with an old timestamp
    cmd, mark, frame = s.pulse(n, lead_us=int(s.o.lead_ms * 3000))
    s.send_frame(frame)
    old_ts = s.signer.last_timestamp
    first = s.await_status(n, cmd, mark, True)
    problems = []
    if first is None or first.msg.faults:
        problems.append("the original signed command was not executed")
    else:
        later = [rx for rx in s.log[mark:] if s.status_for(n, cmd.pulse_id)(rx)
                 and not rx.msg.faults & COIL_FAULT_REFUSED]
        if len(later) > 1:
            problems.append("a replayed frame was executed again")
    cmd2, mark2, _ = s.pulse(n, signed=True, timestamp=old_ts)
    if not_executed(s, n, cmd2, mark2) is not None:
        problems.append("a command with a not-newer timestamp was executed")
    s.add("replay_rejected", FAIL if problems else PASS,
             "; ".join(problems) if problems else "replayed frame and stale timestamp ignored", n)


#: a node's first this many TIME_SYNC replies may step its clock (docs/protocol.md, "slew, do not
#: step"; ``hil.clock.NodeSync.acquire``): its stamps are judged after them
ACQUIRE_REPLIES = 4


def acquire(s: Session, n: int) -> int | None:
    """Broadcast ``TIME_SYNC`` until node ``n`` has answered ``ACQUIRE_REPLIES`` broadcasts (one at a
    time, each waited for up to ``answer_timeout_s``); returns the log index just after its
    ``ACQUIRE_REPLIES``-th reply, or None when it stops answering. While it acquires a node may step
    its clock by as much as its first broadcast was late (a loaded link: 100 ms and more), and a
    compact stamp that far behind the receiver's clock is restored a wrap too far
    (``protocol.schema.unwrap_stamp``): its stamps are judged after acquisition."""
    def replies():
        return [i for i, rx in enumerate(s.log) if rx.src == n and rx.msg.NAME == "TIME_SYNC_REPLY"]

    got = replies()
    while len(got) < ACQUIRE_REPLIES:
        mark = len(s.log)
        seq = s.next_sync_seq()
        s.send(MSG["TIME_SYNC"](s.master_us(), seq))
        if s.wait_for(lambda rx: rx.src == n and rx.msg.NAME == "TIME_SYNC_REPLY" and rx.msg.sync_seq == seq,
                      s.o.answer_timeout_s, mark) is None:
            return None
        got = replies()
    return got[ACQUIRE_REPLIES - 1] + 1


def sensor_rules(s: Session, n: int) -> None:
    o = s.o
    # samples after the node acquired the master's time (before, its stamps may be on its own clock,
    # or step: ``acquire``); observed for ``observe_s`` from then
    after = acquire(s, n)
    if after is not None:
        s.run_for(o.observe_s)
    mags = [rx for rx in s.log[after or 0:] if rx.src == n and rx.msg.NAME == "MAG_SAMPLE"]
    if len(mags) < 3:
        s.add("mag_stream", FAIL, f"{len(mags)} MAG_SAMPLE in {o.observe_s:g} s", n)
        s.add("mag_timestamps", SKIP, "too few samples", n)
        return
    ts = np.array([rx.msg.t_us for rx in mags], dtype=np.int64)
    d = np.diff(ts)
    if np.all(d > 0):
        s.add("mag_timestamps", PASS, f"{len(ts)} samples, strictly increasing", n)
    else:
        k = int(np.argmax(d <= 0))
        s.add("mag_timestamps", FAIL, f"t_us goes from {ts[k]} to {ts[k + 1]}", n)
    stamp_rate = 1e6 / float(np.median(d)) if np.median(d) > 0 else 0.0
    span = mags[-1].t - mags[0].t
    arrival_rate = (len(mags) - 1) / span if span > 0 else 0.0
    problems = []
    tol = o.rate_tolerance
    rate = o.mag_rate_hz or stamp_rate
    if o.mag_rate_hz and abs(stamp_rate / o.mag_rate_hz - 1) > tol:
        problems.append(f"time stamps say {stamp_rate:.1f} Hz, expected {o.mag_rate_hz:g} Hz")
    # samples arrive in bursts (link and scheduling): allow 50 ms of slack on the arrival span
    expect_span = (len(mags) - 1) / rate if rate > 0 else 0.0
    if rate <= 0 or abs(span - expect_span) > tol * expect_span + 0.05:
        problems.append(f"{len(mags)} samples arrived over {span:.3f} s: {arrival_rate:.1f} Hz, "
                        f"expected {rate:.1f} Hz")
    s.add("mag_stream", FAIL if problems else PASS,
             "; ".join(problems) if problems else
             f"{stamp_rate:.1f} Hz by time stamps, {arrival_rate:.1f} Hz arriving", n)
    grid_rule(s, n, rate)


def late_sync_phase(s: Session, seconds: float, on_time: int = 5) -> int:
    """Broadcast every ``late_sync_period_s``: ``on_time`` broadcasts on time (a node still
    acquiring may step its clock), then for ``seconds`` every other one written ``late_sync_us``
    behind; returns the log index where the late broadcasts began."""
    o = s.o
    mark = len(s.log)
    end = None
    nxt, k = s.clock(), 0
    while end is None or s.clock() < end:
        s.pump()
        now = s.clock()
        if now >= nxt:
            seq = s.next_sync_seq()
            late = o.late_sync_us if k >= on_time and (k - on_time) % 2 else 0
            if k == on_time:
                mark, end = len(s.log), now + seconds
            s.send(MSG["TIME_SYNC"](s.master_us(now) - late, seq))
            nxt, k = now + o.late_sync_period_s, k + 1
        s.sleep(0.001)
    return mark


def grid_rule(s: Session, n: int, rate_hz: float) -> None:
    o = s.o
    mark = late_sync_phase(s, o.grid_observe_s)
    ts = np.array([rx.msg.t_us for rx in s.log[mark:] if rx.src == n and rx.msg.NAME == "MAG_SAMPLE"],
                  dtype=np.int64)
    if len(ts) < 3 or rate_hz <= 0:
        s.add("mag_grid", FAIL, f"{len(ts)} MAG_SAMPLE while the broadcasts came late", n)
        return
    P = 1e6 / rate_hz
    d = np.diff(ts).astype(float)
    k = np.maximum(np.floor(d / P + 0.5), 1.0)
    dev = np.abs(d - k * P)[k <= 64]
    worst = float(dev.max()) if dev.size else 0.0
    detail = (f"{len(ts)} samples with every other broadcast {o.late_sync_us} us late: worst interval "
              f"{worst:.0f} us off the {P:.1f} us grid (tolerance {o.grid_tolerance_us} us, margin "
              f"{o.grid_tolerance_us - worst:.0f} us)")
    if worst > o.grid_tolerance_us:
        detail += "; the node steps its clock correction: slew it (docs/protocol.md, 'slew, do not step')"
    s.add("mag_grid", FAIL if worst > o.grid_tolerance_us else PASS, detail, n)
