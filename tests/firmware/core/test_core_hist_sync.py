"""The fusion filter's pose histories copied in part (``estimate/fusion_output.py``
``PoseHistory.rewind_shadow``, ``commit``; compiled: ``core/src/hist_sync.c`` ``ct_hist_sync``).

The independent reference is the whole copy: two plain ``Ring``s kept with ``Ring.copy_from`` and
``Ring.drop_newer_than``, the operations the partial copy replaces. Over seeded sequences of what
the filter does to its histories (the live ring's pushes, a rewind at a recent time, the replay's
pushes onto the shadow, its commit, a replay that is abandoned, a restart that clears the shadow,
more pushes than the capacity between two copies), the Python reference and the compiled core
must leave both rings' times, rows, heads and counts the same bytes as the whole copies. A second
test shows that the copies are partial: a slot neither ring pushed is not copied."""
import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.estimate.fusion_output import MK_VALID, PoseHistory
from coiltrack.firmware.estimate.fusion_state import HIST_FIELDS
from coiltrack.firmware.ring import Ring

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")
COMPILED = core.load("compiled")


class _Whole:
    """The reference: the two histories with whole copies."""

    def __init__(self, cap):
        self.live = Ring(cap, HIST_FIELDS)
        self.shadow = Ring(cap, HIST_FIELDS)

    def rewind_shadow(self, t):
        self.shadow.copy_from(self.live)
        self.shadow.drop_newer_than(t)

    def commit(self):
        self.live.copy_from(self.shadow)

    def restart_shadow(self):
        self.shadow.clear()


def _push(ring, t, row):
    ring.d[ring.push(t)] = row


def _same(a, b, what):
    for name in ("live", "shadow"):
        ra, rb = getattr(a, name), getattr(b, name)
        assert ra.t.tobytes() == rb.t.tobytes(), (what, name, "t")
        assert ra.d.tobytes() == rb.d.tobytes(), (what, name, "d")
        assert (ra._head, ra._count) == (rb._head, rb._count), (what, name)


def _newest(ring):
    return int(ring.tv[ring.peek(0)]) if len(ring) else 0


@pytest.mark.parametrize("cap, seed", [(16, 1), (16, 2), (37, 3), (1024, 4)])
def test_partial_copies_leave_the_whole_copies_bytes(cap, seed):
    rng = np.random.default_rng(seed)
    hs = [_Whole(cap), PoseHistory(cap, core.PYTHON), PoseHistory(cap, COMPILED)]
    assert hs[2].commit != PoseHistory.commit.__get__(hs[2])          # the kernel's method
    t_live = 1000
    partial = 0
    big = cap if cap < 100 else 60
    for step in range(300 if cap < 100 else 80):
        # the live ring's pushes since the last copy: none, a few, about a capacity, more
        n = int(rng.choice([0, 1, 3, int(rng.integers(1, big)), cap - 1, cap, cap + 2]))
        for _ in range(n):
            t_live += int(rng.integers(900, 1100))
            row = rng.normal(size=12)
            for h in hs:
                _push(h.live, t_live, row)
        if not len(hs[0].live):
            continue
        # a rewind at a recent entry's time (or just before or after it), or before them all
        back = int(rng.integers(0, min(len(hs[0].live), 3 * big // 2) + 1))
        t_ref = _newest(hs[0].live) if back == 0 else int(hs[0].live.tv[hs[0].live.peek(back - 1)])
        t_ref += int(rng.choice([-1, 0, 0, 1]))
        restart = rng.random() < 0.05
        for h in hs:
            if restart:
                h.restart_shadow()
            else:
                h.rewind_shadow(t_ref)
        _same(hs[0], hs[1], (step, "rewind"))
        _same(hs[0], hs[2], (step, "rewind"))
        # the replay: the shadow's pushes up to the live ring's newest, the live ring pushed meanwhile
        t_sh = max(t_ref, _newest(hs[0].shadow)) if not restart else t_ref - 5000
        for _ in range(int(rng.integers(0, 4))):
            t_live += 1000
            row = rng.normal(size=12)
            for h in hs:
                _push(h.live, t_live, row)
        lost = rng.random() < 0.1
        while t_sh < t_live and not (lost and rng.random() < 0.3):
            t_sh = min(t_sh + int(rng.integers(400, 1100)), t_live)
            row = rng.normal(size=12)
            for h in hs:
                _push(h.shadow, t_sh, row)
        if lost:                         # the replay lost its samples: no commit
            continue
        partial += int(hs[1].mark[MK_VALID])
        for h in hs:
            h.commit()
        _same(hs[0], hs[1], (step, "commit"))
        _same(hs[0], hs[2], (step, "commit"))
        assert hs[1].mark.tolist() == hs[2].mark.tolist(), step
    assert partial > 20                  # most copies were partial ones


@pytest.mark.parametrize("which", ["python", "compiled"])
def test_a_slot_neither_ring_pushed_is_not_copied(which):
    """After a whole copy, 40 pushes on the live ring and 10 on the shadow: the rewind copies those
    slots (the pushes' rows arrive) and leaves every other slot alone (a value planted in the live
    ring's rows behind the rings' back stays out of the shadow), then the commit the same way back."""
    cap = 1024
    h = PoseHistory(cap, core.PYTHON if which == "python" else COMPILED)
    for i in range(cap + 100):
        h.live.d[h.live.push(1000 * i)] = float(i)
    h.rewind_shadow(1000 * (cap + 50))            # whole (no mark yet)
    assert h.mark[MK_VALID] == 1
    assert h.shadow.t.tobytes() == h.live.t.tobytes() and h.shadow.d.tobytes() == h.live.d.tobytes()
    for _ in range(10):                          # the replay
        t = int(h.shadow.tv[h.shadow.peek(0)]) + 1000
        h.shadow.d[h.shadow.push(t)] = -1.0
    for i in range(cap + 100, cap + 140):        # the live ring meanwhile
        h.live.d[h.live.push(1000 * i)] = float(i)
    far = (h.live.peek(0) + cap // 2) % cap
    h.live.d[far, 0] = 1e300                     # planted: not a push
    h.commit()
    assert h.live.d[far, 0] == 1e300             # (the commit did not overwrite it either)
    for i in range(40):
        h.live.d[h.live.push(1000 * (cap + 200 + i))] = 7.0
    h.rewind_shadow(1000 * (cap + 220))
    assert h.shadow.d[far, 0] != 1e300           # not copied
    k = h.live.peek(0)
    assert h.shadow.t[k] == h.live.t[k] and h.shadow.d[k, 0] == 7.0      # the pushed slots are
    assert len(h.shadow) == cap - 19 and int(h.shadow.tv[h.shadow.peek(0)]) == 1000 * (cap + 220)
