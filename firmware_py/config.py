"""Firmware configuration: source, sensor, timing and limits, in sections.

Everything the firmware allocates is sized from one :class:`FirmwareConfig`
at start-up. It holds one frozen dataclass per section (``cfg.timing.pulse_us``,
``cfg.pulse.mag_sigma_t``; :data:`SECTION_TYPES`), and those dataclasses hold
the one set of defaults. A configuration file says the sections as TOML tables
of the same names (:func:`load_config`, :func:`config_from_dict`;
``examples/firmware.toml``, written by ``python -m coiltrack.tools.docsgen
--example examples/firmware.toml``). A bad value is refused with a
:class:`ConfigError` that names the key as ``section.key``; a key of a section
that was merged or moved is refused naming its new place (:data:`MOVED`).

Changing keys in code: ``cfg.with_(timing={"pulse_us": 40_000})`` (a copy with
those keys of those sections replaced), or ``cfg.with_keys(**flat)`` where the
keys come as plain names (each key lives in one section: :data:`SECTION_OF`).
"""
from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field, fields, replace

from coiltrack.firmware.pose.solver import COST_TOL, STEP_TOL
from coiltrack.protocol.schema import NODE_COIL_DRIVER, NODE_FIRMWARE, NODE_SENSOR_BASE


class ConfigError(ValueError):
    """A configuration value is missing, of the wrong type or out of range.

    ``key`` is the qualified name (``timing.pulse_us``, ``source.coils[0].radius``)."""

    def __init__(self, key: str, message: str):
        key = qualified(key)
        super().__init__(f"config key '{key}': {message}")
        self.key = key
        self.message = message

    def __reduce__(self):
        """Picklable, so a worker process can hand it back."""
        return (ConfigError, (self.key, self.message))


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _fin(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _positive_ints(self, need, names) -> None:
    for name in names:
        v = getattr(self, name)
        need(name, _int(v) and v > 0, f"must be a positive integer, got {v!r}")


def _positive_numbers(self, need, names) -> None:
    for name in names:
        v = getattr(self, name)
        need(name, _fin(v) and v > 0, f"must be a positive number, got {v!r}")


def _non_negative_numbers(self, need, names) -> None:
    for name in names:
        v = getattr(self, name)
        need(name, _fin(v) and v >= 0, f"must be a non-negative number, got {v!r}")


def _bools(self, need, names) -> None:
    for name in names:
        v = getattr(self, name)
        need(name, isinstance(v, bool), f"must be true or false, got {v!r}")


#: the chi-square gate probabilities the firmware has quantiles for
GATES = (0.99, 0.999, 0.9999, 1.0)


@dataclass(frozen=True)
class CoilConfig:
    """One source coil: pose in the source frame, geometry, nominal current."""
    center: tuple[float, float, float] = (0.0, 0.0, 0.0)
    axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    radius: float = 0.055      # m
    turns: int = 50
    current: float = 1.5       # A, nominal pulse current
    resistance: float = 2.0    # ohm, for energy accounting


def thesis_coils() -> tuple[CoilConfig, ...]:
    """Three orthogonal coils of the thesis source (ch. 5.2.1: 50 turns,
    radius 5.5 cm, 1.5 A)."""
    return tuple(CoilConfig(axis=a) for a in ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)))


@dataclass(frozen=True)
class LinkConfig:
    """``[link]``: the node ids on the bus and the link's timeouts."""
    node_id: int = NODE_FIRMWARE
    coil_driver_id: int = NODE_COIL_DRIVER
    sensor_ids: tuple[int, ...] = (NODE_SENSOR_BASE,)
    source_imu_id: int = 0                  # node of the source's IMU + magnetometer (0: source fixed)
    heartbeat_us: int = 1_000_000
    stale_us: int = 2_000_000

    def check(self, need) -> None:
        _positive_ints(self, need, ("heartbeat_us", "stale_us"))
        for name in ("node_id", "coil_driver_id"):
            v = getattr(self, name)
            need(name, _int(v) and 1 <= v <= 255,
                 f"must be a node id in 1..255 (one byte of the frame header), got {v!r}")
        need("sensor_ids", len(self.sensor_ids) >= 1 and all(0 < s < 256 for s in self.sensor_ids),
             "must list 1..255 node ids")
        need("source_imu_id", _int(self.source_imu_id)
             and 0 <= self.source_imu_id < 256 and self.source_imu_id not in self.sensor_ids
             and self.source_imu_id not in (self.node_id, self.coil_driver_id),
             f"must be 0 (none) or a node id other than the sensors', the driver's and the firmware's, "
             f"got {self.source_imu_id!r}")


@dataclass(frozen=True)
class SourceConfig:
    """``[source]``: the coils (``[[source.coils]]``, one table each), their field model and the
    hemisphere the sensor is in."""
    coils: tuple[CoilConfig, ...] = field(default_factory=thesis_coils)
    field_model: str = "exact"             # "exact" | "dipole"
    hemisphere: tuple[float, float, float] = (1.0, 0.0, 0.0)

    def check(self, need) -> None:
        need("coils", 1 <= len(self.coils) <= 16, f"need 1..16 coils, got {len(self.coils)}")
        for i, c in enumerate(self.coils):
            k = f"coils[{i}]"
            need(k + ".radius", c.radius > 0 and math.isfinite(c.radius), f"must be > 0, got {c.radius!r}")
            need(k + ".turns", isinstance(c.turns, int) and c.turns > 0, f"must be a positive integer, got {c.turns!r}")
            need(k + ".axis", len(c.axis) == 3 and math.hypot(*c.axis) > 1e-9, "must be a non-zero 3-vector")
            need(k + ".center", len(c.center) == 3 and all(math.isfinite(v) for v in c.center),
                 "must be a finite 3-vector")
            need(k + ".resistance", c.resistance > 0, f"must be > 0, got {c.resistance!r}")
        need("field_model", self.field_model in ("exact", "dipole"),
             f"must be 'exact' or 'dipole', got {self.field_model!r}")
        need("hemisphere", len(self.hemisphere) == 3 and math.hypot(*self.hemisphere) > 0,
             "must be a non-zero 3-vector")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        for i, c in enumerate(self.coils):
            need(f"coils[{i}].current", 0 < abs(c.current) <= cfg.limits.max_current_a,
                 f"must be non-zero and within max_current_a={cfg.limits.max_current_a}, got {c.current!r}")


@dataclass(frozen=True)
class TimingConfig:
    """``[timing]``: the tick and the fixed X, Y, Z cycle (thesis sec 5.3: 60 ms pulses, 600 ms cycle)."""
    tick_us: int = 1000
    pulse_us: int = 60_000
    cycle_us: int = 600_000
    spacing_us: int = 100_000              # pulse j starts at cycle start + j * spacing
    lead_us: int = 50_000                  # commands leave this long before the cycle
    first_cycle_us: int = 200_000          # start of the first cycle after boot
    align_us: int = 450                    # wall-clock loop: a tick starts this long after the sample expected to complete a burst (0: the grid is not moved)
    align_slew_us: int = 100               # wall-clock loop: the most one tick's period moves while the grid is aligned

    def check(self, need) -> None:
        _positive_ints(self, need, ("tick_us", "pulse_us", "cycle_us", "spacing_us", "lead_us"))
        need("align_us", _int(self.align_us) and 0 <= self.align_us and (
            not _int(self.cycle_us) or self.align_us < self.cycle_us),
             f"must be an integer from 0 to below cycle_us, got {self.align_us!r}")
        need("align_slew_us", _int(self.align_slew_us) and 0 < self.align_slew_us and (
            not _int(self.tick_us) or 4 * self.align_slew_us <= self.tick_us),
             f"must be a positive integer of at most a quarter of tick_us, got {self.align_slew_us!r}")
        need("first_cycle_us", isinstance(self.first_cycle_us, int) and self.first_cycle_us >= 0,
             f"must be a non-negative integer, got {self.first_cycle_us!r}")
        need("lead_us", self.lead_us < self.cycle_us, "must be shorter than cycle_us")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        p = cfg.pulse
        need("pulse_us", self.pulse_us > p.settle_us + p.guard_us, "must be longer than settle_us + guard_us")
        n = len(cfg.source.coils)
        need("spacing_us", n == 1 or self.spacing_us >= self.pulse_us + p.fall_us + p.baseline_us + p.guard_us,
             "the quiet gap between pulses must hold fall_us + baseline_us + guard_us")
        need("cycle_us", self.cycle_us >= (n - 1) * self.spacing_us + self.pulse_us + p.fall_us + p.baseline_us,
             "cycle too short for all pulses and the trailing baseline")


@dataclass(frozen=True)
class PulseConfig:
    """``[pulse]``: pulse-window extraction and the magnetometer it reads (Schepers sec 3.1,
    thesis sec 5.2)."""
    settle_us: int = 3_000                 # current rise + eddy settle
    fall_us: int = 3_000                   # current fall + eddy settle after the pulse
    guard_us: int = 2_000
    baseline_us: int = 35_000              # quiet samples used each side
    min_pulse_samples: int = 3
    min_baseline_samples: int = 2
    drift_limit_t: float = 5e-6
    mag_sigma_t: float = 0.5e-7            # per-sample noise std, T
    mag_rate_hz: float = 120.0
    ring_capacity: int = 4096
    mag_range_t: float = 163.835e-6        # magnetometer range (16 bit x 5 nT)
    saturation_margin: float = 0.9
    earth_field_max_t: float = 65e-6       # bound on any axis when no quiet sample is known

    def check(self, need) -> None:
        _positive_ints(self, need, ("baseline_us", "ring_capacity"))
        for name in ("settle_us", "fall_us", "guard_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and v >= 0, f"must be a non-negative integer, got {v!r}")
        need("mag_sigma_t", self.mag_sigma_t > 0, f"must be > 0, got {self.mag_sigma_t!r}")
        need("mag_rate_hz", self.mag_rate_hz > 0, f"must be > 0, got {self.mag_rate_hz!r}")
        _positive_numbers(self, need, ("mag_range_t",))
        _non_negative_numbers(self, need, ("earth_field_max_t",))
        need("saturation_margin", _fin(self.saturation_margin) and 0 < self.saturation_margin <= 1,
             f"must be in (0, 1], got {self.saturation_margin!r}")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        samples_per_cycle = cfg.timing.cycle_us * 1e-6 * self.mag_rate_hz
        need("ring_capacity", self.ring_capacity >= 2 * samples_per_cycle,
             f"must hold two cycles of samples (>= {int(2 * samples_per_cycle)})")


@dataclass(frozen=True)
class LimitsConfig:
    """``[limits]``: what the coil driver may be asked for."""
    max_current_a: float = 2.0
    coil_max_duty: float = 0.5             # the driver's on-time limit per coil ...
    coil_duty_window_us: int = 1_200_000   # ... over this window
    current_tolerance_a: float = 1e-3      # coil current regulation error (std), A

    def check(self, need) -> None:
        need("coil_max_duty", _fin(self.coil_max_duty) and 0 < self.coil_max_duty <= 1,
             f"must be in (0, 1], got {self.coil_max_duty!r}")
        _positive_ints(self, need, ("coil_duty_window_us",))
        _non_negative_numbers(self, need, ("current_tolerance_a",))


@dataclass(frozen=True)
class BudgetConfig:
    """``[budget]``: the work per tick (a slower board lowers it)."""
    track_budget_evals: int = 27           # coil field evaluations (field + Jacobian at one point) per tick;
                                           # a warm 3-coil solve charges 3 (k + 3) of them with its hand-over
                                           # (k LM steps, ~3-5): 27 fits it in the tick its burst completes
                                           # on the compiled core (docs/tick-budget.md, "The budgets'
                                           # defaults"); a board 4x slower than the machine the figures were
                                           # measured on sets 9 (3-4 ticks; coiltrack perf:
                                           # max_field_evals_per_tick, field_eval_us)
    replay_budget_steps: int = 8           # inertial steps of a delayed fusion update's replay per tick
    solve_gate_probability: float = 1.0    # a warm-started solve whose cost fails this chi-square
                                           # probability is solved again from acquisition (1.0: never;
                                           # a moving sensor's burst fails any tighter gate, and the
                                           # acquisition then finds the same minimum at twice the work)
    windows_budget: int = 4                # pulse windows closed per tick: with many sensors a pulse's
                                           # windows are all ready in the same tick (16 sensors: 1.2 ms)
    handovers_per_tick: int = 4            # sensors' solves begun (handed over) per tick: with many
                                           # sensors solved ahead a burst's hand-overs (each a POSE
                                           # sent and the next sensor's begin, ~10 us of the compiled
                                           # core's glue here, charged only n evaluations) would
                                           # otherwise fill the tick (27 / 3 = 9 at once)
    solve_ahead: bool = True               # idle ticks solve a burst once its last window's samples are
                                           # expected in; the burst uses that solution when its inputs are
                                           # the same bit for bit, else solves as before (pulsed excitation;
                                           # track.magnetic.MagneticTracker)
    # the tick's other work charged against track_budget_evals, in field evaluations (0: not charged,
    # the solve takes the whole budget): a pulse window closed in the tick and an IMU sample the fused
    # tracker processed in it (track.magnetic, track.burst_fusion). A board whose worst tick must stay
    # under a bound sets them from `coiltrack perf`'s work classes; the solve then waits for ticks with
    # room, and its pose leaves later
    window_evals: int = 0
    imu_sample_evals: int = 0
    # a pair gives its twelve 120 Hz steps back at once: the fusion pipeline runs at most this many
    # IMU steps per sensor in one tick (the rest wait, 1 ms each), so a pair's arrival does not
    # make one tick twelve strapdown and covariance steps long; >= 2 keeps up with 1 kHz IMUs
    imu_steps_per_tick: int = 2

    def check(self, need) -> None:
        for name in ("track_budget_evals", "replay_budget_steps", "windows_budget", "handovers_per_tick"):
            v = getattr(self, name)
            need(name, _int(v) and v >= 1, f"must be a positive integer, got {v!r}")
        for name in ("window_evals", "imu_sample_evals"):
            v = getattr(self, name)
            need(name, _int(v) and 0 <= v <= 1_000_000,
                 f"must be an integer in 0..1000000 (field evaluations), got {v!r}")
        _bools(self, need, ("solve_ahead",))
        need("solve_gate_probability", self.solve_gate_probability in GATES,
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.solve_gate_probability!r}")
        v = self.imu_steps_per_tick
        need("imu_steps_per_tick", _int(v) and 2 <= v <= 1000,
             f"must be an integer in 2..1000 (IMU steps per sensor per tick), got {v!r}")


@dataclass(frozen=True)
class AdaptiveConfig:
    """``[adaptive]``: the actuation (``coiltrack.firmware.track.single_coil_tracker``; Schepers &
    Veltink 2010 sec. 2.1), its single-coil filter and its policy: the accuracy it holds, its
    feedback and its constants (``coiltrack.firmware.actuate.accuracy``)."""
    actuation: str = "fixed"               # "fixed" X/Y/Z cycle | "adaptive" single-coil pulses on demand
    single_coil_fusion: bool = False       # fixed cycle: each pulse updates the single-coil EKF (as adaptive)
    sigma_max_pos_m: float = 0.004         # pulse when a position std would exceed this
    sigma_min_pos_m: float = 0.003         # current chosen so the triggering std falls to this
    sigma_max_ori_deg: float = 0.5
    sigma_min_ori_deg: float = 0.4
    sigma_range_ref_m: float = 0.0         # > 0: the sigma bounds hold at this range and scale as
    sigma_range_exp_pos: float = 1.0       #   (r / sigma_range_ref_m)^exp (position, orientation)
    sigma_range_exp_ori: float = 1.0
    adaptive_currents_a: tuple[float, ...] = ()   # candidate currents; () = geometric ladder
    adaptive_min_current_a: float = 0.05
    adaptive_max_current_a: float = 1.5
    adaptive_current_levels: int = 16
    adaptive_current_step_a: float = 0.0    # > 0: the current is refined between the ladder's rungs to this
                                            #   resolution (0.001: the command's mA), no overshoot of sigma_min
    unreached_share: float = 0.0            # > 0: a pulse whose goal no allowed current reaches takes this share
                                            #   of the largest current's reduction at the least current; 0: the largest
    adaptive_pulse_us: int = 0             # 0: pulse_us
    adaptive_lead_us: int = 10_000         # a single pulse is commanded this long before it starts
    adaptive_max_interval_us: int = 1_000_000
    adaptive_pos_noise: float = 0.0        # extra position process noise, m/sqrt(s)
    field_model_rel_sigma: float = 1e-3    # relative field-model error in the measurement covariance
    nis_window: int = 8
    nis_gate_probability: float = 0.999
    reacquire_after: int = 6               # gated single-coil updates in a row before re-acquisition
    acquire_sigma_m: float = 0.1           # a position std beyond this: track lost, acquire again
    pose_every: int = 1                    # adaptive mode: a POSE every N IMU samples
    init_sigma_vel: float = 0.2            # m/s, velocity std when a pose (re)starts the filter
    init_sigma_ori_deg: float = 10.0       # orientation std added to a burst solution at a (re)start
    single_coil_iterations: int = 3         # iterations of the single-coil EKF's iterated update
    accuracy_target: str = "stated"         # "stated": the sigma_* bounds; "fixed": the accuracy the fixed
                                            #   X, Y, Z cycle of [timing] (pulse_us, spacing_us, cycle_us, the
                                            #   coils' nominal currents) would give, predicted beside the filter
    fixed_accuracy_ratio: float = 1.0       # "fixed": RMS wanted over the fixed cycle's (1: the same accuracy)
    adaptive_min_ratio: float = 0.9         # "fixed": sigma_min / sigma_max (how far one pulse brings it down)
    bound_on: str = "axis"                  # "axis": every pose variable within its bound; "trace": the sum
                                            #   of the position (orientation) variances within the sum of
                                            #   their bounds, the RMS error being the root of that trace
    reference_avg_s: float = 30.0           # "fixed": the fixed cycle's variance is averaged since the start,
                                            #   then over this long (the RMS of a run is a mean over the run)
    reference_warmup_us: int = 2_000_000   # "fixed": for this long after a start the fixed cycle itself runs
                                            #   (the start's errors are too large for the linear eq 4), and its
                                            #   covariance is not yet part of the mean the policy holds
    reference_settle_drop: float = 0.0      # "fixed": > 0: after a start the fixed cycle runs, and its reference's
                                            #   mean follows its present covariance, until the reference's gyro-
                                            #   offset variance falls by less than this fraction a cycle (0.05:
                                            #   about 10 s); 0: the mean from reference_warmup_us on
    reference_hold: str = "bound"           # "fixed": "bound": each decision holds the reference's mean variance;
                                            #   "mean": the filter's own running mean is held at the reference's,
                                            #   a deficit carried (coiltrack.firmware.actuate.accuracy_budget)
    reference_catchup: float = 2.0          # "fixed", warm-up: a pulse on demand between the cycle's pulses
                                            #   when a variance would pass this many times the cycle's own
    nis_feedback: bool = True               # bounds tightened by the NIS excess: where the innovations show
                                            #   the covariance understating the errors, pulse sooner
    nis_feedback_updates: int = 30          # updates the NIS excess is averaged over (exponential memory)
    nis_feedback_max: float = 4.0           # largest factor the variance bounds are divided by
    nis_linear_fraction: float = 0.1        # the NIS is tested only while the position std < this x range
    nis_forget_us: int = 2_000_000          # a verdict no update has tested for this long is forgotten
    nis_alarm_z: float = 3.09               # windowed NIS test: normal quantile of its bound (3.09: 99.9 %)
    nis_alarm_excess: float = 3.0           # ... and a mean NIS at least this many times its expectation
    nis_max_scale: float = 1e4              # largest inflation of the measurement covariance while disturbed
    no_imu_us: int = 1_000_000              # a sensor without IMU samples this long is acquired magnetically
    flip_every_us: int = 2_000_000          # set/reset flips commanded at least this often between pulses
    duty_margin: float = 0.95               # pulses kept below this fraction of the driver's duty limit
    saturation_sigmas: float = 3.0          # range check: the sensor assumed this many position stds closer
    decision_refresh_us: int = 20_000       # an unchanged prediction is decided again after this long
    pulse_length: str = "fixed"             # "fixed": every pulse adaptive_pulse_us (or pulse_us) long; "chosen":
                                            #   the length too, weighed against the current (least I^2 L),
                                            #   starts put on the magnetometer's sample clock
    baseline_sharing: str = "ignore"        # "ignore": each amplitude's own variance, as if independent (back to
                                            #   back, neighbours share a baseline: errors correlated ~0.24, the
                                            #   filter overconfident); "bound": a shared baseline counts twice its
                                            #   variance in each (estimate.shared_baseline); "apart": that, and
                                            #   pulses kept a baseline further apart so none is shared
    coil_gain_sigma: float = 0.0            # > 0: the single-coil filter estimates each coil's gain error (a
                                            #   constant, this prior std; y = (1 + g_c) I h_c), which repeated
                                            #   pulses of one coil do not average away; 0: none
    gain_in_choice: bool = True             # with coil_gain_sigma: the chooser's eq 4 adds each gain's variance
                                            #   to R along the field (coil_choice.CoilChooser._gain_term)
    reference_error: str = "filter"         # "fixed": "filter": the fixed cycle's filter's covariance; "actual": its
                                            #   errors' (a sensitivity covariance, the model error estimated from the
                                            #   live filter's NIS: actuate.accuracy_actual)
    saturation_knee: float = 0.0            # > 0: each coil's current at most where its field-model variance is this
                                            #   many times the white one (actuate.saturation_knee: information per
                                            #   joule 1 / (1 + knee) of the unsaturated); 0: no cap

    def check(self, need) -> None:
        need("actuation", self.actuation in ("fixed", "adaptive"),
             f"must be 'fixed' or 'adaptive', got {self.actuation!r}")
        _bools(self, need, ("single_coil_fusion", "gain_in_choice"))
        _positive_numbers(self, need, ("sigma_max_pos_m", "sigma_min_pos_m", "sigma_max_ori_deg", "sigma_min_ori_deg",
                                       "adaptive_min_current_a", "adaptive_max_current_a", "acquire_sigma_m",
                                       "init_sigma_vel"))
        _non_negative_numbers(self, need, ("sigma_range_ref_m", "sigma_range_exp_pos", "sigma_range_exp_ori",
                                           "adaptive_pos_noise", "field_model_rel_sigma", "init_sigma_ori_deg"))
        need("adaptive_current_step_a", _fin(self.adaptive_current_step_a) and 0.0 <= self.adaptive_current_step_a <= 0.1,
             f"must be in [0, 0.1] A, got {self.adaptive_current_step_a!r}")
        need("unreached_share", _fin(self.unreached_share) and 0.0 <= self.unreached_share <= 1.0,
             f"must be in [0, 1], got {self.unreached_share!r}")
        need("coil_gain_sigma", _fin(self.coil_gain_sigma) and 0.0 <= self.coil_gain_sigma <= 0.1,
             f"must be in [0, 0.1], got {self.coil_gain_sigma!r}")
        need("saturation_knee", _fin(self.saturation_knee) and 0.0 <= self.saturation_knee <= 100.0,
             f"must be in [0, 100], got {self.saturation_knee!r}")
        need("reference_settle_drop", _fin(self.reference_settle_drop) and 0.0 <= self.reference_settle_drop < 1.0,
             f"must be in [0, 1), got {self.reference_settle_drop!r}")
        need("sigma_min_pos_m", self.sigma_min_pos_m <= self.sigma_max_pos_m, "must not exceed sigma_max_pos_m")
        need("sigma_min_ori_deg", self.sigma_min_ori_deg <= self.sigma_max_ori_deg,
             "must not exceed sigma_max_ori_deg")
        need("adaptive_currents_a", all(_fin(c) and 0 < c <= self.adaptive_max_current_a
                                        for c in self.adaptive_currents_a),
             f"every candidate current must be in (0, adaptive_max_current_a={self.adaptive_max_current_a}]")
        _positive_ints(self, need, ("single_coil_iterations", "adaptive_current_levels", "adaptive_lead_us",
                                    "adaptive_max_interval_us", "nis_window", "reacquire_after", "pose_every"))
        need("nis_gate_probability", self.nis_gate_probability in GATES,
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.nis_gate_probability!r}")
        self._check_policy(need)

    def _check_policy(self, need) -> None:
        need("accuracy_target", self.accuracy_target in ("stated", "fixed"),
             f"must be 'stated' or 'fixed', got {self.accuracy_target!r}")
        need("reference_hold", self.reference_hold in ("bound", "mean"),
             f"must be 'bound' or 'mean', got {self.reference_hold!r}")
        need("reference_error", self.reference_error in ("filter", "actual"),
             f"must be 'filter' or 'actual', got {self.reference_error!r}")
        need("bound_on", self.bound_on in ("axis", "trace"), f"must be 'axis' or 'trace', got {self.bound_on!r}")
        need("pulse_length", self.pulse_length in ("fixed", "chosen"),
             f"must be 'fixed' or 'chosen', got {self.pulse_length!r}")
        need("baseline_sharing", self.baseline_sharing in ("bound", "apart", "ignore"),
             f"must be 'bound', 'apart' or 'ignore', got {self.baseline_sharing!r}")
        _bools(self, need, ("nis_feedback",))
        _positive_numbers(self, need, ("fixed_accuracy_ratio", "reference_avg_s", "reference_catchup",
                                       "nis_linear_fraction", "nis_alarm_z", "saturation_sigmas"))
        for name in ("nis_feedback_max", "nis_alarm_excess", "nis_max_scale"):
            v = getattr(self, name)
            need(name, _fin(v) and v >= 1, f"must be a number >= 1, got {v!r}")
        for name in ("adaptive_min_ratio", "duty_margin"):
            v = getattr(self, name)
            need(name, _fin(v) and 0 < v <= 1, f"must be in (0, 1], got {v!r}")
        _positive_ints(self, need, ("reference_warmup_us", "nis_feedback_updates", "nis_forget_us", "no_imu_us",
                                    "flip_every_us", "decision_refresh_us"))

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        need("adaptive_max_current_a", self.adaptive_max_current_a <= cfg.limits.max_current_a,
             f"must be within max_current_a={cfg.limits.max_current_a}")
        p = cfg.pulse
        need("adaptive_pulse_us", isinstance(self.adaptive_pulse_us, int) and (
            self.adaptive_pulse_us == 0 or self.adaptive_pulse_us > p.settle_us + p.guard_us),
             "must be 0 (use pulse_us) or longer than settle_us + guard_us")
        if self.actuation == "adaptive":
            # the settled part of a pulse must hold min_pulse_samples besides the first and last
            pl = self.adaptive_pulse_us or cfg.timing.pulse_us
            n = int((pl - p.settle_us - p.guard_us) * 1e-6 * p.mag_rate_hz) - 1
            need("adaptive_pulse_us" if self.adaptive_pulse_us else "pulse_us", n >= p.min_pulse_samples,
                 f"a {pl} us pulse gives about {max(n, 0)} usable samples at {p.mag_rate_hz} Hz, "
                 f"fewer than min_pulse_samples={p.min_pulse_samples}")


@dataclass(frozen=True)
class ImuConfig:
    """``[imu]``: the inertial sensor model of the filters (per-sample std at imu_rate_hz;
    offsets) and the IMU samples the firmware receives."""
    imu_rate_hz: float = 100.0
    imu_acc_sigma: float = 0.014           # m/s^2 per sample (MTx-class: 2e-3 m/s^2/sqrt(Hz) x sqrt(50 Hz))
    imu_gyro_sigma: float = 0.0062         # rad/s per sample (0.05 deg/s/sqrt(Hz) x sqrt(50 Hz))
    imu_acc_bias_sigma: float = 0.05       # m/s^2, initial offset std
    imu_gyro_bias_sigma: float = 0.02      # rad/s, initial offset std
    imu_acc_bias_rw: float = 2e-4          # m/s^2/sqrt(s)
    imu_gyro_bias_rw: float = 1.7e-4       # rad/s/sqrt(s)
    imu_timeout_us: int = 100_000
    gravity_mps2: tuple[float, float, float] = (0.0, 0.0, -9.81)   # gravity in the source frame
    imu_ring_capacity: int = 64             # received IMU samples per node waiting for the tick
    imu_delta_rate_hz: float = 10.0         # nominal IMU_DELTA pairs per second per node (the bus budget: 16
                                            # sensors at 10 Hz); a pair 3.5 intervals after the last only anchors

    def check(self, need) -> None:
        _positive_numbers(self, need, ("imu_rate_hz", "imu_acc_sigma", "imu_gyro_sigma"))
        _non_negative_numbers(self, need, ("imu_acc_bias_sigma", "imu_gyro_bias_sigma", "imu_acc_bias_rw",
                                           "imu_gyro_bias_rw"))
        _positive_ints(self, need, ("imu_timeout_us",))
        for name in ("imu_ring_capacity",):
            v = getattr(self, name)
            need(name, _int(v) and v >= 1, f"must be a positive integer, got {v!r}")
        need("gravity_mps2", len(self.gravity_mps2) == 3 and all(_fin(v) for v in self.gravity_mps2),
             "must be a finite 3-vector")
        g = math.sqrt(sum(v * v for v in self.gravity_mps2))
        need("gravity_mps2", g > 1.0, "must be a 3-vector of the local gravity, |g| > 1 m/s^2")
        need("imu_delta_rate_hz", _fin(self.imu_delta_rate_hz) and 0.0 < self.imu_delta_rate_hz <= 10_000.0,
             f"must be a rate in (0, 10000] Hz, got {self.imu_delta_rate_hz!r}")


@dataclass(frozen=True)
class OrientationConfig:
    """``[orientation]``: the orientation filter (thesis ch. 2; ``coiltrack.firmware.estimate.orientation``)."""
    acc_motion_sigma: float = 0.05          # m/s^2, motion acceleration taken as noise (w_a of eq 2.5)
    acc_corr_time_s: float = 0.0            # c_a = exp(-T / tau) of eq 2.5 (0: white)
    dist_corr: float = 0.99                 # c_d of eq 2.7, per sample
    dist_sigma: float = 2.0e-5              # floor of sigma_d, eq 2.12 (units of |earth field|)
    dist_norm_gain: float = 0.5             # sigma_m of eq 2.12
    dist_dip_gain: float = 0.5              # sigma_phi of eq 2.12 (per rad)
    mag_learn_samples: int = 120            # compass samples averaged for |m| and the dip (eqs 2.8-2.10)
    compass_guard_us: int = 5_000           # compass samples this close to a pulse are not used
    ori_update_every: int = 4               # inclination and compass updates every N IMU samples
    earth_field_t: float = 49e-6            # |earth field| the compass noise is scaled by (T)
    dist_smoothing: float = 0.05            # low-pass weight of norm and dip before eq 2.12
    theta0_sigma: float = 0.05              # rad, initial orientation uncertainty of the ch. 2 filter
    freefall_tolerance: float = 0.3         # relative |y_A| deviation from g beyond which no inclination update

    def check(self, need) -> None:
        _positive_numbers(self, need, ("acc_motion_sigma", "earth_field_t", "theta0_sigma", "freefall_tolerance"))
        _non_negative_numbers(self, need, ("dist_smoothing", "acc_corr_time_s", "dist_sigma", "dist_norm_gain",
                                           "dist_dip_gain"))
        need("dist_corr", _fin(self.dist_corr) and 0.0 <= self.dist_corr <= 1.0,
             f"must be in [0, 1], got {self.dist_corr!r}")
        for name in ("mag_learn_samples", "ori_update_every"):
            v = getattr(self, name)
            need(name, _int(v) and v >= 1, f"must be a positive integer, got {v!r}")
        need("compass_guard_us", _int(self.compass_guard_us) and self.compass_guard_us >= 0,
             f"must be a non-negative integer, got {self.compass_guard_us!r}")


@dataclass(frozen=True)
class FusionConfig:
    """``[fusion]``: the magnetic-inertial fusion (thesis ch. 6; ``coiltrack.firmware.estimate.magnetic_inertial``)."""
    fusion: bool = True                     # fuse IMU_SAMPLEs when they arrive (fixed actuation)
    measurement_model: int = 3              # eq 6.18 (1), eq 6.20 (2), eq 6.21 (3)
    motion_compensation: bool = True        # bring the X, Y, Z pulses to one instant (sec 6.5)
    bias_tau_s: float = 3600.0              # correlation time of the IMU offsets (eqs 6.13-6.14), s
    fusion_gate_probability: float = 0.9999  # chi-square gate of the magnetic and orientation updates
    fusion_reinit_after: int = 3            # rejected magnetic updates in a row before a restart
    xi_sigma_floor: float = 0.005           # rad, added to Xi's tilt uncertainty (accelerometer offset / g)
    xi_heading_sigma_floor: float = 0.035   # rad, added to Xi's heading uncertainty (tilt error / cos(dip))
    xi_var_scale: float = 1.0
    mag_var_scale: float = 1.0              # scale of the solver covariance in the fusion update
    fusion_replay_capacity: int = 128       # IMU samples kept to replay after a delayed magnetic update
    fusion_history_capacity: int = 128      # inertial poses kept for motion compensation
    pose_output_capacity: int = 16          # fused poses waiting to be sent
    qm_sigma: float = 0.01                  # rad, initial std of the misalignment Q_M (eq 6.19)
    psi_sigma: float = 0.05                 # rad, initial std of Psi (eq 6.20)
    meas_sigma: float = 1e-5                # floor of the magnetic measurement std (m, rad)

    def check(self, need) -> None:
        _positive_numbers(self, need, ("bias_tau_s", "xi_var_scale", "mag_var_scale", "qm_sigma", "psi_sigma",
                                       "meas_sigma"))
        _non_negative_numbers(self, need, ("xi_sigma_floor", "xi_heading_sigma_floor"))
        for name in ("fusion_reinit_after", "fusion_replay_capacity", "fusion_history_capacity",
                     "pose_output_capacity"):
            v = getattr(self, name)
            need(name, _int(v) and v >= 1, f"must be a positive integer, got {v!r}")
        _bools(self, need, ("fusion", "motion_compensation"))
        need("measurement_model", self.measurement_model in (1, 2, 3) and not isinstance(self.measurement_model, bool),
             f"must be 1 (eq 6.18), 2 (eq 6.20) or 3 (eq 6.21), got {self.measurement_model!r}")
        need("fusion_gate_probability", self.fusion_gate_probability in GATES,
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.fusion_gate_probability!r}")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        period_us = 1e6 / cfg.imu.imu_rate_hz
        cycle_us = cfg.timing.cycle_us
        need("fusion_replay_capacity", self.fusion_replay_capacity * period_us >= cycle_us,
             f"must hold a cycle of IMU samples (>= {int(math.ceil(cycle_us / period_us))})")
        need("fusion_history_capacity", self.fusion_history_capacity * period_us >= cycle_us,
             f"must hold a cycle of inertial poses (>= {int(math.ceil(cycle_us / period_us))})")


@dataclass(frozen=True)
class SigningConfig:
    """``[signing]``: MAVLink-2-style signatures on the commands that move coil current or change a
    node's configuration (the schema's signable messages; ``coiltrack.protocol.signing``)."""
    signing_key: str = ""                   # hex (64 digits) or a passphrase (SHA-256); "": unsigned
    signing_link_id: int = 1                # this sender's signing link (one byte in every signature)

    def check(self, need) -> None:
        need("signing_key", isinstance(self.signing_key, str), f"must be a string, got {self.signing_key!r}")
        need("signing_link_id", _int(self.signing_link_id) and 0 <= self.signing_link_id <= 255,
             f"must be an integer in 0..255, got {self.signing_link_id!r}")

    def key_bytes(self) -> bytes:
        """The signing key (empty: commands unsigned); see :func:`coiltrack.protocol.signing.key_from_text`."""
        from coiltrack.protocol.signing import key_from_text

        return key_from_text(self.signing_key) if self.signing_key else b""


@dataclass(frozen=True)
class BodyConfig:
    """``[body]``: a sensor and a source moving on the body (thesis sec 5.3, 6.3; docs/bodyworn.md):
    the moving source (``coiltrack.firmware.track.burst_fusion.SourceInertial``) and the body-worn
    sensor's motion handling."""
    source_acceleration: bool = True        # eq 6.8 with the source's measured acceleration (false: the
                                            # source taken as unaccelerated, Phi f_source = -g: for comparison)
    source_acc_sigma: float = 0.0           # m/s^2 per IMU sample: the error of Phi f_source in a_net (eq 6.8)
                                            # as white noise on the velocity; it covers the source orientation's
                                            # error times g on a moving source (0: the IMU's imu_acc_sigma)
    # the earth field turns in a turning sensor's frame during a pulse window (49 uT against a 0.4 uT
    # pulse at 45 cm); the linear baseline removes only its linear part: turn the window's samples with
    # the node's gyroscope first (coiltrack.firmware.measure.gyro_baseline). Needs the node's IMU_SAMPLEs.
    baseline_gyro: bool = False
    # one motion variance (orientation.acc_motion_sigma) cannot suit a still sensor and a walking trunk
    # (1-3 m/s^2 at 0.9-1.8 Hz): the ch. 2 filters' inclination variance grows by acc_adapt_gain x the
    # variance of y_A - g Z about its running mean over acc_adapt_tau_s (estimate.orientation); 0: off
    acc_adapt_gain: float = 0.0
    acc_adapt_tau_s: float = 1.0
    # the compass (eqs 2.21, 2.24) also corrects the inclination through the dip it learned at the start
    # (eqs 2.8-2.10); learned while the body moves, a wrong dip holds a tilt error (walking trunk: 9 deg):
    # true restricts the compass to the heading, the inclination left to the accelerometer
    compass_heading_only: bool = False

    def check(self, need) -> None:
        _bools(self, need, ("source_acceleration", "baseline_gyro", "compass_heading_only"))
        _non_negative_numbers(self, need, ("source_acc_sigma",))
        v = self.acc_adapt_gain
        need("acc_adapt_gain", _fin(v) and v >= 0, f"must be a finite number >= 0 (0: off), got {v!r}")
        v = self.acc_adapt_tau_s
        need("acc_adapt_tau_s", _fin(v) and v > 0, f"must be a positive number of seconds, got {v!r}")


@dataclass(frozen=True)
class PoseConfig:
    """``[pose]``: the pose solver of the burst trackers (``coiltrack.firmware.compose``): Raab's
    iterative tracker (``coiltrack.firmware.pose.raab``; docs/raab.md) or Kuipers + Levenberg-Marquardt
    (``coiltrack.firmware.pose.solver``), and the working volume."""
    pose_solver: str = "lm"                 # "lm": Kuipers + least squares | "raab": Raab's iterative tracker
    raab_iterations: int = 20               # Raab updates per burst with a tracked pose (1: one per pattern,
                                            #   as the paper); near the source each converges ~0.4x
    raab_acquire_iterations: int = 60       # Raab updates per burst without a pose (Fig. 8 acquisition)
    raab_step_tol: float = 1e-4             # converged: angle steps below this (rad), range step below this x range
    raab_refresh: float = 0.02              # evaluate the exact-loop correction again beyond this x range (rad)
    raab_correction: bool = True            # correct the dipole model to the exact loops (model.signal)
    raab_start_position: tuple[float, float, float] = (0.0, 0.0, 0.0)   # m; (0, 0, 0): hemisphere at the
                                            #   range of the field invariant
    raab_start_euler_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)  # psi, theta, phi of the start, deg
    # the working volume: a solution or a fused pose farther from the source is not a pose (a diverged
    # estimate); at 2 m the thesis source's field (18 nT) is below the magnetometer's noise
    working_range_m: float = 2.0
    # when Levenberg-Marquardt stops (coiltrack.firmware.pose.solver): a step
    # below lm_step_tol of the range (rad for the orientation), or a relative cost change below lm_cost_tol.
    # The defaults are the solver's own (STEP_TOL 1e-5, COST_TOL 1e-6). On roetenberg-bench (seed 1, 60 s)
    # lm_cost_tol = 1e-3 takes 3-4 LM iterations instead of 4-6 (the solve 2 ticks instead of 3 at the
    # median), gives 93.77 mm against 93.92 and pose latency p99 5.0 ms against 7.0 (README, Tick budget)
    lm_step_tol: float = STEP_TOL
    lm_cost_tol: float = COST_TOL
    # also stopped when an accepted step is shorter than this many standard deviations of the solution
    # (its length in the metric of the normal equations, sqrt(d^T A d): unlike lm_cost_tol, the same
    # whatever the size of the cost); 0 (the default): not used
    lm_step_sigma: float = 0.0
    raab_step_sigma: float = 0.05           # a linearly converging update also stops when its position and
                                            #   orientation steps are below this fraction of the smallest
                                            #   standard deviations of the last covariance (what remains is about
                                            #   one step: <= 0.05 sigma adds < 0.3 % to the variance); 0: off

    def check(self, need) -> None:
        need("pose_solver", self.pose_solver in ("lm", "raab"), f"must be 'lm' or 'raab', got {self.pose_solver!r}")
        for name in ("raab_iterations", "raab_acquire_iterations"):
            v = getattr(self, name)
            need(name, _int(v) and 1 <= v <= 1000, f"must be an integer in 1..1000, got {v!r}")
        for name in ("raab_step_tol", "raab_refresh"):
            v = getattr(self, name)
            need(name, _fin(v) and 0 < v < 1, f"must be a number in (0, 1), got {v!r}")
        _bools(self, need, ("raab_correction",))
        for name in ("raab_start_position", "raab_start_euler_deg"):
            v = getattr(self, name)
            need(name, len(v) == 3 and all(_fin(c) for c in v), "must be a finite 3-vector")
        need("working_range_m", _fin(self.working_range_m) and self.working_range_m > 0,
             f"must be a positive number of metres, got {self.working_range_m!r}")
        v = self.raab_step_sigma
        need("raab_step_sigma", _fin(v) and 0 <= v < 1,
             f"must be a number in [0, 1) (0: no noise-level stop), got {v!r}")
        for name in ("lm_step_tol", "lm_cost_tol"):
            v = getattr(self, name)
            need(name, _fin(v) and 0 < v < 1, f"must be a number in (0, 1), got {v!r}")
        v = self.lm_step_sigma
        need("lm_step_sigma", _fin(v) and 0 <= v <= 1,
             f"must be a number in [0, 1] (standard deviations; 0: not used), got {v!r}")


@dataclass(frozen=True)
class RecoveryConfig:
    """``[recovery]``: recovery from faults (``coiltrack.firmware.estimate.magnetic_inertial``,
    ``track.burst_fusion``)."""
    # a missed burst (cycle 0.6 s + 0.2 s latency) is bridged; past that the pose is inertial only
    dead_reckon_after_us: int = 1_000_000   # no accepted magnetic update this long: POSE_DEAD_RECKONING
    # inertial drift of an MTx-class IMU passes the magnetic accuracy within about 2 s (thesis sec 6.4)
    dead_reckon_limit_us: int = 2_000_000   # ... this long: not valid; the next update restarts the filter
    recovery_keep_biases: bool = True       # a restart keeps the IMU offsets while they are credible
    recovery_bias_gate_sigmas: float = 4.0  # credible: every offset within this many prior sigmas of zero

    def check(self, need) -> None:
        _positive_ints(self, need, ("dead_reckon_after_us", "dead_reckon_limit_us"))
        need("dead_reckon_limit_us", self.dead_reckon_limit_us >= self.dead_reckon_after_us,
             f"must be at least dead_reckon_after_us ({self.dead_reckon_after_us})")
        _bools(self, need, ("recovery_keep_biases",))
        _positive_numbers(self, need, ("recovery_bias_gate_sigmas",))


@dataclass(frozen=True)
class AcConfig:
    """``[ac]``: AC excitation (``coiltrack.firmware.actuate.ac``, ``coiltrack.firmware.measure.demod``)."""
    excitation: str = "pulsed"              # "pulsed" DC bursts | "ac" sinusoidal drive, synchronous demodulation
    ac_freqs_hz: tuple[float, ...] = (215.0, 315.0, 465.0)  # one per coil (frequency division); see ac_plan
    ac_current_a: float = 0.0               # current amplitude (peak) of every coil; 0: the coil's nominal current
    ac_window_us: int = 18_000              # demodulation block length (holds >= 1 cycle of every coil)
    ac_hop_us: int = 9_000                  # a new block every hop: one magnetic pose per hop (111 Hz)
    ac_start_us: int = 200_000              # drive switched on this long after boot
    ac_lead_us: int = 100_000               # the plan is sent this long before the switch-on
    ac_settle_us: int = 20_000              # blocks starting earlier than this after switch-on are not used (L/R)
    ac_status_timeout_us: int = 3_000_000   # no AC_DRIVE_STATUS for this long (driver reports each 1 s): plan again
    ac_min_separation_hz: float = 20.0      # coils, their harmonics and mains kept this far apart (aliased)
    ac_harmonics: int = 3                   # coil harmonics 2..N checked against the other coils
    mains_hz: tuple[float, ...] = (50.0, 60.0)
    mains_harmonics: int = 3                # mains harmonics 1..N checked against the coils
    mag_integration_us: int = 500           # the magnetometer's averaging time (its sinc response); 0: none
    ac_distortion_ratio: float = 0.02       # POSE_DISTORTED when |quadrature| / |in-phase| exceeds this ...
    ac_distortion_probability: float = 0.999  # ... and the quadrature's chi-square exceeds this quantile

    def check(self, need) -> None:
        need("excitation", self.excitation in ("pulsed", "ac"), f"must be 'pulsed' or 'ac', got {self.excitation!r}")
        _positive_ints(self, need, ("ac_window_us", "ac_hop_us", "ac_lead_us", "ac_status_timeout_us"))
        for name in ("ac_start_us", "ac_settle_us", "mag_integration_us", "ac_harmonics", "mains_harmonics"):
            v = getattr(self, name)
            need(name, _int(v) and v >= 0, f"must be a non-negative integer, got {v!r}")
        _positive_numbers(self, need, ("ac_min_separation_hz", "ac_distortion_ratio"))
        need("mains_hz", all(_fin(f) and f > 0 for f in self.mains_hz), "must list positive frequencies (Hz)")
        need("ac_window_us", self.ac_window_us % self.ac_hop_us == 0, "must be a multiple of ac_hop_us")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        """The current within the limits, the frequency plan (checked by
        :func:`coiltrack.firmware.actuate.ac_plan.check_plan`) and the ring for its blocks."""
        from coiltrack.firmware.actuate.ac_plan import check_plan

        need("ac_current_a", _fin(self.ac_current_a) and 0.0 <= self.ac_current_a <= cfg.limits.max_current_a,
             f"must be in [0, max_current_a={cfg.limits.max_current_a}], got {self.ac_current_a!r}")
        need("ac_distortion_probability", self.ac_distortion_probability in GATES
             and (self.ac_distortion_probability == 1.0 or 3 * len(cfg.source.coils) <= 12),
             f"must be 0.99, 0.999, 0.9999 (up to 4 coils) or 1.0 (no test), got {self.ac_distortion_probability!r}")
        if self.excitation != "ac":
            return
        need("actuation", cfg.adaptive.actuation == "fixed" and not cfg.adaptive.single_coil_fusion,
             "AC excitation drives every coil all the time: needs actuation = 'fixed', single_coil_fusion = false")
        p = cfg.pulse
        bad = check_plan(self.ac_freqs_hz, len(cfg.source.coils), p.mag_rate_hz, self.ac_window_us,
                         self.ac_min_separation_hz, self.ac_harmonics, self.mains_hz, self.mains_harmonics)
        if bad is not None:
            raise ConfigError(*bad)
        need("ring_capacity", p.ring_capacity >= 4 * self.ac_window_us * 1e-6 * p.mag_rate_hz,
             f"must hold four demodulation blocks of samples (>= {int(4 * self.ac_window_us * 1e-6 * p.mag_rate_hz)})")


@dataclass(frozen=True)
class CalibrationConfig:
    """``[calibration]``: the calibration file (``coiltrack.firmware.calibration``; written by
    ``coiltrack calibrate``). The file itself is checked when it is read."""
    calibration_file: str = ""              # path of the calibration TOML read at start-up; "": none
    calibration_source: bool = True         # apply its [source] rows (coil moments, offsets) to the signal model
    calibration_sensors: bool = True        # apply its [sensor.N] models (magnetometer ellipsoid, IMU) on input
    calibration_max_gain_error: float = 0.2  # refuse a coil gain beyond 1 +- this (a file for another source)
    calibration_max_tilt_deg: float = 10.0  # refuse a coil moment this far from its configured axis

    def check(self, need) -> None:
        need("calibration_file", isinstance(self.calibration_file, str),
             f"must be a path (string), got {self.calibration_file!r}")
        _bools(self, need, ("calibration_source", "calibration_sensors"))
        v = self.calibration_max_gain_error
        need("calibration_max_gain_error", _fin(v) and 0 < v < 1, f"must be a number in (0, 1), got {v!r}")
        v = self.calibration_max_tilt_deg
        need("calibration_max_tilt_deg", _fin(v) and 0 < v <= 90,
             f"must be a number of degrees in (0, 90], got {v!r}")


@dataclass(frozen=True)
class DistortionConfig:
    """``[distortion]``: static distortion (``coiltrack.firmware.model.distortion``)."""
    distortion_apply: bool = True           # apply the calibration file's [distortion] map in the signal model

    def check(self, need) -> None:
        _bools(self, need, ("distortion_apply",))


@dataclass(frozen=True)
class QualityConfig:
    """``[quality]``: the pose quality (``coiltrack.firmware.track.quality``)."""
    quality_error_scale_m: float = 0.01     # m: the estimated position error at which the quality is 128
    quality_quiet_sigma_t: float = 2e-6     # T: tolerance of the quiet field's |B| against earth_field_t (0: unused)

    def check(self, need) -> None:
        v = self.quality_error_scale_m
        need("quality_error_scale_m", _fin(v) and 0 < v <= 10.0, f"must be a distance in m, 0 < d <= 10, got {v!r}")
        v = self.quality_quiet_sigma_t
        need("quality_quiet_sigma_t", _fin(v) and 0 <= v < 1e-3,
             f"must be a field in T, 0 <= sigma < 1e-3 (0: no quiet-field term), got {v!r}")


@dataclass(frozen=True)
class ReceiveConfig:
    """``[receive]``: the receive budget (``firmware_py/receive.py``)."""
    # at most this many frames decoded and routed in one
    # tick, the rest left queued for the next ticks (counted); sixteen sensors' samples of one instant
    # are spread over two ticks instead of one 16-frame tick; one sensor's traffic (<= 3 frames a tick)
    # never reaches it; 0: no bound
    rx_frames_per_tick: int = 8
    # bytes the receive queue holds at most (a board's RX buffer); beyond it the queue is dropped and
    # counted (the decoder resynchronises at the next delimiter)
    rx_queue_bytes: int = 16384

    def check(self, need) -> None:
        v = self.rx_frames_per_tick
        need("rx_frames_per_tick", _int(v) and 0 <= v <= 100_000,
             f"must be an integer in 0..100000 (0: no bound), got {v!r}")
        v = self.rx_queue_bytes
        need("rx_queue_bytes", _int(v) and 1024 <= v <= 1 << 24,
             f"must be an integer in 1024..16777216 bytes, got {v!r}")


@dataclass(frozen=True)
class TightConfig:
    """``[tight]``: the tightly coupled tracker (``coiltrack.firmware.track.tight_fusion``; docs/bodyworn.md)."""
    # each pulse window's amplitude updates a relative inertial filter at its own instant instead of one
    # burst solution per cycle (the sensor moves during the 260 ms burst; thesis sec 6.5)
    tight_fusion: bool = False
    # the source module's position on the source (source frame, m): its accelerometer measures there
    # (the bench's SourceImuNode: 6 cm below the coil centre)
    tight_source_imu_position_m: tuple[float, float, float] = (0.0, 0.0, -0.06)
    # m/s^2/sqrt(Hz): acceleration noise beyond the accelerometers' own (an unmodelled vibration, the
    # module position's error under the source's angular acceleration); 0: the IMUs' densities only (on
    # roetenberg-flexion-back, 20 s, seed 1: 0.05 gives 23.8 mm fused, 0 gives 20.0 mm, NIS mean 3.1 of 3)
    tight_acc_noise: float = 0.0
    # the source IMU's accelerometer and gyroscope offsets as filter states (false: taken as zero)
    tight_source_bias_states: bool = True
    # a position std beyond this (m, after five cycles of windows since the start): track lost, started
    # again from the next burst solution (the filter starts from one burst, orientation a few degrees off:
    # on a walking trunk its position std passes 0.1 m before it has converged)
    tight_lost_sigma_m: float = 0.3
    # m/s, velocity std when a burst solution starts the filter (its velocity taken as zero): the speed
    # of the tracked segment relative to the source (the thigh in walking: up to 1 m/s, where 0.2 loses
    # the track twice in the first 4 s; on the trunk 1.0 makes the start 3x worse: 53.9 against 19.0 mm
    # fused on roetenberg-flexion-back, 20 s, seed 1)
    tight_init_sigma_vel: float = 0.2
    # m: a fused pose is sent VALID only while the filter's largest position std is at most this (after
    # a start the filter converges over a few cycles: its first seconds' poses are sent, not valid); 0: off
    tight_valid_sigma_m: float = 0.0
    # IMU steps between quiet-field updates (the sensor's field between pulses against the source
    # module's, b = R^T e: the relative orientation at the magnetometer's rate; needs source_imu_id);
    # 0: none
    tight_quiet_every: int = 4
    # T: std per axis of the quiet-field pair's difference b - R^T e (both magnetometers' noise and
    # set/reset residuals left after FlipOffset, the sample times' mismatch)
    tight_quiet_sigma_t: float = 0.1e-6

    def check(self, need) -> None:
        _bools(self, need, ("tight_fusion", "tight_source_bias_states"))
        v = self.tight_source_imu_position_m
        need("tight_source_imu_position_m", len(v) == 3 and all(_fin(c) and abs(c) <= 1.0 for c in v),
             f"must be a finite 3-vector within 1 m of the coil centre, got {v!r}")
        v = self.tight_acc_noise
        need("tight_acc_noise", _fin(v) and 0 <= v <= 100, f"must be a density in [0, 100] m/s^2/sqrt(Hz), got {v!r}")
        v = self.tight_init_sigma_vel
        need("tight_init_sigma_vel", _fin(v) and 0 < v <= 100, f"must be a speed in (0, 100] m/s, got {v!r}")
        v = self.tight_valid_sigma_m
        need("tight_valid_sigma_m", _fin(v) and 0 <= v <= 10, f"must be a distance in [0, 10] m (0: off), got {v!r}")
        v = self.tight_quiet_every
        need("tight_quiet_every", _int(v) and 0 <= v <= 100_000,
             f"must be a number of IMU steps in [0, 100000] (0: no quiet-field update), got {v!r}")
        v = self.tight_quiet_sigma_t
        need("tight_quiet_sigma_t", _fin(v) and 0 < v < 1e-3, f"must be a field in T, 0 < sigma < 1e-3, got {v!r}")
        v = self.tight_lost_sigma_m
        need("tight_lost_sigma_m", _fin(v) and 0 < v <= 10, f"must be a distance in (0, 10] m, got {v!r}")

    def check_with(self, cfg: "FirmwareConfig", need) -> None:
        need("tight_fusion", not self.tight_fusion or (cfg.adaptive.actuation == "fixed"
                                                       and cfg.ac.excitation == "pulsed"
                                                       and not cfg.adaptive.single_coil_fusion),
             "needs the fixed pulsed cycle (actuation = 'fixed', excitation = 'pulsed', single_coil_fusion = false)")


@dataclass(frozen=True)
class CoreConfig:
    """``[core]``: the numeric core (``coiltrack.firmware.core``)."""
    # "compiled" (the C99 kernels; the Python
    # core, said once, where the extension is not built) or "python" (the reference)
    impl: str = "compiled"

    def check(self, need) -> None:
        need("impl", self.impl in ("compiled", "python"), f"must be 'compiled' or 'python', got {self.impl!r}")


#: the sections of the configuration, in order, and the dataclass of each (TOML tables of the same names)
SECTION_TYPES: dict[str, type] = {
    "link": LinkConfig, "source": SourceConfig, "timing": TimingConfig, "pulse": PulseConfig,
    "limits": LimitsConfig, "budget": BudgetConfig, "adaptive": AdaptiveConfig, "imu": ImuConfig,
    "orientation": OrientationConfig, "fusion": FusionConfig, "signing": SigningConfig, "body": BodyConfig,
    "pose": PoseConfig, "recovery": RecoveryConfig, "ac": AcConfig, "calibration": CalibrationConfig,
    "distortion": DistortionConfig, "quality": QualityConfig, "receive": ReceiveConfig, "tight": TightConfig,
    "core": CoreConfig,
}


def _need(key, ok, msg) -> None:
    if not ok:
        raise ConfigError(key, msg)


@dataclass(frozen=True)
class FirmwareConfig:
    """The firmware's configuration: one frozen dataclass per section (:data:`SECTION_TYPES`)."""
    link: LinkConfig = field(default_factory=LinkConfig)
    source: SourceConfig = field(default_factory=SourceConfig)
    timing: TimingConfig = field(default_factory=TimingConfig)
    pulse: PulseConfig = field(default_factory=PulseConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    budget: BudgetConfig = field(default_factory=BudgetConfig)
    adaptive: AdaptiveConfig = field(default_factory=AdaptiveConfig)
    imu: ImuConfig = field(default_factory=ImuConfig)
    orientation: OrientationConfig = field(default_factory=OrientationConfig)
    fusion: FusionConfig = field(default_factory=FusionConfig)
    signing: SigningConfig = field(default_factory=SigningConfig)
    body: BodyConfig = field(default_factory=BodyConfig)
    pose: PoseConfig = field(default_factory=PoseConfig)
    recovery: RecoveryConfig = field(default_factory=RecoveryConfig)
    ac: AcConfig = field(default_factory=AcConfig)
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)
    distortion: DistortionConfig = field(default_factory=DistortionConfig)
    quality: QualityConfig = field(default_factory=QualityConfig)
    receive: ReceiveConfig = field(default_factory=ReceiveConfig)
    tight: TightConfig = field(default_factory=TightConfig)
    core: CoreConfig = field(default_factory=CoreConfig)

    def validate(self) -> "FirmwareConfig":
        """Return self, or raise ConfigError naming the first bad key: every section's own
        keys first, then the checks that join sections."""
        for name in SECTION_TYPES:
            getattr(self, name).check(_need)
        for name in SECTION_TYPES:
            sec = getattr(self, name)
            if hasattr(sec, "check_with"):
                sec.check_with(self, _need)
        return self

    def with_(self, **sections) -> "FirmwareConfig":
        """A copy with keys of some sections replaced (not validated):
        ``cfg.with_(timing={"pulse_us": 40_000}, pulse={"settle_us": 5_000})``; a section's value
        may also be a whole section dataclass."""
        kw = {}
        for name, change in sections.items():
            if name not in SECTION_TYPES:
                raise TypeError(f"FirmwareConfig has no section {name!r}"
                                + (f" ({name} is a key of [{SECTION_OF[name]}])" if name in SECTION_OF else ""))
            if isinstance(change, SECTION_TYPES[name]):
                kw[name] = change
                continue
            for key in change:
                if key not in _SECTION_KEYS[name]:
                    where = SECTION_OF.get(key)
                    raise TypeError(f"section [{name}] has no key {key!r}"
                                    + (f": it is {where}.{key}" if where else ""))
            kw[name] = replace(getattr(self, name), **change)
        return replace(self, **kw)

    def with_keys(self, **keys) -> "FirmwareConfig":
        """A copy with keys given by their plain names replaced (each key lives in one section,
        :data:`SECTION_OF`): for keyword overrides passed on as ``**kw``."""
        sections: dict[str, dict] = {}
        for key, value in keys.items():
            if key not in SECTION_OF:
                raise TypeError(f"FirmwareConfig has no key {key!r}" + (f" ({MOVED[key]})" if key in MOVED else ""))
            sections.setdefault(SECTION_OF[key], {})[key] = value
        return self.with_(**sections)

    def signing_key_bytes(self) -> bytes:
        """The signing key (empty: commands unsigned): :meth:`SigningConfig.key_bytes`."""
        return self.signing.key_bytes()

    def __getattr__(self, name):
        """Only reached for a missing attribute: a key read without its section gets an error
        that names its place."""
        if name in SECTION_OF:
            raise AttributeError(f"FirmwareConfig has no attribute {name!r}: it is cfg.{SECTION_OF[name]}.{name}")
        if name in MOVED:
            raise AttributeError(f"FirmwareConfig has no attribute {name!r}: {MOVED[name]}")
        raise AttributeError(f"{type(self).__name__!r} object has no attribute {name!r}")


#: the sections of the configuration and their keys (TOML tables of the same names)
SECTIONS: dict[str, tuple[str, ...]] = {name: tuple(f.name for f in fields(cls)) for name, cls in SECTION_TYPES.items()}
SECTION_OF = {k: sec for sec, keys in SECTIONS.items() for k in keys}
_SECTION_KEYS = {sec: frozenset(keys) for sec, keys in SECTIONS.items()}
_COIL_KEYS = {f.name for f in fields(CoilConfig)}
assert len(SECTION_OF) == sum(len(k) for k in SECTIONS.values()), "a key in two sections"

#: sections merged into another (an old file's table is refused naming the new one)
MERGED_SECTIONS = {"adaptive_policy": "adaptive", "body_motion": "body", "lm": "pose", "raab_cost": "pose",
                   "imu_delta": "imu or budget"}
_GIETLER = ("gietler_dt_s", "gietler_sigma_v", "gietler_sigma_w", "gietler_noise_var", "gietler_p0",
            "gietler_iterations", "gietler_iter_tol", "gietler_diverge_m")
#: keys that left the firmware's configuration, and where they went
MOVED: dict[str, str] = {
    **{k: "not a firmware key: a setting of the Gietler experiments' filter "
          "(coiltrack.tools.bench.gietler.GietlerFilterConfig; `coiltrack sweep --scenario gietler-air "
          f"--set gietler.{k}=V`)" for k in _GIETLER},
}


def qualified(key: str) -> str:
    """``pulse_us`` -> ``timing.pulse_us``; ``coils[0].radius`` -> ``source.coils[0].radius``."""
    head = key.split("[", 1)[0].split(".", 1)[0]
    sec = SECTION_OF.get(head)
    return f"{sec}.{key}" if sec and not key.startswith(sec + ".") else key


def _plain(v):
    if isinstance(v, CoilConfig):
        return {f.name: _plain(getattr(v, f.name)) for f in fields(CoilConfig)}
    if isinstance(v, tuple):
        return [_plain(x) for x in v]
    return v


def config_to_dict(cfg: FirmwareConfig) -> dict:
    """The configuration as TOML-shaped sections (lists for tuples)."""
    return {sec: {k: _plain(getattr(getattr(cfg, sec), k)) for k in keys} for sec, keys in SECTIONS.items()}


def _where(sec: str, key: str | None = None) -> str:
    """Why a section or key of a file is not taken: where it lives now, or that it is unknown."""
    if key is None:
        if sec in MERGED_SECTIONS:
            return f"section [{sec}] was merged into [{MERGED_SECTIONS[sec]}]: move its keys there"
        if sec in SECTION_OF:
            return f"belongs in section [{SECTION_OF[sec]}]"
        return "unknown section"
    if key in SECTION_OF:
        return f"belongs in section [{SECTION_OF[key]}] (write it as {SECTION_OF[key]}.{key})"
    if key in MOVED:
        return MOVED[key]
    return "unknown key"


def config_from_dict(d: dict, base: FirmwareConfig | None = None) -> FirmwareConfig:
    """Build and validate a config from a TOML-shaped dict of sections
    (``{"timing": {"pulse_us": 40000}, ...}``) over ``base``; unknown
    sections and keys, and keys outside their section, are refused naming
    where they belong."""
    base = base or FirmwareConfig()
    changes: dict[str, dict] = {}
    for sec, table in d.items():
        if sec not in SECTIONS:
            if isinstance(table, dict) and table and sec in MERGED_SECTIONS:
                key = next(iter(table))
                raise ConfigError(f"{sec}.{key}", _where(sec, key))
            raise ConfigError(sec, _where(sec))
        if not isinstance(table, dict):
            raise ConfigError(sec, "must be a table")
        for key, value in table.items():
            if SECTION_OF.get(key) != sec:
                raise ConfigError(f"{sec}.{key}", _where(sec, key))
            changes.setdefault(sec, {})[key] = _coerce(sec, key, value, getattr(getattr(base, sec), key))
    return base.with_(**changes).validate()


def _coils(value) -> tuple[CoilConfig, ...]:
    if not isinstance(value, list):
        raise ConfigError("coils", "must be an array of tables")
    coils = []
    for i, c in enumerate(value):
        if not isinstance(c, dict):
            raise ConfigError(f"coils[{i}]", "must be a table")
        for k in c:
            if k not in _COIL_KEYS:
                raise ConfigError(f"coils[{i}].{k}", "unknown key")
        cc = {k: (tuple(float(x) for x in v) if isinstance(v, list) else v) for k, v in c.items()}
        coils.append(CoilConfig(**cc))
    return tuple(coils)


def _coerce(sec: str, key: str, value, default):
    """A TOML value as the type of the key's default, or ConfigError naming ``section.key``."""
    name = f"{sec}.{key}"
    if key == "coils":
        return _coils(value)
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise ConfigError(name, f"must be an array, got {value!r}")
        return tuple(value)
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(name, f"must be true or false, got {value!r}")
    elif isinstance(default, int):
        if not isinstance(value, int) or isinstance(value, bool):
            raise ConfigError(name, f"must be an integer, got {value!r}")
    elif isinstance(default, float):
        if not isinstance(value, (int, float)) or isinstance(value, bool):
            raise ConfigError(name, f"must be a number, got {value!r}")
        return float(value)
    elif isinstance(default, str) and not isinstance(value, str):
        raise ConfigError(name, f"must be a string, got {value!r}")
    return value


def load_config(path) -> FirmwareConfig:
    """Read a TOML configuration file: one table per section of
    :data:`SECTIONS`, ``[[source.coils]]`` tables as in CoilConfig."""
    with open(path, "rb") as fh:
        data = fh.read()
    try:
        d = tomllib.loads(data.decode("utf-8-sig"))
    except UnicodeDecodeError as exc:
        raise ConfigError("<file>", f"{path} is not UTF-8 text (byte {data[exc.start]:#04x} at offset "
                                    f"{exc.start}): save it as UTF-8") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError("<file>", f"not valid TOML: {exc}") from None
    return config_from_dict(d)
