"""The tester's side of a conformance session: the link, the master clock, the log of what
arrived, and sending (:mod:`coiltrack.protocol.conformance`)."""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ..codec import MSG
from ..errors import ProtocolError
from ..framing import FrameDecoder, FrameEncoder, cobs_decode
from ..peer import role_name
from ..schema import (BUS_START_LSB_US, BY_ID, PULSE_ID_MASK, STAMP_FLIP, STAMP_MASK, STAMP_SATURATED, unwrap_stamp)
from ..signing import Signer
from .results import MASTER_EPOCH_US, ConformOptions, ConformReport, RuleResult


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


class Session:
    """A session on ``link`` (a byte Port): plumbing shared by every rule; ``transport`` is for display."""

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

    def sync(self) -> None:
        now = self.clock()
        if self.next_sync is not None and now < self.next_sync:
            return
        self.next_sync = now + self.o.sync_period_s
        self.send(MSG["TIME_SYNC"](self.master_us(now), self.next_sync_seq()))

    def next_sync_seq(self) -> int:
        """The next TIME_SYNC sequence number, remembered as sent."""
        self.sync_seq = (self.sync_seq + 1) & 0xFFFF
        self.syncs_sent.add(self.sync_seq)
        return self.sync_seq

    def start(self) -> None:
        """The master clock's zero: now."""
        self.t0 = self.clock()

    def pump(self) -> None:
        self.sync()
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
            self.encoder.take_seq()
        else:
            frame = self.encoder.encode(msg)
        self.send_frame(frame)
        return frame

    def pulse_id(self) -> int:
        pid = self.next_pulse_id
        self.next_pulse_id = (pid + 1) & PULSE_ID_MASK
        return pid

    def status_for(self, node: int, pid: int):
        return lambda rx: rx.src == node and rx.msg.NAME == "COIL_STATUS" and rx.msg.pulse_id == pid

    def pulse(self, n: int, current_ma: int | None = None, duration_us: int | None = None,
               signed=None, key=None, timestamp=None, lead_us: int | None = None, coil: int = 0):
        o = self.o
        pid = self.pulse_id()
        lead = int(o.lead_ms * 1000) if lead_us is None else lead_us
        start = (self.master_us() + lead) // BUS_START_LSB_US * BUS_START_LSB_US   # on the bus form's 8 us grid
        dur = int(o.pulse_ms * 1000) if duration_us is None else duration_us
        cur = o.pulse_current_ma if current_ma is None else current_ma
        cmd = MSG["COIL_PULSE_CMD"](coil, pid, cur, start, dur)
        mark = len(self.log)
        frame = self.send(cmd, signed=signed, key=key, timestamp=timestamp)
        return cmd, mark, frame

    def await_status(self, n: int, cmd, mark: int, executed_expected: bool):
        o = self.o
        pulse_s = max(0.0, (cmd.start_us + min(cmd.duration_us, 1_000_000) - self.master_us()) * 1e-6)
        timeout = pulse_s + (o.answer_timeout_s if executed_expected else o.silence_s)
        return self.wait_for(self.status_for(n, cmd.pulse_id), timeout, mark)

    def report(self) -> ConformReport:
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
