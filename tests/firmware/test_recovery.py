"""Recovery of the fused track (thesis ch. 6 filter) and of the ch. 2 filter
after faults, on seeded synthetic data: restarts from the magnetic solution,
offsets kept when credible, dead-reckoning status, the orientation found
again after a break in the IMU stream. References: the magnetic solution
itself (a restart must land on it), the random-walk variance growth
``sigma_rw^2 dt`` and the Gauss-Markov decay ``exp(-dt / tau)`` (eqs
6.13-6.14), TRIAD in closed form."""
import math

import numpy as np

from coiltrack.firmware.estimate.layout import ACC, GYR, POS
from coiltrack.firmware.estimate.magnetic_inertial import (FUS_GAP_REINIT, OUT_DEAD_RECKONING, OUT_LOST,
                                                          OUT_RECOVERED, OUT_STATUS, OUT_VAR_P, RECOVER_DISAGREE,
                                                          RECOVER_GAP, FusionFilter, FusionParams)
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams
from coiltrack.hil.motion import HandMovedBench, rotvec_to_matrix

G = np.array([0.0, 0.0, -9.81])
EARTH = np.array([20e-6, 0.0, -45e-6])
ACC_S, GYR_S = 0.0155, 0.0067
RATE = 120.0
TRAJ = HandMovedBench(seed=3, duration_s=30, v_max=0.12, w_max_deg=30.0)
_EYE = np.eye(3)
_C = np.diag([4e-6, 3e-6, 5e-6, 1e-4, 1.2e-4, 0.8e-4])


class _Feed:
    """A model-3 fusion filter and its ch. 2 filter fed from a seeded synthetic
    IMU on ``TRAJ``; magnetic solutions are the truth (or the truth moved)."""

    def __init__(self, T=8.0, seed=5, **kw):
        rng = np.random.default_rng(seed)
        self.t_us = (np.arange(int(T * RATE)) * (1e6 / RATE)).astype(np.int64) + 1000
        K = TRAJ.kinematics(self.t_us)
        ba, bg = rng.normal(0, 0.02, 3), rng.normal(0, 8.7e-3, 3)
        n = self.t_us.size
        self.f = np.einsum("nji,nj->ni", K.R, K.acceleration - G) + ba + rng.normal(0, ACC_S, (n, 3))
        self.w = K.angular_velocity + bg + rng.normal(0, GYR_S, (n, 3))
        self.m = np.einsum("nji,j->ni", K.R, EARTH) + rng.normal(0, 0.5e-7, (n, 3))
        self.of = OrientationFilter(OrientationParams.from_config(None, gyro_noise=GYR_S, acc_noise=ACC_S,
                                                                  mag_noise=0.5e-7 / 49e-6, gyro_bias_sigma=0.02,
                                                                  mag_learn_samples=60))
        self.ff = FusionFilter(FusionParams.from_config(None, measurement_model=3, acc_noise=ACC_S, gyro_noise=GYR_S,
                                                        gyro_bias_sigma=0.02, **kw), self.of, fixed_source=True)
        self.i = 0
        self.status = []            # (t_us, OUT_STATUS, position variance x) of every output

    def push(self):
        i, of, ff = self.i, self.of, self.ff
        t = int(self.t_us[i])
        if not of.initialized:
            of.initialize(t, *self.f[i], *self.m[i])
        else:
            of.predict(t, *self.w[i])
            of.update_acc(*self.f[i])
            of.update_mag(*self.m[i])
        self.i += 1
        if ff.push_imu(t, *self.f[i], *self.w[i], 0.0, 0.0, 9.81, _EYE):
            k = ff.pop_output()
            self.status.append((t, int(ff.out_dv[k, OUT_STATUS]), float(ff.out_dv[k, OUT_VAR_P])))
            ff.release_output()

    def run_to(self, t_end):
        while int(self.t_us[self.i]) <= t_end:
            self.push()

    def update(self, t_ref, offset=(0.0, 0.0, 0.0), replay=True):
        """Snapshot at ``t_ref``, IMU to 170 ms past it, fuse the truth (+ ``offset``, m);
        ``replay=False``: the update only (the shadow state still at ``t_ref``)."""
        self.ff.schedule_snapshot(t_ref)
        self.run_to(t_ref + 170_000)
        k = TRAJ.kinematics(t_ref)
        q = k.position + np.asarray(offset)
        flags = self.ff.begin_magnetic_update(t_ref, q, k.R @ rotvec_to_matrix([0.004, -0.006, 0.003]), _C)
        if replay:
            self.ff.finish()
        return flags, q


def _tracking(**kw):
    """A filter initialised and updated every 0.6 s to 3.33 s (five updates)."""
    fd = _Feed(**kw)
    for j in range(5):
        fd.update(330_000 + j * 600_000)
    assert fd.ff.updates == 4 and fd.ff.recoveries == 0
    return fd


def test_persistent_disagreement_restarts_from_the_magnetic_solution():
    """The magnetic solutions jump 0.4 m (the filter is the one that is wrong,
    e.g. a wrong mirror solution it was started on): each is gated; after
    ``reinit_after`` of them in a row the filter restarts on the solution
    itself (its position to 1e-9 m), counts it with the reason, and flags the
    poses that follow as recovered until an update is accepted. Catches a
    recovery that never triggers (the filter rejecting every solution for ever,
    as the 5 s sensor outage did) or that restarts somewhere else."""
    fd = _tracking()
    ff = fd.ff
    n = ff.prm.reinit_after
    for j in range(n):
        flags, q = fd.update(3_330_000 + j * 600_000, offset=(0.4, 0.0, 0.0), replay=j < n - 1)
    assert ff.recoveries == 1 and ff.recovery_reason == RECOVER_DISAGREE and ff.reinits == 1
    t_ref = 3_330_000 + (n - 1) * 600_000
    assert ff.sh.t_us == t_ref
    np.testing.assert_allclose(ff.sh.p, q, atol=1e-9)
    ff.finish()
    fd.run_to(t_ref + 250_000)
    assert fd.status[-1][1] & OUT_RECOVERED
    fd.update(t_ref + 600_000, offset=(0.4, 0.0, 0.0))       # consistent with the restart: accepted
    fd.run_to(t_ref + 900_000)
    assert ff.updates == 5 and not fd.status[-1][1] & OUT_RECOVERED


def test_restart_keeps_credible_offsets_decayed_and_with_grown_variance():
    """A restart after disagreement keeps the accelerometer and gyroscope
    offsets of the prior: decayed by exp(-dt/tau) and with their variance grown
    by sigma_rw^2 dt over the time since they were kept (eqs 6.13-6.14; dt = 0
    here: kept and restored at the same t_ref), the offset block of P unchanged
    otherwise. Catches offsets reset to zero at a restart (the filter then
    spends tens of seconds relearning them while dead reckoning drifts)."""
    fd = _tracking()
    ff = fd.ff
    for j in range(ff.prm.reinit_after - 1):
        fd.update(3_330_000 + j * 600_000, offset=(0.4, 0.0, 0.0))
    ba, bg = ff.sn.ba.copy(), ff.sn.bg.copy()
    assert np.abs(ba).max() > 1e-4          # something was learnt
    idx = np.r_[ACC.start:ACC.stop, GYR.start:GYR.stop]
    t_ref = 3_330_000 + (ff.prm.reinit_after - 1) * 600_000
    ff.schedule_snapshot(t_ref)
    fd.run_to(t_ref + 170_000)
    prior = ff.sn.P[np.ix_(idx, idx)].copy()
    ba, bg = ff.sn.ba.copy(), ff.sn.bg.copy()
    k = TRAJ.kinematics(t_ref)
    ff.begin_magnetic_update(t_ref, k.position + [0.4, 0, 0], k.R, _C)
    assert ff.recoveries == 1 and ff.biases_kept == 1
    np.testing.assert_allclose(ff.sh.ba, ba, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ff.sh.bg, bg, rtol=0, atol=1e-15)
    np.testing.assert_allclose(ff.sh.P[np.ix_(idx, idx)], prior, rtol=0, atol=1e-18)
    ff.finish()


def test_offsets_restored_after_a_gap_decay_and_grow_by_the_random_walk():
    """Kept offsets restored 100 s later: nominal times exp(-100 s / tau),
    variance kP + sigma_rw^2 x 100 s (eqs 6.13-6.14, the independent closed
    forms). Catches a variance not grown (an overconfident restart) or a
    missing decay."""
    ff = _tracking(acc_bias_tau_s=500.0, gyro_bias_tau_s=400.0).ff
    ff.recovery.keep_biases(ff.st)
    assert ff.recovery.kept
    kb = np.r_[ff.st.ba, ff.st.bg]
    idx = np.r_[ACC.start:ACC.stop, GYR.start:GYR.stop]
    kP = ff.st.P[np.ix_(idx, idx)].copy()
    t = ff.recovery.kept_t + 100_000_000
    from coiltrack.firmware.estimate.fusion_state import InsState

    st = InsState(ff.n, None)
    assert ff.recovery.restore_biases(st, t)
    ka, kg = math.exp(-100 / 500.0), math.exp(-100 / 400.0)
    np.testing.assert_allclose(np.r_[st.ba, st.bg], kb * np.r_[[ka] * 3, [kg] * 3], rtol=1e-12)
    s = np.r_[[ka] * 3, [kg] * 3]
    want = kP * np.outer(s, s) + np.diag([ff.prm.acc_bias_rw ** 2 * 100] * 3 + [ff.prm.gyro_bias_rw ** 2 * 100] * 3)
    np.testing.assert_allclose(st.P[np.ix_(idx, idx)], want, rtol=1e-12, atol=0)


def test_offsets_beyond_their_gate_are_not_kept():
    """An offset 10 prior sigmas from zero (a diverged state ran it off) is not
    credible: the restart starts the offsets afresh. Catches keeping whatever
    the diverged state held."""
    ff = _tracking().ff
    ff.st.ba[1] = 10 * ff.prm.acc_bias_sigma
    ff.recovery.keep_biases(ff.st)
    assert not ff.recovery.kept


def test_no_update_sets_dead_reckoning_then_not_valid_with_grown_covariance_and_a_gap_restart():
    """No magnetic update after 3.33 s: the outputs carry OUT_DEAD_RECKONING
    once ``dead_reckon_after_us`` has passed since the last update's t_ref and
    OUT_LOST after ``dead_reckon_limit_us`` (to the sample), the reported
    position variance grows all the while; the next solution restarts the
    filter (FUS_GAP_REINIT) on it. Catches the dead-reckoning bit missing
    (the 600-1200 gap poses of the issue sent as plain valid poses) or a
    covariance frozen during the gap."""
    fd = _tracking(dead_reckon_after_us=800_000, dead_reckon_limit_us=1_500_000)
    ff = fd.ff
    t_last = ff.last_update_t
    fd.run_to(t_last + 2_500_000)
    rows = [(t, s, v) for t, s, v in fd.status if t > t_last + 200_000]
    for t, s, v in rows:
        age = t - t_last
        assert bool(s & OUT_DEAD_RECKONING) == (age > 800_000), (t, s)
        assert bool(s & OUT_LOST) == (age > 1_500_000), (t, s)
    var = np.array([v for _, _, v in rows])
    assert np.all(np.diff(var) > 0)
    t_ref = t_last + 2_600_000
    flags, q = fd.update(t_ref, replay=False)
    assert flags & FUS_GAP_REINIT and ff.recoveries == 1 and ff.recovery_reason == RECOVER_GAP
    np.testing.assert_allclose(ff.sh.p, q, atol=1e-9)
    np.testing.assert_allclose(ff.sh.P[POS, POS], _C[:3, :3], atol=1e-15)
    ff.finish()


def test_reacquire_finds_the_orientation_in_the_same_frame_and_keeps_the_gyro_offset():
    """After a break the sensor has turned 90 deg about the vertical and 20 deg
    about x: reacquire gives the TRIAD orientation of the new samples in the
    frame of the first initialisation (closed form: R^T e_z along the specific
    force, R^T h_G along the field, h_G unchanged), keeps the gyroscope offset
    and grows its variance by sigma_wb^2 dt (capped at the initial one), and
    restarts theta with theta0_sigma. Catches the orientation integrated over
    the break with one rate sample (the 63 deg error after the 5 s outage) or
    the offset thrown away."""
    prm = OrientationParams.from_config(None)
    of = OrientationFilter(prm)
    f0 = -G
    assert of.initialize(0, *f0, *EARTH)
    h0 = of.h_g.copy()
    of.set_bias(0.001, -0.002, 0.003)
    from coiltrack.firmware.estimate.layout import BIAS, THETA

    Pb = of.P[BIAS.start, BIAS.start]
    R_true = rotvec_to_matrix([0.0, 0.0, math.pi / 2]) @ rotvec_to_matrix([math.radians(20), 0.0, 0.0])
    f = R_true.T @ -G
    m = R_true.T @ EARTH
    assert of.reacquire(5_000_000, *f, *m)
    np.testing.assert_allclose(of.R, R_true, atol=1e-12)
    np.testing.assert_allclose(of.h_g, h0, atol=0)
    np.testing.assert_allclose(of.bias, [0.001, -0.002, 0.003], atol=0)
    want = min(Pb + prm.gyro_bias_rw ** 2 * 5.0, prm.gyro_bias_sigma ** 2)
    np.testing.assert_allclose(of.P[BIAS.start, BIAS.start], want, rtol=1e-12)
    np.testing.assert_allclose(of.P[THETA.start, THETA.start], prm.theta0_sigma ** 2, rtol=1e-12)
    assert of.P[THETA.start, BIAS.start] == 0.0 and of.reacquired == 1
