"""State-layout tables: one row per named slice of a state vector.

Every estimator in the firmware has one table ``(name, index, size, unit,
meaning)`` (PX4 EKF2 style). Code indexes the state and the covariance by
name, ``P[POS, POS]``, never by number, and the table is the only place the
numbers live. The slices are plain Python ``slice`` objects, so
``P[POS, VEL]`` is a numpy view (no copy, no array data allocated).

Tables
------
``ORIENTATION_LAYOUT`` (9 states)
    The complementary orientation filter of the thesis ch. 2
    (``002_cd7f1fdb7fc67471.txt`` eq 2.15): orientation error, gyroscope
    offset error, magnetic disturbance error.
``FUSION_LAYOUT`` (21 states) and ``FUSION_XI_LAYOUT`` (24 states)
    The magnetic-inertial complementary filter of the thesis ch. 6
    (eq 6.9: position, velocity, orientation, accelerometer and gyroscope
    errors, magnetic position and orientation errors; eq 6.19 adds the
    error of the inertial-magnetic orientation ``Xi`` of ch. 2, used by the
    measurement models 2 and 3, eqs 6.20-6.21). ``XI`` comes last, so the
    first 21 indices are the same in both tables.

``SCHEPERS_LAYOUT`` and ``schepers_layout(n_clones, n_gains)`` (15 + 6 per clone + 1 per coil gain)
    The single-coil EKF (Schepers & Veltink 2010 with the ch. 6 error model,
    ``coiltrack.firmware.estimate.single_coil``): the inertial rows of eq 6.9
    (sensor-frame orientation error), per pulse in flight a clone of
    the position and orientation errors at the pulse's measurement time, and
    optionally (``GAIN``, last) each coil's constant gain error.
``relative_layout(n_clones)`` (21 + 6 per clone; ``RELATIVE_LAYOUT``: 3 clones)
    The tightly coupled tracker's relative inertial EKF
    (``coiltrack.firmware.estimate.relative_inertial``): the single-coil
    EKF's inertial rows in the moving source's frame, the source IMU's
    offsets, a clone per pulse of the burst.
``fusion_measurement_layout(model)`` (6 or 9 rows)
    The innovation of the fusion filter's magnetic update, eqs 6.18-6.21.
``POSE_LAYOUT`` (6)
    A pose covariance over ``(dp, dtheta)``, as the solver and the
    single-coil EKF report it (``POSE_POS``, ``POSE_ORI``).

The inertial rows ``POS, VEL, ORI, ACC, GYR`` have the same indices in every
inertial table (checked below), so ``estimate.strapdown`` writes the error
transition of both inertial filters with the same names.

Error conventions (``true = estimate (+) error``) are stated per filter in
``coiltrack.firmware.estimate.orientation`` and ``coiltrack.firmware.estimate.magnetic_inertial``.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class StateSlot:
    name: str
    index: int
    size: int
    unit: str
    meaning: str

    @property
    def sl(self) -> slice:
        return slice(self.index, self.index + self.size)


class StateLayout:
    """A table of named, contiguous state slices.

    ``layout.POS`` is the slice of the row named ``POS``; ``layout.n`` the
    state dimension; ``layout.rows`` the table itself.
    """

    def __init__(self, name: str, rows: tuple[tuple[str, int, str, str], ...]):
        self.name = name
        slots = []
        i = 0
        for rname, size, unit, meaning in rows:
            slots.append(StateSlot(rname, i, size, unit, meaning))
            i += size
        self.rows: tuple[StateSlot, ...] = tuple(slots)
        self.n = i
        for s in slots:
            setattr(self, s.name, s.sl)

    def __len__(self) -> int:
        return self.n

    def slot(self, name: str) -> StateSlot:
        for s in self.rows:
            if s.name == name:
                return s
        raise KeyError(name)

    def names(self) -> tuple[str, ...]:
        return tuple(s.name for s in self.rows)

    def table(self) -> str:
        """The layout as a text table (for docs and ``coiltrack perf``)."""
        lines = [f"{self.name}: {self.n} states", "  name  index  size  unit     meaning"]
        for s in self.rows:
            lines.append(f"  {s.name:<5} {s.index:>5}  {s.size:>4}  {s.unit:<8} {s.meaning}")
        return "\n".join(lines)


#: thesis ch. 2, eq 2.15: x = [theta_e, b_e, d_e]
ORIENTATION_LAYOUT = StateLayout("orientation (thesis eq 2.15)", (
    ("THETA", 3, "rad", "orientation error, sensor frame (R_true = R exp([theta]x))"),
    ("BIAS", 3, "rad/s", "gyroscope offset error, sensor frame (eq 2.3)"),
    ("DIST", 3, "1", "magnetic disturbance error, sensor frame, in units of |earth field| (eq 2.7)"),
))

_FUSION_ROWS = (
    ("POS", 3, "m", "position error, global frame (eq 6.10)"),
    ("VEL", 3, "m/s", "velocity error, global frame (eq 6.11)"),
    ("ORI", 3, "rad", "orientation error, global frame (Theta_true = exp([ori]x) Theta) (eq 6.12)"),
    ("ACC", 3, "m/s^2", "accelerometer error, sensor frame, first-order Markov (eq 6.13)"),
    ("GYR", 3, "rad/s", "gyroscope error, sensor frame, first-order Markov (eq 6.14)"),
    ("QM", 3, "m", "magnetic position error, global frame, white (eq 6.15)"),
    ("PSI", 3, "rad", "magnetic orientation error, global frame, white (eq 6.16)"),
)

#: thesis ch. 6, eq 6.9: the 21-state complementary error filter
FUSION_LAYOUT = StateLayout("fusion (thesis eq 6.9)", _FUSION_ROWS)

#: thesis ch. 6, eq 6.19: eq 6.9 plus the error of the ch. 2 orientation Xi
FUSION_XI_LAYOUT = StateLayout("fusion with Xi (thesis eq 6.19)", _FUSION_ROWS + (
    ("XI", 3, "rad", "error of the inertial-magnetic orientation Xi (ch. 2), global frame, white"),
))

# module-level names, so filter code reads P[POS, POS]
THETA = ORIENTATION_LAYOUT.THETA
BIAS = ORIENTATION_LAYOUT.BIAS
DIST = ORIENTATION_LAYOUT.DIST

POS = FUSION_XI_LAYOUT.POS
VEL = FUSION_XI_LAYOUT.VEL
ORI = FUSION_XI_LAYOUT.ORI
ACC = FUSION_XI_LAYOUT.ACC
GYR = FUSION_XI_LAYOUT.GYR
QM = FUSION_XI_LAYOUT.QM
PSI = FUSION_XI_LAYOUT.PSI
XI = FUSION_XI_LAYOUT.XI
#: the inertial navigation part (propagated states)
INS = slice(POS.start, GYR.stop)

assert FUSION_LAYOUT.n == 21 and FUSION_XI_LAYOUT.n == 24
assert all(getattr(FUSION_LAYOUT, s.name) == getattr(FUSION_XI_LAYOUT, s.name) for s in FUSION_LAYOUT.rows)


#: a pose covariance (solver, single-coil EKF): position error, orientation error
POSE_LAYOUT = StateLayout("pose covariance", (
    ("POS", 3, "m", "position error"),
    ("ORI", 3, "rad", "orientation error (rotation vector)"),
))
POSE_POS = POSE_LAYOUT.POS
POSE_ORI = POSE_LAYOUT.ORI


def schepers_layout(n_clones: int, n_gains: int = 0) -> StateLayout:
    """The single-coil EKF's table with ``n_clones`` pulses in flight and, with ``n_gains`` > 0,
    one gain error per coil after the clones (``[adaptive] coil_gain_sigma``: the measurement is
    ``y = (1 + g_c) I R^T B_c(p)``, a constant per coil that repeated pulses of that coil do not
    average away)."""
    rows = [
        ("POS", 3, "m", "position error, source frame"),
        ("VEL", 3, "m/s", "velocity error, source frame"),
        ("ORI", 3, "rad", "orientation error, sensor frame (R_true = R exp([ori]x))"),
        ("ACC", 3, "m/s^2", "accelerometer offset error, sensor frame, random walk"),
        ("GYR", 3, "rad/s", "gyroscope offset error, sensor frame, random walk"),
    ]
    for k in range(n_clones):
        rows.append((f"C{k}P", 3, "m", f"clone {k}: POS at the measurement time of pulse slot {k}"))
        rows.append((f"C{k}O", 3, "rad", f"clone {k}: ORI at the measurement time of pulse slot {k}"))
    if n_gains:
        rows.append(("GAIN", n_gains, "1", "coil gain errors, one per coil, constant: y = (1 + g_c) I R^T B_c(p)"))
        return StateLayout(f"schepers single-coil EKF ({n_clones} clones, {n_gains} coil gains)", tuple(rows))
    return StateLayout(f"schepers single-coil EKF ({n_clones} clones)", tuple(rows))


#: the single-coil EKF's default table (two pulses in flight)
SCHEPERS_LAYOUT = schepers_layout(2)
#: its propagated (inertial) part
SCHEPERS_CORE = slice(SCHEPERS_LAYOUT.POS.start, SCHEPERS_LAYOUT.GYR.stop)

assert all(getattr(SCHEPERS_LAYOUT, r) == getattr(FUSION_LAYOUT, r) for r in ("POS", "VEL", "ORI", "ACC", "GYR"))
assert SCHEPERS_CORE == INS


def fusion_measurement_layout(measurement_model: int) -> StateLayout:
    """Rows of the fusion filter's innovation (thesis sec 6.2.5): the position
    ``Phi q - p`` (``ZP``), ``log(Psi Theta^T)`` of the magnetic orientation
    (``ZPSI``, models 1 and 3: eqs 6.18, 6.21) and ``log(Xi Theta^T)`` of the
    ch. 2 orientation (``ZXI``, models 2 and 3: eqs 6.20, 6.21)."""
    rows = [("ZP", 3, "m", "position: Phi q - p, global frame")]
    if measurement_model != 2:
        rows.append(("ZPSI", 3, "rad", "magnetic orientation: log(Psi Theta^T), global frame"))
    if measurement_model != 1:
        rows.append(("ZXI", 3, "rad", "inertial-magnetic orientation: log(Xi Theta^T), global frame"))
    return StateLayout(f"fusion innovation, measurement model {measurement_model}", tuple(rows))


def fusion_layout(measurement_model: int) -> StateLayout:
    """The table for a measurement model (thesis sec 6.2.5): model 1 (eq 6.18)
    uses the 21 states of eq 6.9; models 2 and 3 (eqs 6.20, 6.21) add ``XI``."""
    return FUSION_LAYOUT if measurement_model == 1 else FUSION_XI_LAYOUT


#: Gietler et al. 2019 (``003_93f59c2e1c5b6c59.txt``), eq 11: the Brownian-motion state
#: X = [v, z, omega, theta] of the emitter platform relative to the receiver (eqs 6-12)
BROWNIAN_LAYOUT = StateLayout("Gietler Brownian motion (eq 11)", (
    ("VEL", 3, "m/s", "platform velocity v, receiver frame (eq 6)"),
    ("POS", 3, "m", "platform position z = emitter 1, receiver frame (eq 6)"),
    ("RATE", 3, "rad/s", "Euler-angle rate omega (eq 7)"),
    ("THETA", 3, "rad", "Z-Y-X Euler angles theta, R = Rz Ry Rx (eqs 3-4, 7)"),
))


def relative_layout(n_clones: int) -> StateLayout:
    """The tightly coupled tracker's table (``coiltrack.firmware.estimate.relative_inertial``):
    the sensor's pose and velocity relative to a moving source, in the source frame, the
    offsets of both IMUs, and per pulse in flight a clone of the pose at its measurement time.
    ``POS`` .. ``GYR`` have the indices of every inertial table (checked below)."""
    rows = [
        ("POS", 3, "m", "position error, source frame (sensor relative to the coil centre)"),
        ("VEL", 3, "m/s", "error of the relative world velocity Phi^T d(p_s - p_m)/dt, source frame"),
        ("ORI", 3, "rad", "orientation error, sensor frame (R_true = R exp([ori]x), R = Phi^T Theta)"),
        ("ACC", 3, "m/s^2", "sensor accelerometer offset error, sensor frame, random walk"),
        ("GYR", 3, "rad/s", "sensor gyroscope offset error, sensor frame, random walk"),
        ("SACC", 3, "m/s^2", "source accelerometer offset error, source frame, random walk (sec 6.5)"),
        ("SGYR", 3, "rad/s", "source gyroscope offset error, source frame, random walk"),
    ]
    for k in range(n_clones):
        rows.append((f"C{k}P", 3, "m", f"clone {k}: POS at the measurement time of pulse {k}"))
        rows.append((f"C{k}O", 3, "rad", f"clone {k}: ORI at the measurement time of pulse {k}"))
    return StateLayout(f"relative inertial tracker ({n_clones} clones)", tuple(rows))


#: the tightly coupled tracker's table for the three-coil burst (one clone per pulse)
RELATIVE_LAYOUT = relative_layout(3)

assert all(getattr(RELATIVE_LAYOUT, r) == getattr(FUSION_LAYOUT, r) for r in ("POS", "VEL", "ORI", "ACC", "GYR"))
