"""The room's distortion map inside the one signal model (firmware_py.model.distortion)."""
import numpy as np
import pytest

from coiltrack.firmware.model.distortion import DistortionMap
from coiltrack.firmware.model.field import Coil
from coiltrack.firmware.model.signal import SignalModel

MU0_4PI = 1e-7


def _coils():
    return [Coil((0, 0, 0), ax, 0.055, 50) for ax in ((1, 0, 0), (0, 1, 0), (0, 0, 1))]


def _map():
    pos = [[[0.05, 0.02, -1.1], [0.3, -0.2, -0.9]], [[0.1, 0.0, -1.2]], [[-0.2, 0.3, -1.0], [0.4, 0.1, -1.3]]]
    mom = [[[-0.08, 0.01, -0.005], [0.002, 0.01, 0.03]], [[0.0, -0.1, -0.004]], [[0.0, -0.04, 0.18], [0.01, 0.0, 0.02]]]
    return DistortionMap(pos, mom)


def _numpy_dipole(p, q, m):
    d = p - q
    r = np.linalg.norm(d)
    return MU0_4PI * (3.0 * d * (d @ m) / r ** 2 - m) / r ** 3


def test_map_adds_the_dipole_fields_scaled_by_the_current():
    """B with the map = B without + I_j sum_k B_dip(p - q_jk; mu_jk), the dipole formula written
    out here in numpy (independent of field.dipole_point): catches a map not scaled by the
    current, added to the wrong coil, or with the moment's sign flipped. Tolerance 1e-12 relative
    (rounding)."""
    dm = _map()
    sm0, sm = SignalModel(_coils()), SignalModel(_coils())
    sm.set_distortion(dm)
    cur = [1.5, -0.8, 1.1]
    p = np.array([0.31, -0.12, 0.07])
    sm0.fields(*p, cur, False)
    sm.fields(*p, cur, False)
    for j in range(3):
        exp = sm0.B[j] + cur[j] * sum(_numpy_dipole(p, np.array(q), np.array(m))
                                      for q, m in zip(dm._q[j], dm._m[j]))
        assert np.allclose(sm.B[j], exp, rtol=1e-12, atol=1e-20)


def test_jacobian_with_the_map_matches_finite_differences():
    """H of ``measure`` (signals and pose Jacobian) with the map against central differences of
    ``predict`` in position (step 1e-6 m) and sensor-frame rotation (1e-6 rad), relative 1e-6 of
    the largest entry: catches a map whose gradient is missing or transposed in J (the position
    columns) while its field is there."""
    from scipy.spatial.transform import Rotation

    sm = SignalModel(_coils())
    sm.set_distortion(_map())
    cur = [1.5, 1.5, 1.5]
    p = np.array([0.42, 0.1, -0.3])
    R = Rotation.from_rotvec([0.3, -0.5, 0.8]).as_matrix()
    h = np.zeros(9)
    H = np.zeros(54)
    sm.measure(*p, R, cur, h, H)
    H = H.reshape(9, 6)
    num = np.zeros((9, 6))
    hp, hm = np.zeros(9), np.zeros(9)
    for k in range(6):
        e = np.zeros(3)
        if k < 3:
            e[k] = 1e-6
            sm.predict(*(p + e), R, cur, hp)
            sm.predict(*(p - e), R, cur, hm)
            num[:, k] = (hp - hm) / 2e-6
        else:
            e[k - 3] = 1e-6
            sm.predict(*p, R @ Rotation.from_rotvec(e).as_matrix(), cur, hp)
            sm.predict(*p, R @ Rotation.from_rotvec(-e).as_matrix(), cur, hm)
            num[:, k] = (hp - hm) / 2e-6
    assert np.max(np.abs(H - num)) <= 1e-6 * np.max(np.abs(num))


def test_table_round_trip_and_refusals():
    """to_table / from_table keep the map; a wrong coil count, a non-dipole model or a bad row
    is refused naming the key (catches a silently ignored map)."""
    dm = _map()
    back = DistortionMap.from_table(dm.to_table(), 3)
    assert back._q == dm._q and back._m == dm._m
    with pytest.raises(ValueError, match="coils"):
        DistortionMap.from_table(dm.to_table(), 4)
    bad = dm.to_table()
    bad["model"] = "poly"
    with pytest.raises(ValueError, match="distortion.model"):
        DistortionMap.from_table(bad)
    bad = dm.to_table()
    bad["coil1_position_m"] = [[0.0, 1.0]]
    with pytest.raises(ValueError, match="coil1_position_m"):
        DistortionMap.from_table(bad)


def test_map_evaluation_allocates_no_array():
    """The map's run-time path allocates no numpy array (tracemalloc, as tests/firmware/test_alloc.py):
    catches a per-call buffer."""
    import tracemalloc

    sm = SignalModel(_coils())
    sm.set_distortion(_map())
    cur = memoryview(np.array([1.5, 1.5, 1.5]))
    R = np.eye(3)
    h, H = memoryview(np.zeros(9)), memoryview(np.zeros(54))
    sm.measure(0.3, 0.1, 0.0, R, cur, h, H)
    tracemalloc.start()
    s0 = tracemalloc.take_snapshot()
    for _ in range(50):
        sm.measure(0.3, 0.1, 0.0, R, cur, h, H)
    s1 = tracemalloc.take_snapshot()
    tracemalloc.stop()
    grown = sum(st.size_diff for st in s1.compare_to(s0, "filename") if "numpy" in str(st.traceback))
    assert grown <= 0


def _tracker_with(name: str, dm, **changes):
    """The tracker of scenario ``name``'s firmware built with a calibration holding the map ``dm``."""
    import dataclasses

    from coiltrack.firmware.calibration import Calibration
    from coiltrack.firmware.loop import Firmware
    from coiltrack.tools import scenarios
    from coiltrack.tools.bench.links import inproc_pair

    fw_end, _ = inproc_pair()
    cfg = (scenarios.get(name).firmware_config()).with_keys(**changes)
    return Firmware(cfg, fw_end, calibration=Calibration(distortion=dm)).tracker


def test_the_map_reaches_every_pose_solver_of_the_fused_pipeline():
    """The fused pipeline solves each burst twice (the plain solve and the motion-compensated
    re-solve of ``track.burst_fusion``): catches the map put into the first only, so that the
    re-solve fits the room-free model. The map is given to each solver as the composition
    (``firmware.compose``) builds it; ``distortion_apply = false`` leaves every solver without."""
    dm = _map()
    tracker = _tracker_with("roetenberg-fusion", dm)
    assert tracker.solver.signal.distortion is dm and tracker.comp_solver.signal.distortion is dm
    tracker = _tracker_with("roetenberg-fusion", dm, distortion_apply=False)
    assert tracker.solver.signal.distortion is None and tracker.comp_solver.signal.distortion is None


def test_the_map_reaches_the_single_coil_acquisition_solver():
    """The single-coil tracker's acquisition solves a full burst: catches its solver left out."""
    dm = _map()
    assert _tracker_with("schepers-adaptive", dm).acquisition.solver.signal.distortion is dm
