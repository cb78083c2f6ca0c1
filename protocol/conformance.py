"""Conformance suite: checks a node someone else built against the protocol.

The tester plays the master (the firmware, node 1 by default) on a byte
Port: a :class:`protocol.serial_link.SerialLink` for serial, a
:class:`protocol.can.CanLink` for CAN, so the same rules run on both links.
It discovers nodes by their HEARTBEAT, then runs the rules that apply to
each node's role and reports pass / fail / skip per rule and per message.

Rules (``RULES`` lists them with their text):

link and every node
    ``heartbeat`` a HEARTBEAT within 1.5 s; ``heartbeat_version`` matching
    protocol version and schema hash (:func:`protocol.check_peer`);
    ``heartbeat_period`` no gap over 1.5 s between heartbeats;
    ``src_matches_node`` frames' src equals the HEARTBEAT's node;
    ``frames_valid`` every frame it sends decodes (COBS, length, CRC with CRC
    extra; on CAN also the ISO-TP segmentation); ``sequence`` sequence
    numbers increase by one per sender; ``survives_garbage`` after random
    bytes, corrupted, truncated and over-long frames it still answers.
coil driver (role 1)
    ``pulse_status`` a pulse scheduled ``lead`` ahead is answered, after the
    pulse, by COIL_STATUS with the same pulse id, no fault, edges within
    ``edge_tolerance_us`` of the command and a current of the commanded sign
    and 50..120 % of its size; ``refuse_over_current`` and ``refuse_too_long``
    are answered with the REFUSED bit. With a key: ``signed_accepted``,
    ``unsigned_rejected``, ``forged_rejected``, ``replay_rejected``.
sensor (role 2)
    ``mag_stream`` MAG_SAMPLE (or protocol v2's MAG_PACKED, its time restored
    on arrival) at the expected rate (from its time stamps and
    from arrival times, within ``rate_tolerance``); ``mag_timestamps``
    strictly increasing ``t_us``; ``mag_grid`` every interval between
    consecutive stamps within ``grid_tolerance_us`` (400 us, the firmware's
    ``stamp_interval_tol_us``) of a whole number of periods while every other
    broadcast is written ``late_sync_us`` behind, as a frame that arrived
    late: a node that steps its correction at each broadcast fails, one that
    slews passes (the firmware counts a larger jump as a clock step).
bench mode (``bench=True``: a driver and a sensor sharing a real coil)
    ``bench_pulse`` ``bench_pulses`` pulses of the firmware's length and
    current, their starts dithered over one sample period: every sample in
    the firmware's window (``start + settle_us`` .. ``end - guard_us``) shows
    the pulse's field, every quiet sample (before the start, after
    ``end + fall_us``) does not; the rise and fall edges as seen in the
    samples are bracketed to a fraction of the sample period and reported
    with their margins to the window.
time
    ``time_sync`` every node answers the tester's TIME_SYNC with
    TIME_SYNC_REPLY (same ``sync_seq``).
optional (skipped when the node does not answer)
    ``config_get`` CONFIG_ACK to CONFIG_GET.

Master time: the tester is the master. It broadcasts TIME_SYNC from the
start and every ``sync_period_s`` with its own clock (``master_us()``), so
nodes stamp samples and edges on it and it schedules pulses on it, exactly
as the firmware does. (A node streams and accepts pulses only once it is
synchronised.)
"""
from __future__ import annotations

import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from .codec import MSG
from .errors import ProtocolError, SchemaMismatchError
from .framing import FrameDecoder, FrameEncoder, build_frame, cobs_decode, cobs_encode, encode_frame
from .peer import check_peer, role_name
from .schema import (BUS_START_LSB_US, BY_ID, COIL_FAULT_REFUSED, CURRENT_LSB_A, NODE_FIRMWARE, PULSE_ID_MASK,
                     ROLE_COIL_DRIVER, STAMP_FLIP, STAMP_MASK, STAMP_SATURATED, unwrap_stamp,
                     ROLE_SENSOR)
from .signing import Signer

PASS, FAIL, SKIP = "PASS", "FAIL", "SKIP"
#: master time of the tester's start (any value; nodes only follow it)
MASTER_EPOCH_US = 1_000_000

RULES = {
    "heartbeat": "node sends HEARTBEAT within the heartbeat timeout (1.5 s)",
    "heartbeat_version": "HEARTBEAT protocol version and schema hash match (check_peer)",
    "heartbeat_period": "no gap longer than the heartbeat timeout between heartbeats",
    "src_matches_node": "frame src equals HEARTBEAT.node",
    "frames_valid": "every frame the node sends decodes with a valid CRC",
    "sequence": "sequence numbers increase by one per sender",
    "pulse_status": "scheduled pulse answered by COIL_STATUS after the pulse, plausible edges and current",
    "refuse_over_current": "over-current pulse command answered with COIL_STATUS REFUSED",
    "refuse_too_long": "too-long pulse command answered with COIL_STATUS REFUSED",
    "signed_accepted": "a correctly signed pulse command is executed",
    "unsigned_rejected": "an unsigned pulse command is not executed",
    "forged_rejected": "a pulse command signed with another key is not executed",
    "replay_rejected": "a replayed or not-newer signed command is not executed",
    "mag_stream": "MAG_SAMPLE streamed at the expected rate",
    "mag_timestamps": "MAG_SAMPLE t_us strictly increasing",
    "survives_garbage": "node still answers after garbage and corrupted frames",
    "config_get": "CONFIG_GET answered with CONFIG_ACK (optional)",
    "discovered": "a node first heard after discovery (its rules were not run)",
    "time_sync": "TIME_SYNC answered with TIME_SYNC_REPLY",
    "mag_grid": "MAG_SAMPLE stamps stay on the rate grid (within 400 us) while broadcasts arrive late: "
                "clock corrections slewed, not stepped",
    "bench_pulse": "bench mode: a commanded pulse shows in the sensor's samples inside the firmware's window, "
                   "edges measured against the command",
}


@dataclass
class ConformOptions:
    src: int = NODE_FIRMWARE
    node: int | None = None              # test only this node id
    heartbeat_timeout_s: float = 1.5
    observe_s: float = 1.2               # stream observation window
    discover_s: float | None = None      # listen this long for nodes (default: heartbeat_timeout_s)
    lead_ms: float = 100.0               # pulses scheduled this far ahead
    pulse_ms: float = 20.0
    pulse_current_ma: int = 500
    over_current_ma: int = 30_000
    too_long_us: int = 10_000_000
    answer_timeout_s: float = 1.0        # extra time allowed for an answer after the pulse
    silence_s: float = 0.25              # wait after a pulse's end before calling it "not executed"
    edge_tolerance_us: int = 2_000
    mag_rate_hz: float | None = 120.0    # None or 0: only self-consistency
    rate_tolerance: float = 0.10
    key: bytes | None = None
    link_id: int = 0
    seed: int = 1
    optional_wait_s: float = 0.25
    sync_period_s: float = 0.5           # TIME_SYNC broadcast period (the tester is the master)
    max_log: int = 200_000
    # stamp regularity (mag_grid): broadcasts every late_sync_period_s, every other one written
    # late_sync_us behind (as if it had arrived that late); the firmware's sample-grid tolerance
    late_sync_us: int = 1_500
    late_sync_period_s: float = 0.1
    grid_observe_s: float = 1.2
    grid_tolerance_us: int = 400
    # bench mode (--bench): driver and sensor share a real coil; the firmware's pulse and windows
    bench: bool = False
    bench_pulses: int = 6
    bench_pulse_ms: float = 60.0
    bench_current_ma: int = 1_500
    bench_coils: int = 3                 # the pulses go round the driver's first coils
    settle_us: int = 3_000               # the firmware's windows (pulse.settle_us, guard_us, fall_us)
    guard_us: int = 2_000
    fall_us: int = 3_000


@dataclass
class RuleResult:
    rule: str
    status: str
    detail: str = ""
    node: int | None = None


@dataclass
class ConformReport:
    transport: str
    nodes: dict = field(default_factory=dict)        # node id -> role name
    messages: dict = field(default_factory=dict)     # name -> stats
    rules: list = field(default_factory=list)
    counters: dict = field(default_factory=dict)
    duration_s: float = 0.0

    @property
    def passed(self) -> int:
        return sum(r.status == PASS for r in self.rules)

    @property
    def failed(self) -> int:
        return sum(r.status == FAIL for r in self.rules)

    @property
    def skipped(self) -> int:
        return sum(r.status == SKIP for r in self.rules)

    @property
    def ok(self) -> bool:
        return self.failed == 0 and any(r.status == PASS for r in self.rules)

    def result(self, rule: str, node: int | None = None) -> RuleResult | None:
        for r in self.rules:
            if r.rule == rule and (node is None or r.node == node):
                return r
        return None

    def to_dict(self) -> dict:
        return {"transport": self.transport, "nodes": {str(k): v for k, v in self.nodes.items()},
                "messages": self.messages, "rules": [asdict(r) for r in self.rules],
                "counters": self.counters, "duration_s": round(self.duration_s, 3),
                "passed": self.passed, "failed": self.failed, "skipped": self.skipped, "ok": self.ok}

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=2)

    def format(self) -> str:
        out = [f"coiltrack conform over {self.transport}: "
               + (", ".join(f"node {k} ({v})" for k, v in sorted(self.nodes.items())) or "no node found")]
        out.append("")
        out.append("messages received")
        out.append(f"  {'message':16s} {'from':12s} {'count':>6s} {'rate Hz':>8s} {'bad':>4s}  result")
        for name, st in self.messages.items():
            frm = ",".join(str(s) for s in st["from"]) or "-"
            out.append(f"  {name:16s} {frm:12s} {st['count']:6d} {st['rate_hz']:8.2f} {st['bad']:4d}  "
                       f"{PASS if st['bad'] == 0 else FAIL}")
        out.append("")
        out.append("rules")
        for r in self.rules:
            who = "link" if r.node is None else f"node {r.node}"
            out.append(f"  {r.status:4s}  {who:8s} {r.rule:20s} {r.detail}")
        out.append("")
        out.append(f"{self.passed} passed, {self.failed} failed, {self.skipped} skipped "
                   f"in {self.duration_s:.1f} s: {'CONFORMS' if self.ok else 'DOES NOT CONFORM'}")
        return "\n".join(out)


class _Decoder(FrameDecoder):
    """FrameDecoder that attributes bad frames to a message when it can."""

    def __init__(self, on_frame):
        super().__init__(on_frame=on_frame)
        self.bad_by_message: dict[str, int] = {}

    def _decode(self, enc):
        before = self.frames_bad
        msg = super()._decode(enc)
        if msg is None and self.frames_bad > before:
            name = "?"
            try:
                raw = cobs_decode(bytes(enc))
                if len(raw) > 4 and raw[4] in BY_ID:
                    name = BY_ID[raw[4]].name
            except ProtocolError:
                pass
            self.bad_by_message[name] = self.bad_by_message.get(name, 0) + 1
        return msg


@dataclass
class _Rx:
    t: float          # local monotonic seconds
    src: int
    seq: int
    flags: int
    msg: object


class Conformance:
    """Run the suite on ``link`` (a byte Port). ``transport`` is for display."""

    def __init__(self, link, options: ConformOptions | None = None, transport: str = "link",
                 clock=time.monotonic, sleep=time.sleep):
        self.link = link
        self.o = options or ConformOptions()
        self.transport = transport
        self.clock = clock
        self.sleep = sleep
        self.rng = np.random.default_rng(self.o.seed)
        self.decoder = _Decoder(self._on_frame)
        self.encoder = FrameEncoder(self.o.src)
        self.signer = Signer(self.o.key, self.o.link_id) if self.o.key else None
        self.log: list[_Rx] = []
        self.heartbeats: dict[int, list[_Rx]] = {}
        self.sync_seq = int(self.rng.integers(0, 0x8000))
        self.syncs_sent: set[int] = set()
        self.next_sync = None
        self.dropped_log = 0
        self.rules: list[RuleResult] = []
        self.t0 = self.clock()
        self.next_pulse_id = int(self.rng.integers(0x400, 0xC00))     # 12 bits: the bus form's pulse_id

    # ------------------------------------------------------------ plumbing
    def _on_frame(self, hdr, msg) -> None:
        t = self.clock()
        if msg.NAME == "MAG_PACKED":
            # protocol v2's one-frame sample: its time restored against the master clock at arrival,
            # then judged by the same rules as a MAG_SAMPLE
            st = msg.stamp
            msg = MSG["MAG_SAMPLE"](msg.node, unwrap_stamp(st & STAMP_MASK, self.master_us(t)), msg.x, msg.y, msg.z,
                                    (1 if st & STAMP_FLIP else 0) | (2 if st & STAMP_SATURATED else 0))
        rx = _Rx(t, hdr.src, hdr.seq, hdr.flags, msg)
        if len(self.log) < self.o.max_log:
            self.log.append(rx)
        else:
            self.dropped_log += 1
        if msg.NAME == "HEARTBEAT":
            self.heartbeats.setdefault(msg.node, []).append(rx)

    def master_us(self, t: float | None = None) -> int:
        """Master time (us) of local time ``t`` (default: now)."""
        t = self.clock() if t is None else t
        return MASTER_EPOCH_US + int(round((t - self.t0) * 1e6))

    def local_of_master(self, master_us: int) -> float:
        return self.t0 + (master_us - MASTER_EPOCH_US) * 1e-6

    def _sync(self) -> None:
        now = self.clock()
        if self.next_sync is not None and now < self.next_sync:
            return
        self.next_sync = now + self.o.sync_period_s
        self.sync_seq = (self.sync_seq + 1) & 0xFFFF
        self.syncs_sent.add(self.sync_seq)
        self.send(MSG["TIME_SYNC"](self.master_us(now), self.sync_seq))

    def pump(self) -> None:
        self._sync()
        flush = getattr(self.link, "flush", None)
        if flush is not None:
            flush()
        data = self.link.read()
        if data:
            self.decoder.feed(data)

    def wait_for(self, pred, timeout_s: float, start_index: int = 0):
        """Poll the link until a received message satisfies ``pred`` (bounded)."""
        deadline = self.clock() + timeout_s
        i = start_index
        while True:
            self.pump()
            while i < len(self.log):
                if pred(self.log[i]):
                    return self.log[i]
                i += 1
            if self.clock() >= deadline:
                return None
            self.sleep(0.001)

    def run_for(self, seconds: float) -> None:
        deadline = self.clock() + seconds
        while self.clock() < deadline:
            self.pump()
            self.sleep(0.001)

    def add(self, rule: str, status: str, detail: str = "", node: int | None = None) -> RuleResult:
        r = RuleResult(rule, status, detail, node)
        self.rules.append(r)
        return r

    def send_frame(self, frame: bytes) -> None:
        self.link.write(frame)

    def send(self, msg, signed: bool | None = None, key: bytes | None = None, timestamp: int | None = None) -> bytes:
        """Frame and send ``msg``; signable messages are signed when a key is
        set (``signed=False`` forces unsigned; ``key`` signs with another key)."""
        if signed is None:
            signed = self.signer is not None and msg.DEF.signable
        if signed:
            if self.signer is None:
                raise ValueError("signing needs a key")
            if key is None:
                frame = self.signer.encode_signed(msg, self.encoder.seq, self.o.src, timestamp)
            else:   # a forger: another key, but a fresh timestamp
                ts = self.signer.next_timestamp(timestamp)
                frame = Signer(key, self.o.link_id).encode_signed(msg, self.encoder.seq, self.o.src, ts)
            self.encoder.seq = (self.encoder.seq + 1) & 0xFF
        else:
            frame = self.encoder.encode(msg)
        self.send_frame(frame)
        return frame

    def _pulse_id(self) -> int:
        pid = self.next_pulse_id
        self.next_pulse_id = (pid + 1) & PULSE_ID_MASK
        return pid

    def _status_for(self, node: int, pid: int):
        return lambda rx: rx.src == node and rx.msg.NAME == "COIL_STATUS" and rx.msg.pulse_id == pid

    # --------------------------------------------------------------- run
    def run(self) -> ConformReport:
        o = self.o
        self.t0 = self.clock()
        first = self.wait_for(lambda rx: rx.msg.NAME == "HEARTBEAT" and (o.node is None or rx.msg.node == o.node),
                              o.heartbeat_timeout_s)
        if first is None:
            self.add("heartbeat", FAIL, f"no HEARTBEAT within {o.heartbeat_timeout_s:g} s", o.node)
            return self._report()
        self.add("heartbeat", PASS, f"first HEARTBEAT after {first.t - self.t0:.2f} s", None)
        # every node heartbeats within heartbeat_timeout_s: listen that long to find them all
        discover = o.heartbeat_timeout_s if o.discover_s is None else o.discover_s
        listen = o.observe_s if o.node is not None else max(o.observe_s, self.t0 + discover - self.clock())
        self.run_for(listen)
        nodes = {n: hb[0].msg.role for n, hb in self.heartbeats.items() if o.node is None or n == o.node}
        for n in sorted(nodes):
            self._check_version(n)
        for n in sorted(nodes):
            if nodes[n] == ROLE_COIL_DRIVER:
                self._driver_rules(n)
            elif nodes[n] == ROLE_SENSOR:
                self._sensor_rules(n)
        if o.bench:
            self._bench_rules(nodes)
        self._garbage_rules(nodes)
        self._optional_rules(nodes)
        self._link_rules(nodes)
        for n in sorted(set(self.heartbeats) - set(nodes)):
            if o.node is None:
                self.add("discovered", SKIP, "first heard after discovery: rules not run (use --node)", n)
        return self._report()

    # --------------------------------------------------------- node rules
    def _check_version(self, n: int) -> None:
        hb = self.heartbeats[n][-1].msg
        try:
            check_peer(hb)
        except SchemaMismatchError as exc:
            self.add("heartbeat_version", FAIL, str(exc), n)
            return
        self.add("heartbeat_version", PASS, f"v{hb.proto_version} schema {hb.schema_hash:#010x}", n)

    def _pulse(self, n: int, current_ma: int | None = None, duration_us: int | None = None,
               signed=None, key=None, timestamp=None, lead_us: int | None = None, coil: int = 0):
        o = self.o
        pid = self._pulse_id()
        lead = int(o.lead_ms * 1000) if lead_us is None else lead_us
        start = (self.master_us() + lead) // BUS_START_LSB_US * BUS_START_LSB_US   # on the bus form's 8 us grid
        dur = int(o.pulse_ms * 1000) if duration_us is None else duration_us
        cur = o.pulse_current_ma if current_ma is None else current_ma
        cmd = MSG["COIL_PULSE_CMD"](coil, pid, cur, start, dur)
        mark = len(self.log)
        frame = self.send(cmd, signed=signed, key=key, timestamp=timestamp)
        return cmd, mark, frame

    def _await_status(self, n: int, cmd, mark: int, executed_expected: bool):
        o = self.o
        pulse_s = max(0.0, (cmd.start_us + min(cmd.duration_us, 1_000_000) - self.master_us()) * 1e-6)
        timeout = pulse_s + (o.answer_timeout_s if executed_expected else o.silence_s)
        return self.wait_for(self._status_for(n, cmd.pulse_id), timeout, mark)

    def _judge_pulse(self, n: int, cmd, rx) -> tuple[str, str]:
        o = self.o
        if rx is None:
            hint = "" if self.signer else " (if the node requires signed commands, pass a key)"
            return FAIL, f"no COIL_STATUS for pulse {cmd.pulse_id}{hint}"
        st = rx.msg
        if st.faults:
            return FAIL, f"COIL_STATUS faults {st.faults:#04x} for a valid command"
        problems = []
        if abs(st.start_us - cmd.start_us) > o.edge_tolerance_us:
            problems.append(f"start {st.start_us - cmd.start_us:+d} us off")
        if abs((st.end_us - st.start_us) - cmd.duration_us) > o.edge_tolerance_us:
            problems.append(f"duration {st.end_us - st.start_us} us for {cmd.duration_us} us")
        end_local = self.local_of_master(st.end_us)
        if rx.t < end_local - o.edge_tolerance_us * 1e-6 - 0.005:
            problems.append(f"status arrived {end_local - rx.t:.3f} s before the pulse ended")
        want = cmd.current_ma
        if want and not (st.current_ma * want > 0 and 0.5 <= st.current_ma / want <= 1.2):
            problems.append(f"current {st.current_ma * CURRENT_LSB_A:.3f} A for {want * CURRENT_LSB_A:.3f} A")
        if problems:
            return FAIL, "; ".join(problems)
        return PASS, (f"pulse {cmd.pulse_id}: {st.current_ma * CURRENT_LSB_A:.3f} A, "
                      f"{st.end_us - st.start_us} us, status {rx.t - end_local:+.3f} s after the end")

    def _driver_rules(self, n: int) -> None:
        o = self.o
        cmd, mark, _ = self._pulse(n)
        rx = self._await_status(n, cmd, mark, True)
        self.add("pulse_status", *self._judge_pulse(n, cmd, rx), node=n)
        for rule, kw, what in (("refuse_over_current", {"current_ma": o.over_current_ma},
                                f"{o.over_current_ma * CURRENT_LSB_A:g} A"),
                               ("refuse_too_long", {"duration_us": o.too_long_us},
                                f"{o.too_long_us / 1e6:g} s")):
            cmd, mark, _ = self._pulse(n, **kw)
            rx = self.wait_for(self._status_for(n, cmd.pulse_id), o.answer_timeout_s, mark)
            if rx is None:
                self.add(rule, FAIL, f"no COIL_STATUS for a {what} command", n)
            elif rx.msg.faults & COIL_FAULT_REFUSED:
                self.add(rule, PASS, f"{what} refused, faults {rx.msg.faults:#04x}", n)
            else:
                self.add(rule, FAIL, f"{what} command not refused (faults {rx.msg.faults:#04x})", n)
        if self.signer is None:
            for rule in ("signed_accepted", "unsigned_rejected", "forged_rejected", "replay_rejected"):
                self.add(rule, SKIP, "no key given", n)
            return
        self._signing_rules(n)

    def _not_executed(self, n: int, cmd, mark: int):
        """None if no (non-refused) COIL_STATUS for cmd arrived, else that status."""
        rx = self._await_status(n, cmd, mark, False)
        if rx is not None and rx.msg.faults & COIL_FAULT_REFUSED:
            return None
        return rx

    def _signing_rules(self, n: int) -> None:
        # a correctly signed command runs
        cmd, mark, good_frame = self._pulse(n)
        rx = self._await_status(n, cmd, mark, True)
        st, detail = self._judge_pulse(n, cmd, rx)
        self.add("signed_accepted", st, detail, n)
        # unsigned
        cmd, mark, _ = self._pulse(n, signed=False)
        rx = self._not_executed(n, cmd, mark)
        self.add("unsigned_rejected", PASS if rx is None else FAIL,
                 "unsigned command ignored" if rx is None else "node executed an unsigned COIL_PULSE_CMD", n)
        # forged: another key
        wrong = bytes(b ^ 0x5A for b in self.o.key)
        cmd, mark, _ = self._pulse(n, signed=True, key=wrong)
        rx = self._not_executed(n, cmd, mark)
        self.add("forged_rejected", PASS if rx is None else FAIL,
                 "forged signature ignored" if rx is None else "node executed a command signed with another key", n)
        # replay: the same signed frame twice, and a new command with an old timestamp
        cmd, mark, frame = self._pulse(n, lead_us=int(self.o.lead_ms * 3000))
        self.send_frame(frame)
        old_ts = self.signer.last_timestamp
        first = self._await_status(n, cmd, mark, True)
        problems = []
        if first is None or first.msg.faults:
            problems.append("the original signed command was not executed")
        else:
            later = [rx for rx in self.log[mark:] if self._status_for(n, cmd.pulse_id)(rx)
                     and not rx.msg.faults & COIL_FAULT_REFUSED]
            if len(later) > 1:
                problems.append("a replayed frame was executed again")
        cmd2, mark2, _ = self._pulse(n, signed=True, timestamp=old_ts)
        if self._not_executed(n, cmd2, mark2) is not None:
            problems.append("a command with a not-newer timestamp was executed")
        self.add("replay_rejected", FAIL if problems else PASS,
                 "; ".join(problems) if problems else "replayed frame and stale timestamp ignored", n)

    def _sensor_rules(self, n: int) -> None:
        o = self.o
        # samples after the node synchronised (before, its stamps may be on its own clock)
        synced_at = next((r.t for r in self.log if r.src == n and r.msg.NAME == "TIME_SYNC_REPLY"), None)
        mags = [rx for rx in self.log if rx.src == n and rx.msg.NAME == "MAG_SAMPLE"
                and (synced_at is None or rx.t > synced_at)]
        if len(mags) < 3:
            self.add("mag_stream", FAIL, f"{len(mags)} MAG_SAMPLE in {o.observe_s:g} s", n)
            self.add("mag_timestamps", SKIP, "too few samples", n)
            return
        ts = np.array([rx.msg.t_us for rx in mags], dtype=np.int64)
        d = np.diff(ts)
        if np.all(d > 0):
            self.add("mag_timestamps", PASS, f"{len(ts)} samples, strictly increasing", n)
        else:
            k = int(np.argmax(d <= 0))
            self.add("mag_timestamps", FAIL, f"t_us goes from {ts[k]} to {ts[k + 1]}", n)
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
        self.add("mag_stream", FAIL if problems else PASS,
                 "; ".join(problems) if problems else
                 f"{stamp_rate:.1f} Hz by time stamps, {arrival_rate:.1f} Hz arriving", n)
        self._grid_rule(n, rate)

    def _late_sync_phase(self, seconds: float, on_time: int = 5) -> int:
        """Broadcast every ``late_sync_period_s``: ``on_time`` broadcasts on time (a node still
        acquiring may step its clock), then for ``seconds`` every other one written ``late_sync_us``
        behind; returns the log index where the late broadcasts began."""
        o = self.o
        mark = len(self.log)
        end = None
        nxt, k = self.clock(), 0
        while end is None or self.clock() < end:
            self.pump()
            now = self.clock()
            if now >= nxt:
                self.sync_seq = (self.sync_seq + 1) & 0xFFFF
                self.syncs_sent.add(self.sync_seq)
                late = o.late_sync_us if k >= on_time and (k - on_time) % 2 else 0
                if k == on_time:
                    mark, end = len(self.log), now + seconds
                self.send(MSG["TIME_SYNC"](self.master_us(now) - late, self.sync_seq))
                nxt, k = now + o.late_sync_period_s, k + 1
            self.sleep(0.001)
        return mark

    def _grid_rule(self, n: int, rate_hz: float) -> None:
        o = self.o
        mark = self._late_sync_phase(o.grid_observe_s)
        ts = np.array([rx.msg.t_us for rx in self.log[mark:] if rx.src == n and rx.msg.NAME == "MAG_SAMPLE"],
                      dtype=np.int64)
        if len(ts) < 3 or rate_hz <= 0:
            self.add("mag_grid", FAIL, f"{len(ts)} MAG_SAMPLE while the broadcasts came late", n)
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
        self.add("mag_grid", FAIL if worst > o.grid_tolerance_us else PASS, detail, n)

    # ------------------------------------------------------------ bench mode
    def _bench_rules(self, nodes: dict) -> None:
        drivers = [n for n in sorted(nodes) if nodes[n] == ROLE_COIL_DRIVER]
        sensors = [n for n in sorted(nodes) if nodes[n] == ROLE_SENSOR]
        if not drivers or not sensors:
            self.add("bench_pulse", FAIL, "bench mode needs a coil driver and a sensor on the link", None)
            return
        for s in sensors:
            self._bench_pulse_rule(drivers[0], s)

    def _bench_samples(self, s: int, lo: int, hi: int) -> tuple[np.ndarray, np.ndarray]:
        rx = [r.msg for r in self.log if r.src == s and r.msg.NAME == "MAG_SAMPLE" and lo <= r.msg.t_us <= hi]
        t = np.array([m.t_us for m in rx], dtype=np.int64)
        B = np.array([[m.x, m.y, m.z] for m in rx], dtype=float).reshape(-1, 3)
        flip = np.array([m.flip & 1 for m in rx], dtype=np.int64)
        return t, B, flip

    def _bench_pulse_rule(self, d: int, s: int) -> None:
        o = self.o
        rate = o.mag_rate_hz or 120.0
        P = 1e6 / rate
        dur = int(o.bench_pulse_ms * 1000)
        problems, rise, fall, amps = [], [-1e9, 1e9], [-1e9, 1e9], []
        for i in range(o.bench_pulses):
            # the start dithered against the sensor's sample grid by i / bench_pulses of a period,
            # so that the samples bracket the edges to P / bench_pulses over the pulses
            grid = [r.msg.t_us for r in self.log[-400:] if r.src == s and r.msg.NAME == "MAG_SAMPLE"]
            earliest = self.master_us() + int(o.lead_ms * 1000)
            if grid:
                k = int(np.ceil((earliest - grid[-1]) / P))
                start = grid[-1] + int(round((k + i / o.bench_pulses) * P))
            else:
                start = earliest
            self.run_for(0.0)
            cmd, mark, _ = self._pulse(d, current_ma=o.bench_current_ma, duration_us=dur,
                                       lead_us=start - self.master_us(), coil=i % o.bench_coils)
            st = self._await_status(d, cmd, mark, True)
            self.run_for(0.05)                         # the trailing quiet samples
            if st is None or st.msg.faults:
                problems.append(f"pulse {i}: " + ("no COIL_STATUS" if st is None else
                                                  f"COIL_STATUS faults {st.msg.faults:#04x}"))
                continue
            t0, t1 = cmd.start_us, cmd.start_us + dur
            t, B, flip = self._bench_samples(s, t0 - 35_000, t1 + 38_000)
            pre = (t >= t0 - 35_000) & (t <= t0 - 2_000)
            post = t >= t1 + o.fall_us
            # the set/reset offset changes sign with the flip bit: one quiet baseline per flip state
            base = np.zeros_like(B)
            for f in (0, 1):
                q = (pre | post) & (flip == f)
                base[flip == f] = B[q].mean(axis=0) if q.any() else np.nan
            keep = ~np.isnan(base[:, 0])
            t, B, base, pre, post = t[keep], B[keep], base[keep], pre[keep], post[keep]
            win = (t >= t0 + o.settle_us) & (t <= t1 - o.guard_us)
            if pre.sum() < 2 or win.sum() < 2 or post.sum() < 1:
                problems.append(f"pulse {i}: {int(pre.sum())} quiet and {int(win.sum())} in-window samples")
                continue
            dB = np.linalg.norm(B - base, axis=1)
            A = float(np.median(dB[win]))
            noise = float(np.std(dB[pre])) + 1.0
            amps.append(A)
            if A < 10.0 * noise:
                problems.append(f"pulse {i}: no field in the window ({A:.0f} LSB against {noise:.0f} LSB of noise)")
                continue
            if np.any(np.abs(dB[win] - A) > 0.1 * A):
                problems.append(f"pulse {i}: the field is not flat over the window (the node applies it late "
                                f"or early?)")
            if np.any(dB[post] > 0.05 * A) or np.any(dB[pre] > 0.05 * A):
                problems.append(f"pulse {i}: field in the quiet samples around the pulse")
            on = dB > 0.5 * A
            rel = t - t0
            # the rise edge lies between the last sample off and the first sample on (relative to the start)
            first_on = int(np.argmax(on))
            if on[first_on] and first_on > 0:
                rise = [max(rise[0], rel[first_on - 1]), min(rise[1], rel[first_on])]
            last_on = len(on) - 1 - int(np.argmax(on[::-1]))
            if last_on + 1 < len(on):
                fall = [max(fall[0], rel[last_on] - dur), min(fall[1], rel[last_on + 1] - dur)]
        if problems:
            self.add("bench_pulse", FAIL, "; ".join(problems[:3]), s)
            return
        detail = (f"{o.bench_pulses} pulses of {o.bench_current_ma * CURRENT_LSB_A:g} A for {dur} us on node {d}: "
                  f"field {np.median(amps):.0f} LSB; rise edge at {rise[0]:+.0f}..{rise[1]:+.0f} us of the commanded "
                  f"start (margin {o.settle_us - rise[1]:.0f} us to the window), fall edge at {fall[0]:+.0f}.."
                  f"{fall[1]:+.0f} us of the commanded end (margin {fall[0] + o.guard_us:.0f} us)")
        self.add("bench_pulse", PASS, detail, s)

    # ------------------------------------------------------------ garbage
    def _garbage_serial(self) -> bytes:
        rng = self.rng
        good = encode_frame(MSG["TIME_SYNC"](123_456, 0xFFFF), 0, self.o.src)
        parts = [bytes(rng.integers(0, 256, 300, dtype=np.uint8)) + b"\x00"]
        flipped = bytearray(good)
        i = int(rng.integers(0, len(flipped) - 1))
        flipped[i] ^= 0x10
        if b"\x00" in flipped[:-1]:
            flipped[i] ^= 0x30
        parts.append(bytes(flipped))
        parts.append(good[: len(good) // 2] + b"\x00")
        parts.append(bytes(rng.integers(1, 256, 3000, dtype=np.uint8)) + b"\x00")   # longer than any frame
        raw = bytearray(build_frame(MSG["TIME_SYNC"](0, 0), 0, self.o.src))
        raw[0] += 1                                                                    # wrong length byte
        parts.append(cobs_encode(bytes(raw)) + b"\x00")
        raw = bytearray(build_frame(MSG["TIME_SYNC"](0, 0), 0, self.o.src))
        raw[4] = 0xEE                                                                  # unknown id
        parts.append(cobs_encode(bytes(raw)) + b"\x00")
        return b"".join(parts)

    def _garbage_can(self) -> int:
        import can

        from .can import (_MSG_BY_BASE, BASE_ID, FUNCTION_MASK, NODE_MASK, build_pdu, can_id, direct_size, ext_id,
                          segment)

        bus = self.link.bus
        rng = self.rng
        src = self.o.src & NODE_MASK
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

    def _garbage_rules(self, nodes: dict) -> None:
        if not nodes:
            return
        if hasattr(self.link, "bus") and hasattr(self.link, "codec"):
            what = f"{self._garbage_can()} bad CAN frames"
        else:
            g = self._garbage_serial()
            self.send_frame(g)
            what = f"{len(g)} bytes of garbage and bad frames"
        self.run_for(0.05)
        for n in sorted(nodes):
            role = nodes[n]
            if role == ROLE_COIL_DRIVER:
                cmd, mark, _ = self._pulse(n)
                rx = self._await_status(n, cmd, mark, True)
                ok = rx is not None and not rx.msg.faults
                self.add("survives_garbage", PASS if ok else FAIL,
                         f"after {what}: pulse " + ("answered" if ok else "not answered"), n)
            else:
                name = "MAG_SAMPLE" if role == ROLE_SENSOR else "HEARTBEAT"
                mark = len(self.log)
                timeout = 0.5 if role == ROLE_SENSOR else self.o.heartbeat_timeout_s
                rx = self.wait_for(lambda r: r.src == n and r.msg.NAME == name, timeout, mark)
                self.add("survives_garbage", PASS if rx else FAIL,
                         f"after {what}: {name} " + ("still arriving" if rx else "stopped"), n)

    # ----------------------------------------------------------- optional
    def _optional_rules(self, nodes: dict) -> None:
        """CONFIG_GET to every node, one wait for all the answers."""
        if not nodes:
            return
        mark = len(self.log)
        for n in sorted(nodes):
            self.send(MSG["CONFIG_GET"](n, 0))
        self.wait_for(lambda r: False, self.o.optional_wait_s, mark)
        for n in sorted(nodes):
            rx = next((r for r in self.log[mark:] if r.src == n and r.msg.NAME == "CONFIG_ACK"), None)
            if rx is None:
                self.add("config_get", SKIP, "no CONFIG_ACK (configuration is optional)", n)
            else:
                self.add("config_get", PASS, f"CONFIG_ACK key {rx.msg.key} result {rx.msg.result}", n)

    def _time_sync_rule(self, n: int) -> None:
        replies = [r for r in self.log if r.src == n and r.msg.NAME == "TIME_SYNC_REPLY"]
        ours = [r for r in replies if r.msg.sync_seq in self.syncs_sent]
        if not ours:
            self.add("time_sync", FAIL, f"no TIME_SYNC_REPLY to {len(self.syncs_sent)} TIME_SYNC"
                     + (f" ({len(replies)} replies with unknown sync_seq)" if replies else ""), n)
            return
        last = ours[-1].msg
        states = [h.msg.state for h in self.heartbeats.get(n, [])]
        self.add("time_sync", PASS, f"{len(ours)} replies to {len(self.syncs_sent)} TIME_SYNC; last offset "
                 f"{last.offset_us} us, drift {last.drift_ppb} ppb; heartbeat states {sorted(set(states))}", n)

    # --------------------------------------------------------- link rules
    def _link_rules(self, nodes: dict) -> None:
        o = self.o
        if nodes:   # observe long enough to judge the heartbeat period of every node
            need = max(self.heartbeats[n][0].t for n in nodes) + o.heartbeat_timeout_s + 0.05 - self.clock()
            if need > 0:
                self.run_for(need)
        end = self.clock()
        for n in sorted(nodes):
            hbs = self.heartbeats[n]
            times = [hbs[0].t] + [h.t for h in hbs[1:]] + [end]
            gaps = np.diff(times)
            if end - hbs[0].t < o.heartbeat_timeout_s:
                self.add("heartbeat_period", SKIP, "session too short", n)
            elif gaps.max() > o.heartbeat_timeout_s:
                self.add("heartbeat_period", FAIL, f"{gaps.max():.2f} s without HEARTBEAT", n)
            else:
                self.add("heartbeat_period", PASS, f"{len(hbs)} heartbeats, longest gap {gaps.max():.2f} s", n)
            self._time_sync_rule(n)
            wrong = [rx for rx in self.log if rx.msg.NAME == "HEARTBEAT" and rx.msg.node == n and rx.src != n]
            self.add("src_matches_node", FAIL if wrong else PASS,
                     f"HEARTBEAT of node {n} sent with src {wrong[0].src}" if wrong else "src == node", n)
        d = self.decoder
        can_bad = 0
        re = getattr(self.link, "reassembler", None)
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
        self.add("frames_valid", FAIL if bad else PASS, detail)
        # on CAN the reassembler judges the gaps: a single frame carries no seq (it is numbered on
        # receipt), so only consecutive PDUs of a sender show one
        gaps = re.seq_gaps if re is not None else d.seq_gaps
        self.add("sequence", FAIL if gaps else PASS,
                 f"{gaps} gaps in per-sender sequence numbers" if gaps else "no gaps")

    def _report(self) -> ConformReport:
        rep = ConformReport(self.transport)
        rep.duration_s = self.clock() - self.t0
        for n, hb in sorted(self.heartbeats.items()):
            if self.o.node is None or n == self.o.node:
                rep.nodes[n] = role_name(hb[-1].msg.role)
        span = max(rep.duration_s, 1e-9)
        names: dict[str, dict] = {}
        for rx in self.log:
            st = names.setdefault(rx.msg.NAME, {"count": 0, "from": set(), "bad": 0, "rate_hz": 0.0})
            st["count"] += 1
            st["from"].add(rx.src)
        bad = dict(self.decoder.bad_by_message)
        re = getattr(self.link, "reassembler", None)
        if re is not None:
            for k, v in re.bad_by_message.items():
                bad[k] = bad.get(k, 0) + v
        for name, v in bad.items():
            names.setdefault(name, {"count": 0, "from": set(), "bad": 0, "rate_hz": 0.0})["bad"] += v
        for name, st in names.items():
            st["from"] = sorted(st["from"])
            st["rate_hz"] = round(st["count"] / span, 2)
        rep.messages = dict(sorted(names.items()))
        rep.rules = self.rules
        rep.counters = {"decoder": self.decoder.counters()}
        if re is not None:
            rep.counters["can"] = re.counters()
        return rep


def run_conformance(link, options: ConformOptions | None = None, transport: str = "link") -> ConformReport:
    """Run the whole suite on ``link``; returns the report."""
    return Conformance(link, options, transport).run()
