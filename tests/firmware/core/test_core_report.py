"""The compiled magnetic POSE of a burst (transmit.Transmitter.pose_cov6 on the compiled core: one
``ct_pose_frame`` call from the tracker's arrays) against its Python reference (the record filled by
``pose_cov6`` and sent by ``pose``): the same bytes, refusals and counters; a recorder wrapping
``pose`` still sees every pose. And the quiet-field term of the grading (track.quality) against
its closed form. Seeded; skips without the extension."""
import math
import random

import numpy as np
import pytest

from coiltrack.firmware import core
from coiltrack.firmware.transmit import Transmitter
from coiltrack.protocol.schema import POSE_FUSED, POSE_VALID

_core = pytest.importorskip("coiltrack.firmware._core", reason="the compiled core is not built here")


def _pair(transmitter_pair, fail_every: int = 0):
    ref, got = transmitter_pair(fail_every)
    assert got.pose_cov6.__func__ is Transmitter._pose_cov6_compiled      # the compiled path is the one tested
    return ref, got


def _args(rng):
    """A pose as the tracker hands it: position (3,) and covariance (6, 6) arrays, the quaternion a
    memoryview of 4 doubles or a tuple, with NaN, huge and negative variances among them."""
    p = np.array([rng.uniform(-2, 2) for _ in range(3)])
    A = np.array([[rng.gauss(0, 1) for _ in range(6)] for _ in range(6)])
    cov = A @ A.T * 10.0 ** rng.uniform(-12, 2)
    k = rng.randrange(6)
    if rng.random() < 0.2:
        cov[k, k] = rng.choice([math.nan, math.inf, 1e300, -1.0, 3.0e38, 1e-320])
    q = np.array([rng.gauss(0, 1) for _ in range(4)])
    q /= np.linalg.norm(q)
    q = memoryview(q) if rng.random() < 0.5 else tuple(float(v) for v in q)
    node = rng.choice([0, 1, 255, 256, rng.randrange(256)])          # 256: refused (a tx error)
    t_us = rng.choice([0, rng.randrange(1 << 40), -5])              # -5: refused
    status = rng.choice([0, POSE_VALID, POSE_VALID | POSE_FUSED, rng.randrange(1 << 16)])
    quality = rng.choice([0, 255, rng.randrange(256)])
    return node, t_us, p, q, cov, status, quality


@pytest.mark.parametrize("fail_every", [0, 3])
def test_pose_cov6_frames_are_the_python_bytes(fail_every, transmitter_pair):
    """1500 poses with random arrays, refused integers and a link failing every third write: the
    same frames (bytes, sequence numbers), tx errors and pose counters as the Python reference."""
    rng = random.Random(11)
    ref, got = _pair(transmitter_pair, fail_every)
    for k in range(1500):
        a = _args(rng)
        ref.pose_cov6(*a)
        got.pose_cov6(*a)
        if k % 97 == 0:
            ref.event(3, k)
            got.event(3, k)
    assert got.port.frames == ref.port.frames and len(ref.port.frames) > 500
    assert (got.tx_errors, got.poses, got.fused_poses) == (ref.tx_errors, ref.poses, ref.fused_poses)
    assert ref.tx_errors > 0 and ref.fused_poses > 0


def test_pose_cov6_goes_through_a_wrapped_pose(transmitter_pair):
    """A recorder that wraps ``pose`` (as the replay tests do) sees the magnetic poses with the
    reference's record values, and the frames stay the reference's."""
    rng = random.Random(2)
    ref, got = _pair(transmitter_pair)
    seen = []
    send = got.pose

    def pose(r):
        seen.append((r.node, r.t_us, r.status, r.quality, *r.p, *r.q, *r.var))
        send(r)
    got.pose = pose
    for _ in range(50):
        a = _args(rng)
        ref.pose_cov6(*a)
        got.pose_cov6(*a)
    assert len(seen) == 50
    assert got.port.frames == ref.port.frames
    node, t_us, p, q, cov, status, quality = a
    assert seen[-1][:4] == (node, t_us, status, quality)
    assert seen[-1][4:7] == tuple(float(v) for v in p)
    assert seen[-1][11:] == tuple(float(cov[i, i]) for i in range(6))


class _Ring:
    """A sample ring's newest slot (``peek(0)``, -1 when empty) and its flat buffer."""

    def __init__(self, rows):
        self.b = np.array(rows, dtype=float).reshape(-1)
        self.bv = memoryview(self.b)
        self.n = len(rows)

    def __len__(self):
        return self.n

    def peek(self, age):
        return self.n - 1 - age if 0 <= age < self.n else -1


class _Ch:
    def __init__(self, node, ring):
        self.node, self.ring = node, ring


def test_quiet_term_closed_form_and_unused_cases():
    """``((|B| - earth) / sigma)^2`` of the newest sample, against the closed form; 0 with an
    empty ring, an unknown node, a zero sigma or a zero earth field."""
    from types import SimpleNamespace

    from coiltrack.firmware.track.quality import PoseQuality

    def cfg(sigma, earth):
        return SimpleNamespace(quality=SimpleNamespace(quality_error_scale_m=0.01, quality_quiet_sigma_t=sigma),
                               orientation=SimpleNamespace(earth_field_t=earth))
    full = _Ring([[1e-6, 2e-6, 3e-6], [20e-6, -30e-6, 35e-6]])
    chans = (_Ch(1, full), _Ch(2, _Ring([])))
    q = PoseQuality(cfg(2e-6, 50e-6), 3, chans, core=core.PYTHON)
    m = math.sqrt(20e-6 ** 2 + 30e-6 ** 2 + 35e-6 ** 2)
    assert q.quiet_term(1) == pytest.approx(((m - 50e-6) / 2e-6) ** 2, rel=1e-14)
    assert q.quiet_term(2) == 0.0 and q.quiet_term(9) == 0.0
    assert PoseQuality(cfg(0.0, 50e-6), 3, chans, core=core.PYTHON).quiet_term(1) == 0.0
    assert PoseQuality(cfg(2e-6, 0.0), 3, chans, core=core.PYTHON).quiet_term(1) == 0.0
