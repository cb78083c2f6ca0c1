"""Time synchronisation, master side: ``TIME_SYNC`` broadcasts and the
bookkeeping of the nodes' ``TIME_SYNC_REPLY`` answers.

The firmware's clock is the master clock. It broadcasts ``TIME_SYNC``
(master time at transmission, plus a configured constant link latency, and a
sequence number) every ``period_us`` and on request: the supervisor asks for
one right before and one right after each burst of pulses, so a clock step
of any node during a burst shows in the replies before the burst's pose is
computed. Each node fits offset and drift of its own clock to the broadcasts
(thesis ``002`` ch. 7: synchronisation over the bus) and answers with its
counter at reception and its current estimate of offset (node - master) and
drift.

From consecutive replies of a node the master predicts the next offset
(``offset + drift * dt``); a reply further than ``step_threshold_us`` from the
prediction means the node's clock stepped: :meth:`on_reply` returns True and
the supervisor reports ``EVT_CLOCK_STEP``. The first replies of a node, and
of a node that came back (rebooted), are its acquisition and are not judged.
The round-trip time of each answered broadcast is kept (``rtt_us``,
``rtt_min_us``) as a measure of the link latency.

Fixed-size state, allocated in ``__init__``; no numpy in the per-tick path.
"""
from __future__ import annotations

from coiltrack.protocol import MSG

TimeSyncMsg = MSG["TIME_SYNC"]

_HISTORY = 16        # broadcasts remembered for round-trip times
_REQUESTS = 6        # pending requested broadcast times
_REPLIES = 5         # reply arrival times remembered per node
_NEVER = 1 << 62     # no request pending
_ACQUIRE = 4         # replies of a (re)acquiring node not judged for steps


class TimeSyncMaster:
    def __init__(self, node_ids, period_us: int = 250_000, latency_us: int = 0,
                 step_threshold_us: int = 1500):
        self.period_us = int(period_us)
        self.latency_us = int(latency_us)
        self.step_threshold_us = int(step_threshold_us)
        self.next_us = 0
        self.seq = 0
        self._sent_seq = [-1] * _HISTORY
        self._sent_t = [0] * _HISTORY
        self._req = [-1] * _REQUESTS           # requested broadcast times (-1: free)
        self.due_us = 0                       # the next broadcast: min(next_us, the requests)
        self.node_ids = tuple(int(n) for n in node_ids)
        n = len(self.node_ids)
        self._slot = {nid: i for i, nid in enumerate(self.node_ids)}
        self.have = [False] * n
        self.last_reply_us = [0] * n           # master time the last reply arrived
        self._hist = [[0] * _REPLIES for _ in range(n)]    # arrival times of the last replies
        self._hk = [0] * n
        self.acquired = [0] * n                # replies since (re)acquisition
        self.offset_us = [0] * n               # node's reported offset (node - master)
        self.drift_ppb = [0] * n
        self.rtt_us = [0] * n
        self.rtt_min_us = [0] * n
        self.replies = [0] * n
        self.steps = [0] * n
        self.sent = 0

    #: the per-node lists the compiled supervisor kernel shares (:meth:`use_arrays`), in ``ct_supervise.h``'s order
    NODE_LISTS = ("have", "last_reply_us", "_hk", "acquired", "offset_us", "drift_ppb", "rtt_us", "rtt_min_us",
                  "replies")

    def use_arrays(self, view) -> None:
        """Keep the state a reply changes in ``view`` (int64 items laid out as ``ct_supervise.h``
        says: the sent sequence numbers and times, the per-node lists, the reply history), shared
        with the compiled supervisor kernel: the same values, the lists become views of it."""
        n = len(self.node_ids)
        at = 0
        for name, k in (("_sent_seq", _HISTORY), ("_sent_t", _HISTORY)) + tuple((m, n) for m in self.NODE_LISTS):
            old = getattr(self, name)
            v = view[at:at + k]
            for j in range(k):
                v[j] = old[j]
            setattr(self, name, v)
            at += k
        rows = []
        for i in range(n):
            v = view[at:at + _REPLIES]
            for j in range(_REPLIES):
                v[j] = self._hist[i][j]
            rows.append(v)
            at += _REPLIES
        self._hist = rows

    def slot(self, node: int) -> int:
        return self._slot.get(node, -1)

    def forget(self, node: int) -> None:
        """The node restarted: its next replies re-acquire (no step is judged on them)."""
        i = self._slot.get(node, -1)
        if i >= 0:
            self.have[i] = False
            self.acquired[i] = 0

    def first_suspect_us(self, i: int, now_us: int) -> int:
        """Arrival of the reply ``_REPLIES - 1`` replies back: a forward step a node confirms
        with three broadcasts happened before the first of them."""
        if i < 0:
            return now_us
        return self._hist[i][self._hk[i]] or now_us

    def kick(self) -> None:
        """Broadcast at the next tick (a node came back)."""
        self.next_us = 0
        self.due_us = 0

    def request(self, at_us: int) -> None:
        """Broadcast at (or right after) master time ``at_us`` besides the periodic ones."""
        r = self._req
        if at_us < self.due_us:
            self.due_us = at_us
        for i in range(_REQUESTS):
            if r[i] < 0:
                r[i] = at_us
                return
        # full: replace the latest request with the earlier of the two
        j = 0
        for i in range(1, _REQUESTS):
            if r[i] > r[j]:
                j = i
        if at_us < r[j]:
            r[j] = at_us

    def step(self, now_us: int, send, sync=None) -> bool:
        """Send a broadcast when one is due (through ``send(msg)``, or ``sync(master_time_us,
        sync_seq)`` when given: ``Transmitter.time_sync``, the same frame, built on the compiled core
        without the message); return True when it did. Nothing is due before ``_due_us`` (the
        periodic time and the requests, kept as they are set)."""
        if now_us < self.due_us:
            return False
        due = now_us >= self.next_us
        r = self._req
        req = _NEVER                           # the earliest request still pending
        for i in range(_REQUESTS):
            if 0 <= r[i] <= now_us:
                due = True
                r[i] = -1
            elif r[i] > now_us and r[i] < req:
                req = r[i]
        if not due:
            self.due_us = req if req < self.next_us else self.next_us
            return False
        seq = self.seq
        k = seq % _HISTORY
        self._sent_seq[k] = seq
        self._sent_t[k] = now_us
        if sync is None:
            send(TimeSyncMsg(now_us + self.latency_us, seq))
        else:
            sync(now_us + self.latency_us, seq)
        self.seq = (seq + 1) & 0xFFFF
        self.sent += 1
        self.next_us = now_us + self.period_us
        self.due_us = req if req < self.next_us else self.next_us
        return True

    def acquiring(self, i: int) -> bool:
        """Whether node slot ``i`` is still (re)acquiring: fewer than ``_ACQUIRE`` replies booked
        since (re)acquisition. Asked before :meth:`on_reply` books a reply, it says whether that
        reply answers one of the node's first ``_ACQUIRE`` broadcasts, whose clock corrections the
        node applies as steps (its stamps are not yet on one time base)."""
        return 0 <= i < len(self.acquired) and self.acquired[i] < _ACQUIRE

    def on_reply(self, msg, now_us: int) -> bool:
        """Book a TIME_SYNC_REPLY; return True when it shows a clock step of that node."""
        i = self._slot.get(msg.node, -1)
        if i < 0:
            return False
        k = msg.sync_seq % _HISTORY
        if self._sent_seq[k] == msg.sync_seq:
            rtt = now_us - self._sent_t[k]
            self.rtt_us[i] = rtt
            if self.rtt_min_us[i] == 0 or rtt < self.rtt_min_us[i]:
                self.rtt_min_us[i] = rtt
        stepped = False
        if self.have[i] and self.acquired[i] >= _ACQUIRE:
            dt = now_us - self.last_reply_us[i]
            pred = self.offset_us[i] + self.drift_ppb[i] * dt // 1_000_000_000
            if abs(msg.offset_us - pred) > self.step_threshold_us:
                stepped = True
                self.steps[i] += 1
        self.have[i] = True
        self.acquired[i] += 1
        self.last_reply_us[i] = now_us
        k = self._hk[i]
        self._hist[i][k] = now_us
        self._hk[i] = (k + 1) % _REPLIES
        self.offset_us[i] = msg.offset_us
        self.drift_ppb[i] = msg.drift_ppb
        self.replies[i] += 1
        return stepped
