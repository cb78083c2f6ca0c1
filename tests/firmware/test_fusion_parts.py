"""The fusion filter's parts chosen once at construction (``estimate.magnetic_inertial``): the
measurement model (``estimate.fusion_measurement``, thesis ``002_cd7f1fdb7fc67471.txt`` eqs
6.18-6.21) and the source frame (``estimate.fusion_state``: a moving source's ``Phi`` from the IMU
samples, a fixed one the identity); and the fusing trackers' source (``track.burst_fusion``,
``track.tight_fusion``: a source module or its null object)."""
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from coiltrack.firmware.config import FirmwareConfig
from coiltrack.firmware.estimate.fusion_measurement import (InertialMagneticOrientation, MagneticOrientation,
                                                            MeasurementModel, make_measurement_model)
from coiltrack.firmware.estimate.fusion_state import FixedSource, MovingSource
from coiltrack.firmware.estimate.layout import ORI, POS, PSI, QM, XI
from coiltrack.firmware.estimate.magnetic_inertial import (FUS_INITIALISED, OUT_P, OUT_STATUS, OUT_VAR_P, FusionFilter,
                                                           FusionParams)
from coiltrack.firmware.estimate.orientation import OrientationFilter, OrientationParams
from coiltrack.firmware.track import burst_fusion, tight_fusion

G = np.array([0.0, 0.0, 9.81])


@pytest.mark.parametrize("model, kind, rows", [(1, MagneticOrientation, ("ZP", "ZPSI")),
                                               (2, InertialMagneticOrientation, ("ZP", "ZXI")),
                                               (3, InertialMagneticOrientation, ("ZP", "ZPSI", "ZXI"))])
def test_measurement_model_is_chosen_by_number_with_the_constant_c_of_the_thesis(model, kind, rows):
    """Model 1 is eq 6.18, models 2 and 3 eqs 6.20-6.21: the model class, its rows, and ``H`` the
    constant ``C`` (position rows on ``POS`` and ``QM``, each orientation row on ``ORI`` and its
    white state). Catches a model 2 that still stacks the magnetic orientation, or a row on the
    wrong white state."""
    xi = OrientationFilter(OrientationParams.from_config(None))
    prm = FusionParams.from_config(None, measurement_model=model)
    m = make_measurement_model(prm, xi)
    assert isinstance(m, kind)
    assert all(callable(getattr(m, f)) for f in MeasurementModel.__dict__ if not f.startswith("_")
               and callable(MeasurementModel.__dict__[f]))
    assert tuple(m.zlayout.names()) == rows
    ff = FusionFilter(prm, xi)
    assert isinstance(ff.meas, kind)
    H = ff.upd.H
    want = np.zeros_like(H)
    white = {"ZPSI": PSI, "ZXI": XI}
    for r, name in enumerate(rows):
        for i in range(3):
            if name == "ZP":
                want[3 * r + i, POS.start + i] = want[3 * r + i, QM.start + i] = 1.0
            else:
                want[3 * r + i, ORI.start + i] = want[3 * r + i, white[name].start + i] = 1.0
    np.testing.assert_array_equal(H, want)


def test_models_2_and_3_need_xi():
    """Models 2 and 3 read Xi: refused at construction without it (model 1 needs none)."""
    for model in (2, 3):
        with pytest.raises(ValueError, match="Xi"):
            FusionFilter(FusionParams.from_config(None, measurement_model=model))
    assert isinstance(FusionFilter(FusionParams.from_config(None, measurement_model=1)).meas, MagneticOrientation)


def _run(fixed: bool, Phi) -> np.ndarray:
    """Two seconds of a sensor at rest (100 Hz) with one magnetic update at 1 s; the output rows."""
    ff = FusionFilter(FusionParams.from_config(None, measurement_model=1), fixed_source=fixed)
    assert isinstance(ff.frame, FixedSource if fixed else MovingSource)
    Rs = Rotation.from_rotvec([0.1, -0.2, 0.3]).as_matrix()         # sensor to global
    f = Rs.T @ G
    q = np.array([0.2, 0.1, -0.05])
    C = np.diag([1e-6] * 3 + [1e-4] * 3)
    rows = []
    for k in range(200):
        t = 10_000 * k
        if k == 50:
            ff.schedule_snapshot(t + 5_000)
        if k == 100:
            flags = ff.magnetic_update(505_000, Phi.T @ q, Phi.T @ Rs, C)
            assert flags & FUS_INITIALISED, flags
        ff.push_imu(t, *f, 0.0, 0.0, 0.0, *G, Phi)
        k_out = ff.pop_output()
        while k_out >= 0:
            rows.append(ff.out_d[k_out].copy())
            ff.release_output()
            k_out = ff.pop_output()
    return np.array(rows)


def test_fixed_source_is_the_moving_one_at_phi_identity_and_a_turned_source_turns_the_outputs():
    """The fixed source (Phi = I, no frame change) gives the outputs of the moving one fed the
    identity, to the bit; a source turned by Phi reports the same pose in its own frame: position
    Phi^T p. Catches the frame change applied the
    wrong way round (Phi p for Phi^T p) or skipped for a moving source."""
    a = _run(True, np.eye(3))
    b = _run(False, np.eye(3))
    assert len(a) > 50
    np.testing.assert_array_equal(a, b)
    Phi = Rotation.from_rotvec([0.0, 0.0, 0.7]).as_matrix()
    c = _run(False, Phi)
    np.testing.assert_allclose(c[:, OUT_P:OUT_P + 3], a[:, OUT_P:OUT_P + 3] @ Phi, atol=1e-9)    # Phi^T p
    np.testing.assert_array_equal(c[:, OUT_STATUS], a[:, OUT_STATUS])
    assert np.all(c[:, OUT_VAR_P:OUT_VAR_P + 3] > 0)


def test_fusing_trackers_choose_their_source_once():
    """No source IMU: the null objects (Phi = I, f_source = -g; nothing kept, waited for or
    counted); with one: the source module, its acceleration measured or (``source_acceleration``
    off) taken as -g."""
    cfg = FirmwareConfig()
    gate = burst_fusion.PulseGate(np.zeros(3, np.int64), np.zeros(3, np.int64), cfg.pulse.fall_us, cfg.orientation.compass_guard_us)
    fixed = burst_fusion.make_source(cfg, gate)
    assert fixed.fixed and fixed.counters() == {} and not fixed.hold(0, 0, 10**6)
    np.testing.assert_array_equal(fixed.phi, np.eye(3))
    np.testing.assert_array_equal(fixed.fref, -np.asarray(cfg.imu.gravity_mps2))
    cfg8 = FirmwareConfig().with_(link={"source_imu_id": 8})
    moving = burst_fusion.make_source(cfg8, gate)
    assert not moving.fixed and isinstance(moving.force, burst_fusion.MeasuredForce)
    assert "source_imu_samples" in moving.counters()
    noanet = burst_fusion.make_source(FirmwareConfig().with_(
        link={"source_imu_id": 8},
        body={"source_acceleration": False}), gate)
    fv = noanet.fref.copy()
    noanet.force.update(memoryview(np.eye(3)), memoryview(noanet.fref), 1.0, 2.0, 3.0)
    np.testing.assert_array_equal(noanet.fref, fv)
    moving.force.update(memoryview(np.eye(3)), memoryview(moving.fref), 1.0, 2.0, 3.0)
    np.testing.assert_array_equal(moving.fref, [1.0, 2.0, 3.0])
    t_fixed = tight_fusion._make_source(cfg)
    f, w = np.zeros(3), np.zeros(3)
    t_fixed.sample_into(0, f, w, np.array([0.0, 0.0, -9.81]))
    np.testing.assert_array_equal(f, [0.0, 0.0, 9.81])
    assert t_fixed.fixed and t_fixed.ready(10**9) and not tight_fusion._make_source(cfg8).fixed
