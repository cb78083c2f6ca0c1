"""The sensor's stamps judged after its time-sync acquisition (docs/protocol.md, "slew, do not
step": a node's first four replies may step its clock; the firmware judges its stamps afresh
after each of them).

On a loaded machine the node read the tester's first ``TIME_SYNC`` 120 ms after it was written:
the node's line then lies 120 ms behind the master (it cannot know the broadcast was late) and
its compact stamps (``MAG_PACKED``: 14 bits of 8 us, restored by the receiver within 114.7 ms
behind its clock, ``protocol.schema.unwrap_stamp``) were restored a wrap (131.072 ms) too far, until the
next broadcast, on time, stepped the line forward, as acquisition allows: the restored stamps
ran back once and ``mag_timestamps`` failed (``tests/protocol/test_conformance.py::
test_conform_command_serial`` did once under load: its stamps went from 2480640 to 2357904).
Here on injected time (the lockstep emulator), the first broadcast held back 120 ms on the link
and a broadcast every 0.3 s, so the next one comes while the stream is observed: before the
stamps were judged after acquisition, ``t_us`` went from 1302912 to 1300176 (131072 - 120000 -
8333 us back) and ``mag_timestamps`` failed; 112 ms (a lag within the stamp's 114.7 ms) passed."""
from __future__ import annotations

from coiltrack.protocol import MSG
from coiltrack.protocol.conformance import PASS, Conformance, ConformOptions
from coiltrack.protocol.framing import FrameDecoder

_SYNC = MSG["TIME_SYNC"].ID


class _HoldFirstSync:
    """The tester's end of a link whose first TIME_SYNC frame reaches the node ``hold_s`` late
    (``clock``: the lockstep's); every other frame passes at once."""

    def __init__(self, link, clock, hold_s: float):
        self.link, self.clock, self.hold_s = link, clock, hold_s
        self.held = None            # (due, frame)
        self.done = False
        self._dec = FrameDecoder()

    def _is_sync(self, frame: bytes) -> bool:
        got = self._dec.feed(frame)
        return any(m.ID == _SYNC for m in got)

    def write(self, data: bytes) -> None:
        if not self.done and self._is_sync(data):
            self.done = True
            self.held = (self.clock() + self.hold_s, bytes(data))
            return
        self.link.write(data)

    def read(self) -> bytes:
        if self.held is not None and self.clock() >= self.held[0]:
            self.link.write(self.held[1])
            self.held = None
        return self.link.read()


def test_first_broadcast_120ms_late_stamps_judged_after_acquisition(pipes, lockstep, fast):
    tester, node_side = pipes()
    ls = lockstep(node_side)

    link = _HoldFirstSync(tester, ls.now, 0.120)
    opts = ConformOptions(**dict(fast, lead_ms=200.0, answer_timeout_s=5.0, sync_period_s=0.3))
    rep = Conformance(link, opts, "in-memory serial", clock=ls.now, sleep=ls.sleep).run()
    assert link.done and link.held is None
    sensor = 16
    assert rep.result("mag_timestamps", sensor).status == PASS, rep.format()
    assert rep.result("mag_stream", sensor).status == PASS, rep.format()
    assert rep.result("mag_grid", sensor).status == PASS, rep.format()
    assert rep.ok, rep.format()
