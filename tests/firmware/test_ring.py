"""The one fixed-capacity ring (``coiltrack.firmware.ring.Ring``) against a
plain Python list model of a FIFO that forgets its oldest entries, and its
cost: no numpy allocation after construction."""
import numpy as np
import pytest

from coiltrack.firmware.ring import Ring, field_slices
from coiltrack.tools.bench.alloc import NumpyAllocationCounter, available


def _contents(r):
    return [(int(r.t[r.slot(i)]), r.d[r.slot(i)].tolist()) for i in range(len(r))]


def test_named_rows_and_bad_arguments():
    r = Ring(5, (("F", 3), ("W", 2), ("S", 1)))
    assert (r.F, r.W, r.S) == (slice(0, 3), slice(3, 5), slice(5, 6))
    assert r.d.shape == (5, 6) and r.t.dtype == np.int64 and r.fields == ("F", "W", "S")
    assert field_slices((("A", 2), ("B", 9)))["B"] == slice(2, 11)
    for bad in ((("F", 0),), (("push", 3),), (("F", 1), ("F", 2)), (("1x", 1),)):
        with pytest.raises(ValueError, match="ring field"):
            Ring(4, bad)
    with pytest.raises(ValueError, match="capacity must be >= 2"):
        Ring(1, (("F", 1),))


def test_against_a_list_model_with_overwrite_pop_peek_rewind():
    """Random pushes, pops and rewinds; after each, the ring holds the newest
    ``capacity`` entries of the model in order, ``peek(age)`` is the entry
    ``age`` back, and a push into a full ring replaces the oldest slot only."""
    rng = np.random.default_rng(3)
    cap = 7
    r = Ring(cap, (("X", 2),))
    model = []
    t = 0
    for _ in range(2000):
        op = rng.integers(0, 10)
        if op < 6:
            t += int(rng.integers(1, 4))
            before = {r.slot(i): (int(r.t[r.slot(i)]), r.d[r.slot(i)].tolist()) for i in range(len(r))}
            oldest = r.slot(0) if len(r) == cap else None
            k = r.push(t)
            r.d[k] = (t, -t)
            model.append((t, [float(t), float(-t)]))
            model = model[-cap:]
            # only the slot written changed; when full, it was the oldest
            if oldest is not None:
                assert k == oldest
            for s, e in before.items():
                if s != k:
                    assert (int(r.t[s]), r.d[s].tolist()) == e
        elif op < 8:
            k = r.pop()
            if model:
                assert (int(r.t[k]), r.d[k].tolist()) == model.pop(0)
            else:
                assert k == -1
        else:
            cut = t - int(rng.integers(0, 6))
            r.drop_newer_than(cut)
            model = [e for e in model if e[0] <= cut]
        assert _contents(r) == model
        assert len(r) == len(model) and r.full == (len(model) == cap)
        for age in range(len(model)):
            assert int(r.t[r.peek(age)]) == model[-1 - age][0]
        assert r.peek(len(model)) == -1 and r.peek(-1) == -1
        if model:
            q = int(rng.integers(model[0][0] - 1, model[-1][0] + 2))
            assert r.index_at_or_after(q) == sum(1 for e in model if e[0] < q)


def test_copy_from_and_clear():
    a = Ring(4, (("X", 1),))
    b = Ring(4, (("X", 1),))
    for t in range(1, 7):
        a.d[a.push(t)] = t * 10
    b.copy_from(a)
    assert _contents(b) == _contents(a) == [(t, [t * 10.0]) for t in range(3, 7)]
    b.d[b.push(7)] = 70
    assert _contents(a)[-1] == (6, [60.0])       # a copy, not a view
    with pytest.raises(ValueError, match="same capacity and width"):
        Ring(5, (("X", 1),)).copy_from(a)
    b.clear()
    assert len(b) == 0 and b.pop() == -1 and b.peek(0) == -1


@pytest.mark.skipif(not available(), reason="numpy memory handler API not reachable")
def test_operations_allocate_no_array():
    r = Ring(16, (("F", 3), ("W", 3)))
    dv = r.dv
    counter = NumpyAllocationCounter()
    with counter:
        for t in range(100):
            k = r.push(t)
            dv[k, 0] = 1.0
            r.peek(3)
            r.index_at_or_after(t - 5)
            if t % 3 == 0:
                r.pop()
            if t % 17 == 0:
                r.drop_newer_than(t - 2)
    assert counter.count == 0
