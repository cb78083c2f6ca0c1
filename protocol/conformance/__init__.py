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
    strictly increasing ``t_us``, both over ``observe_s`` of samples after the node's
    acquisition (its first four TIME_SYNC replies; ``node_rules.acquire``); ``mag_grid`` every interval between
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

import time

from ..schema import ROLE_COIL_DRIVER, ROLE_SENSOR
from .bench_rules import bench_rules
from .link_rules import garbage_rules, link_rules, optional_rules
from .node_rules import check_version, driver_rules, sensor_rules
from .results import FAIL, MASTER_EPOCH_US, PASS, RULES, SKIP, ConformOptions, ConformReport, RuleResult
from .session import Session

__all__ = ["FAIL", "MASTER_EPOCH_US", "PASS", "RULES", "SKIP", "ConformOptions", "ConformReport", "Conformance",
           "RuleResult", "Session", "run_conformance"]


class Conformance:
    """Run the suite on ``link`` (a byte Port). ``transport`` is for display; ``clock`` and ``sleep``
    are injected (monotonic seconds)."""

    def __init__(self, link, options: ConformOptions | None = None, transport: str = "link",
                 clock=time.monotonic, sleep=time.sleep):
        self.session = Session(link, options, transport, clock, sleep)

    def run(self) -> ConformReport:
        s = self.session
        o = s.o
        s.start()
        first = s.wait_for(lambda rx: rx.msg.NAME == "HEARTBEAT" and (o.node is None or rx.msg.node == o.node),
                              o.heartbeat_timeout_s)
        if first is None:
            s.add("heartbeat", FAIL, f"no HEARTBEAT within {o.heartbeat_timeout_s:g} s", o.node)
            return s.report()
        s.add("heartbeat", PASS, f"first HEARTBEAT after {first.t - s.t0:.2f} s", None)
        # every node heartbeats within heartbeat_timeout_s: listen that long to find them all
        discover = o.heartbeat_timeout_s if o.discover_s is None else o.discover_s
        listen = o.observe_s if o.node is not None else max(o.observe_s, s.t0 + discover - s.clock())
        s.run_for(listen)
        nodes = {n: hb[0].msg.role for n, hb in s.heartbeats.items() if o.node is None or n == o.node}
        for n in sorted(nodes):
            check_version(s, n)
        for n in sorted(nodes):
            if nodes[n] == ROLE_COIL_DRIVER:
                driver_rules(s, n)
            elif nodes[n] == ROLE_SENSOR:
                sensor_rules(s, n)
        if o.bench:
            bench_rules(s, nodes)
        garbage_rules(s, nodes)
        optional_rules(s, nodes)
        link_rules(s, nodes)
        for n in sorted(set(s.heartbeats) - set(nodes)):
            if o.node is None:
                s.add("discovered", SKIP, "first heard after discovery: rules not run (use --node)", n)
        return s.report()


def run_conformance(link, options: ConformOptions | None = None, transport: str = "link") -> ConformReport:
    """Run the whole suite on ``link``; returns the report."""
    return Conformance(link, options, transport).run()
