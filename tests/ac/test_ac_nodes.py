"""The AC bench: conductors' fields at the drive frequency, the fast magnetometer node, the AC driver.

The conducting sphere's response is checked against Wait's (1951) solution
written here with scipy's spherical Bessel functions of complex argument
(``m = 2 pi a^3 H0 (2 mu_r - G) / (mu_r + G)``, ``G = x j0(x) / j1(x) - 1``,
``x = a sqrt(-i w mu_r mu0 sigma)``), independent of ``hil.conductors``' series
and cotangent forms; the field at the sensor is the point dipole of that moment.
"""
import math
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.special import spherical_jn

from coiltrack.hil import physics
from coiltrack.hil.ac import ACCoilDriver, ACRequest, coil_impedance
from coiltrack.hil.ac_nodes import ACDriverNode, FastSensorNode, object_response
from coiltrack.hil.magnetometers import FastMagProfile
from coiltrack.hil.motion import StaticPose
from coiltrack.hil.world import ConductingSphereObject, EddyObject, MetalObject, World
from coiltrack.protocol import MSG
from coiltrack.protocol.schema import AC_FAULT_REFUSED

MU0 = 4e-7 * math.pi


def wait_moment(omega, a, sigma, mu_r, B0):
    x = a * np.sqrt(-1j * omega * mu_r * MU0 * sigma + 0j)
    G = x * spherical_jn(0, x) / spherical_jn(1, x) - 1.0
    return 2 * np.pi * a**3 * (np.asarray(B0) / MU0) * (2 * mu_r - G) / (mu_r + G)


def dipole(p, c, m):
    r = np.asarray(p) - c
    d = np.linalg.norm(r)
    return 1e-7 * (3 * r * np.dot(m, r) / d**5 - m / d**3)


SPHERE_C = np.array([-0.06, 0.02, 0.01])
SENSOR_P = np.array([0.22, 0.05, -0.03])


@pytest.mark.parametrize("kind, a, sigma, mu_r", [("sphere", 0.03, 3.5e7, 1.0), ("metal", 0.02, 6e6, 200.0)])
@pytest.mark.parametrize("f", [215.0, 465.0, 5000.0])
def test_sphere_response_against_wait_in_amplitude_and_phase(kind, a, sigma, mu_r, f):
    """Aluminium (non-magnetic) and steel (mu_r 200) spheres from 215 Hz to 5 kHz (a/delta 0.8-8):
    the emulator's field phasor at the sensor per ampere of each coil equals Wait's dipole to
    1e-9 in amplitude and 1e-9 rad in phase: catches a conjugated phasor (a lead for a lag), a
    moment sign, the permeability left out, or the field taken at the wrong point."""
    src = physics.thesis_source()
    world = World(src, StaticPose(SENSOR_P, np.eye(3)))
    if kind == "sphere":
        obj = ConductingSphereObject(physics.ConductingSphere(SPHERE_C, a, sigma))
    else:
        obj = MetalObject(radius=a, mu_r=mu_r, sigma=sigma, position=SPHERE_C)
    w = 2 * np.pi * f
    for k in range(3):
        B0 = src.unit_fields(SPHERE_C[None, :])[k, 0]
        m = wait_moment(w, a, sigma, mu_r, B0)
        want = dipole(SENSOR_P, SPHERE_C, m.real) + 1j * dipole(SENSOR_P, SPHERE_C, m.imag)
        got = object_response(world, obj, w, k, SENSOR_P)
        big = np.abs(want) > 1e-3 * np.abs(want).max()
        np.testing.assert_allclose(np.abs(got[big]), np.abs(want[big]), rtol=1e-9)
        np.testing.assert_allclose(np.angle(got[big] / want[big]), 0.0, atol=1e-9)


def test_lumped_eddy_loop_lags_by_its_transfer_function():
    """The lumped eddy loop at 215 Hz, tau 2 ms: its field is ``-kappa m_c i w tau / (1 + i w tau)``
    through the dipole, phase arg = atan(1 / (w tau)) after the sign flip (a lagging, opposing
    moment): catches the transfer function conjugated or replaced by its DC value 0."""
    src = physics.thesis_source()
    world = World(src, StaticPose(SENSOR_P, np.eye(3)))
    c = np.array([-0.08, 0.0, 0.0])
    obj = EddyObject(physics.EddyConductor(c, coupling=0.02, tau_s=2e-3))
    w = 2 * np.pi * 215.0
    for k in range(3):
        m_c = src[k].moment_per_amp
        h = 1j * w * 2e-3 / (1 + 1j * w * 2e-3)
        m = -0.02 * m_c * h
        want = dipole(SENSOR_P, c, m.real) + 1j * dipole(SENSOR_P, c, m.imag)
        np.testing.assert_allclose(object_response(world, obj, w, k, SENSOR_P), want, rtol=1e-9, atol=1e-18)


def test_fast_node_samples_the_filtered_coil_and_conductor_fields():
    """The node's AC field at a sample time equals, computed here, the coils' current averaged over
    the 0.5 ms before the sample (closed form of the steady-state cosine: ``|I| sinc(f T) cos(w t
    + arg I - pi f T)``) times magpylib's unit fields, plus ``Re[H(f) I F e^{i w t}]`` of the sphere
    (``F`` from Wait as above), to 1e-9 relative: catches the filter's delay or droop left out of
    either part, or the conductor's phase applied twice."""
    src = physics.thesis_source()
    sphere = physics.ConductingSphere(SPHERE_C, 0.03, 3.5e7)
    world = World(src, StaticPose(SENSOR_P, np.eye(3)), objects=[ConductingSphereObject(sphere)])
    freqs = (215.0, 315.0, 465.0)
    reqs = [ACRequest(k, f, 1.5 * abs(coil_impedance(src[k], 2 * np.pi * f)), 0.4 * k) for k, f in enumerate(freqs)]
    drv = ACCoilDriver(src, reqs, start_s=0.0)
    prof = FastMagProfile.mmc5983ma()
    node = FastSensorNode(16, world, prof, driver=SimpleNamespace(ac_driver=drv))   # a driver node running drv
    U = src.unit_fields(SENSOR_P[None, :])[:, 0, :]
    for t_us in (500_123, 731_777):           # long after the L/R switch-on transient
        t = t_us * 1e-6
        want = np.zeros(3)
        for k, d in enumerate(drv.drives):
            f, I = d.freq_hz, d.current
            T = prof.integration_s
            ibar = abs(I) * np.sinc(f * T) * math.cos(d.omega * t + np.angle(I) - math.pi * f * T)
            want += ibar * U[k]
            B0 = src.unit_fields(SPHERE_C[None, :])[k, 0]          # the coil's field at the sphere
            m = wait_moment(d.omega, 0.03, 3.5e7, 1.0, B0)
            F = dipole(SENSOR_P, SPHERE_C, m.real) + 1j * dipole(SENSOR_P, SPHERE_C, m.imag)
            H = np.sinc(f * T) * np.exp(-1j * math.pi * f * T)
            want += np.real(H * I * F * np.exp(1j * d.omega * t))
        got = node._coil_ac_field(t_us)
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9 * np.abs(want).max())


class _Sent(list):
    def __call__(self, node, msg):
        self.append(msg)


def test_ac_driver_refuses_before_sync_and_reports_its_current_after():
    """Before time sync a plan is refused with ``AC_FAULT_REFUSED``; once synchronised the driver
    runs it and reports the measured current amplitude (1.5 A within 0.1 %) and phase against the
    plan's reference (0 within 1 mrad, its current sensor's noise): catches a status phase taken
    against the wrong time origin (radians off) or a plan accepted unsynchronised."""
    world = World(physics.thesis_source(), StaticPose(SENSOR_P, np.eye(3)))
    drv = ACDriverNode(2, world)
    sent = _Sent()
    cmd = MSG["AC_DRIVE_CMD"]
    drv.handle(cmd(0, 1, 215_000, 1_500_000, 300_000, 300_000, 0), 1_000, sent)
    assert sent[-1].NAME == "AC_DRIVE_STATUS" and sent[-1].faults & AC_FAULT_REFUSED
    drv.handle(MSG["TIME_SYNC"](10_000, 1), 10_000, sent)
    for c, f in enumerate((215_000, 315_000, 465_000)):
        drv.handle(cmd(c, 2, f, 1_500_000, 300_000, 300_000, 0), 20_000, sent)
    t = 20_000
    while t < 1_500_000:
        drv.tick(t, sent)
        t += 1000
    st = [m for m in sent if m.NAME == "AC_DRIVE_STATUS" and m.plan_id == 2]
    assert {m.coil for m in st} == {0, 1, 2}
    for m in st:
        assert m.faults == 0
        assert m.amplitude_ua * 1e-6 == pytest.approx(1.5, rel=1e-3)
        assert abs(m.phase_urad * 1e-6) < 1e-3


def test_the_ac_bench_is_built_once_of_its_own_nodes():
    """``hil.bench.assemble(kinds=ACNodeKinds(...))`` builds the AC driver and the fast sensor
    nodes themselves (they were swapped in after the bench was built): the emulator serves exactly
    those nodes, each sensor sees that driver's drive, and a node-off fault lands on them."""
    from coiltrack.hil.ac_nodes import ACNodeKinds
    from coiltrack.hil.bench import assemble
    from coiltrack.hil.faults import BenchFaults
    from coiltrack.hil.nodes import MagSpec
    from coiltrack.tools.bench.links import inproc_pair

    world = World(physics.thesis_source(), StaticPose(SENSOR_P, np.eye(3)))
    _, emu_end = inproc_pair()
    prof = FastMagProfile.mmc5983ma()
    bench = assemble(world, emu_end, mag=MagSpec(), faults=BenchFaults.parse("node_off=sensor@1s-2s"),
                     sensor_ids=(16, 17), kinds=ACNodeKinds(prof), seed_sensor=5)
    assert type(bench.driver) is ACDriverNode
    assert [type(s) for s in bench.sensors] == [FastSensorNode, FastSensorNode]
    assert bench.emulator.nodes == [bench.driver, *bench.sensors] and bench.emulator.driver is bench.driver
    assert all(s.driver is bench.driver and s.profile is prof for s in bench.sensors)
    assert bench.sensors[0].off_windows == [(1_000_000, 2_000_000)] and bench.sensors[1].off_windows == []
    assert bench.sensors[0]._coil_ac_field(1_000).tolist() == [0.0, 0.0, 0.0]     # no plan runs yet
