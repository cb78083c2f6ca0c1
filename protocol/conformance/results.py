"""The suite's options, its rules and its report (:mod:`coiltrack.protocol.conformance`)."""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field


from ..schema import NODE_FIRMWARE

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
    "mag_timestamps": "MAG_SAMPLE t_us strictly increasing (after the node acquired the master time)",
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
