"""Firmware configuration: source, sensor, timing and limits.

Everything the firmware allocates is sized from one :class:`FirmwareConfig`
at start-up; it holds the one set of defaults. Its keys are grouped in
sections (:data:`SECTIONS`: ``link``, ``source``, ``timing``, ``pulse``,
``limits``, ``budget``, ``adaptive``, ``imu``, ``orientation``, ``fusion``,
``signing``, ``body``, ``pose``, ``recovery``, ``ac``, ``adaptive_policy``),
and a configuration file says them in TOML tables of the same names
(:func:`load_config`, :func:`config_from_dict`; ``examples/firmware.toml``).
A bad value is refused with a :class:`ConfigError` that names the key as
``section.key``.
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
class FirmwareConfig:
    # --- identity and links
    node_id: int = NODE_FIRMWARE
    coil_driver_id: int = NODE_COIL_DRIVER
    sensor_ids: tuple[int, ...] = (NODE_SENSOR_BASE,)
    # --- source
    coils: tuple[CoilConfig, ...] = field(default_factory=thesis_coils)
    field_model: str = "exact"             # "exact" | "dipole"
    hemisphere: tuple[float, float, float] = (1.0, 0.0, 0.0)
    # --- timing (thesis sec 5.3: 60 ms pulses, 600 ms cycle)
    tick_us: int = 1000
    pulse_us: int = 60_000
    cycle_us: int = 600_000
    spacing_us: int = 100_000              # pulse j starts at cycle start + j * spacing
    lead_us: int = 50_000                  # commands leave this long before the cycle
    first_cycle_us: int = 200_000          # start of the first cycle after boot
    heartbeat_us: int = 1_000_000
    # --- pulse-window extraction (Schepers sec 3.1, thesis sec 5.2)
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
    # --- work per tick (a slower board lowers them)
    track_budget_evals: int = 9            # coil field evaluations (field + Jacobian at one point) per tick;
                                           # a warm 3-coil solve is 3 (k + 2) of them (k LM steps, ~3): 9
                                           # spreads it over two ticks; on the compiled core ([core]) 18 fits
                                           # it in one (the LM step with its cost in C, ~7x cheaper), a board
                                           # 4x slower keeps 9 (coiltrack perf: max_field_evals_per_tick)
    replay_budget_steps: int = 8           # inertial steps of a delayed fusion update's replay per tick
    windows_budget: int = 4                # pulse windows closed per tick: with many sensors a pulse's
                                           # windows are all ready in the same tick (16 sensors: 1.2 ms)
    # the tick's other work charged against track_budget_evals, in field evaluations (0: not charged,
    # the solve takes the whole budget): a pulse window closed in the tick and an IMU sample the fused
    # tracker processed in it (track.magnetic, track.burst_fusion). A board whose worst tick must stay
    # under a bound sets them from `coiltrack perf`'s work classes; the solve then waits for ticks with
    # room, and its pose leaves later
    window_evals: int = 0
    imu_sample_evals: int = 0
    solve_ahead: bool = True               # idle ticks solve a burst once its last window's samples are
                                           # expected in; the burst uses that solution when its inputs are
                                           # the same bit for bit, else solves as before (pulsed excitation;
                                           # track.magnetic.MagneticTracker)
    solve_gate_probability: float = 1.0    # a warm-started solve whose cost fails this chi-square
                                           # probability is solved again from acquisition (1.0: never;
                                           # a moving sensor's burst fails any tighter gate, and the
                                           # acquisition then finds the same minimum at twice the work)
    # --- limits
    max_current_a: float = 2.0
    stale_us: int = 2_000_000
    coil_max_duty: float = 0.5             # the driver's on-time limit per coil ...
    coil_duty_window_us: int = 1_200_000   # ... over this window
    # --- actuation (coiltrack.firmware.track.single_coil_tracker; Schepers & Veltink 2010 sec. 2.1)
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
    adaptive_pulse_us: int = 0             # 0: pulse_us
    adaptive_lead_us: int = 10_000         # a single pulse is commanded this long before it starts
    adaptive_max_interval_us: int = 1_000_000
    adaptive_pos_noise: float = 0.0        # extra position process noise, m/sqrt(s)
    field_model_rel_sigma: float = 1e-3    # relative field-model error in the measurement covariance
    current_tolerance_a: float = 1e-3      # coil current regulation error (std), A
    mag_range_t: float = 163.835e-6        # magnetometer range (16 bit x 5 nT)
    saturation_margin: float = 0.9
    earth_field_max_t: float = 65e-6       # bound on any axis when no quiet sample is known
    nis_window: int = 8
    nis_gate_probability: float = 0.999
    reacquire_after: int = 6               # gated single-coil updates in a row before re-acquisition
    acquire_sigma_m: float = 0.1           # a position std beyond this: track lost, acquire again
    pose_every: int = 1                    # adaptive mode: a POSE every N IMU samples
    init_sigma_vel: float = 0.2            # m/s, velocity std when a pose (re)starts the filter
    init_sigma_ori_deg: float = 10.0       # orientation std added to a burst solution at a (re)start
    # --- inertial sensor model of the filters (per-sample std at imu_rate_hz; offsets)
    imu_rate_hz: float = 100.0
    imu_acc_sigma: float = 0.014           # m/s^2 per sample (MTx-class: 2e-3 m/s^2/sqrt(Hz) x sqrt(50 Hz))
    imu_gyro_sigma: float = 0.0062         # rad/s per sample (0.05 deg/s/sqrt(Hz) x sqrt(50 Hz))
    imu_acc_bias_sigma: float = 0.05       # m/s^2, initial offset std
    imu_gyro_bias_sigma: float = 0.02      # rad/s, initial offset std
    imu_acc_bias_rw: float = 2e-4          # m/s^2/sqrt(s)
    imu_gyro_bias_rw: float = 1.7e-4       # rad/s/sqrt(s)
    imu_timeout_us: int = 100_000
    gravity_mps2: tuple[float, float, float] = (0.0, 0.0, -9.81)   # gravity in the source frame
    # --- orientation filter (thesis ch. 2; coiltrack.firmware.estimate.orientation)
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
    # --- magnetic-inertial fusion (thesis ch. 6; coiltrack.firmware.estimate.magnetic_inertial)
    fusion: bool = True                     # fuse IMU_SAMPLEs when they arrive (fixed actuation)
    measurement_model: int = 3              # eq 6.18 (1), eq 6.20 (2), eq 6.21 (3)
    motion_compensation: bool = True        # bring the X, Y, Z pulses to one instant (sec 6.5)
    source_imu_id: int = 0                  # node of the source's IMU + magnetometer (0: source fixed)
    bias_tau_s: float = 3600.0              # correlation time of the IMU offsets (eqs 6.13-6.14), s
    fusion_gate_probability: float = 0.9999  # chi-square gate of the magnetic and orientation updates
    fusion_reinit_after: int = 3            # rejected magnetic updates in a row before a restart
    xi_sigma_floor: float = 0.005           # rad, added to Xi's tilt uncertainty (accelerometer offset / g)
    xi_heading_sigma_floor: float = 0.035   # rad, added to Xi's heading uncertainty (tilt error / cos(dip))
    xi_var_scale: float = 1.0
    mag_var_scale: float = 1.0              # scale of the solver covariance in the fusion update
    qm_sigma: float = 0.01                  # rad, initial std of the misalignment Q_M (eq 6.19)
    psi_sigma: float = 0.05                 # rad, initial std of Psi (eq 6.20)
    meas_sigma: float = 1e-5                # floor of the magnetic measurement std (m, rad)
    single_coil_iterations: int = 3         # iterations of the single-coil EKF's iterated update
    imu_ring_capacity: int = 64             # received IMU samples per node waiting for the tick
    fusion_replay_capacity: int = 128       # IMU samples kept to replay after a delayed magnetic update
    fusion_history_capacity: int = 128      # inertial poses kept for motion compensation
    pose_output_capacity: int = 16          # fused poses waiting to be sent
    # [signing]: MAVLink-2-style signatures on the commands that move coil current or change a
    # node's configuration (the schema's signable messages; coiltrack.protocol.signing)
    signing_key: str = ""                   # hex (64 digits) or a passphrase (SHA-256); "": unsigned
    signing_link_id: int = 1                # this sender's signing link (one byte in every signature)
    # --- a moving source (body-worn; coiltrack.firmware.track.burst_fusion.SourceInertial)
    source_acceleration: bool = True        # eq 6.8 with the source's measured acceleration (false: the
                                            # source taken as unaccelerated, Phi f_source = -g: for comparison)
    source_acc_sigma: float = 0.0           # m/s^2 per IMU sample: the error of Phi f_source in a_net (eq 6.8)
                                            # as white noise on the velocity; it covers the source orientation's
                                            # error times g on a moving source (0: the IMU's imu_acc_sigma)
    # --- pose solver of the burst trackers (coiltrack.firmware.compose)
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
    # --- recovery from faults (coiltrack.firmware.estimate.magnetic_inertial, track.burst_fusion)
    # a missed burst (cycle 0.6 s + 0.2 s latency) is bridged; past that the pose is inertial only
    dead_reckon_after_us: int = 1_000_000   # no accepted magnetic update this long: POSE_DEAD_RECKONING
    # inertial drift of an MTx-class IMU passes the magnetic accuracy within about 2 s (thesis sec 6.4)
    dead_reckon_limit_us: int = 2_000_000   # ... this long: not valid; the next update restarts the filter
    recovery_keep_biases: bool = True       # a restart keeps the IMU offsets while they are credible
    recovery_bias_gate_sigmas: float = 4.0  # credible: every offset within this many prior sigmas of zero
    # --- AC excitation (section [ac]; coiltrack.firmware.actuate.ac, coiltrack.firmware.measure.demod)
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
    # --- adaptive policy: the accuracy it holds, its feedback and its constants
    # (coiltrack.firmware.actuate.accuracy, coiltrack.firmware.track.single_coil_tracker)
    accuracy_target: str = "stated"         # "stated": the sigma_* bounds; "fixed": the accuracy the fixed
                                            #   X, Y, Z cycle of [timing] (pulse_us, spacing_us, cycle_us, the
                                            #   coils' nominal currents) would give, predicted beside the filter
    fixed_accuracy_ratio: float = 1.0       # "fixed": RMS wanted over the fixed cycle's (1: the same accuracy)
    adaptive_min_ratio: float = 0.9         # "fixed": sigma_min / sigma_max (how far one pulse brings it down)
    bound_on: str = "axis"                  # "axis": every pose variable within its bound; "trace": the sum
                                            #   of the position (orientation) variances within the sum of
                                            #   their bounds, the RMS error being the root of that trace
    reference_warmup_us: int = 2_000_000   # "fixed": for this long after a start the fixed cycle itself runs
                                            #   (the start's errors are too large for the linear eq 4), and its
                                            #   covariance is not yet part of the mean the policy holds
    reference_catchup: float = 2.0          # "fixed", warm-up: a pulse on demand between the cycle's pulses
                                            #   when a variance would pass this many times the cycle's own
    reference_avg_s: float = 30.0           # "fixed": the fixed cycle's variance is averaged since the start,
                                            #   then over this long (the RMS of a run is a mean over the run)
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
    # --- Gietler's Brownian-motion tracker (003_93f59c2e1c5b6c59.txt eqs 6-24; estimate/brownian.py)
    gietler_dt_s: float = 0.1               # s, filter step (sec III-C: delta tau = 0.1 s)
    gietler_sigma_v: float = 0.01           # m s^-3/2, velocity Wiener intensity of the model (eq 6)
    gietler_sigma_w: float = 0.1            # rad s^-3/2, Euler-rate Wiener intensity (eq 7)
    gietler_noise_var: float = 1e-4         # (A/m)^2, measurement noise variance per component (eq 14)
    gietler_p0: float = 0.1                 # initial covariance P0 = p0 I (eq 17; 0.1 in sec III-C)
    gietler_iterations: int = 3             # iterated EKF: at most this many linearisations per step (1: EKF)
    gietler_iter_tol: float = 1e-4          # m or rad: the iteration stops when no state moves more
    gietler_diverge_m: float = 2.0          # m: an estimate farther from the receiver has diverged
    # --- a sensor and source moving on the body (thesis sec 5.3, 6.3; docs/bodyworn.md)
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
    # --- calibration file (coiltrack.firmware.calibration; written by `coiltrack calibrate`)
    calibration_file: str = ""              # path of the calibration TOML read at start-up; "": none
    calibration_source: bool = True         # apply its [source] rows (coil moments, offsets) to the signal model
    calibration_sensors: bool = True        # apply its [sensor.N] models (magnetometer ellipsoid, IMU) on input
    calibration_max_gain_error: float = 0.2  # refuse a coil gain beyond 1 +- this (a file for another source)
    calibration_max_tilt_deg: float = 10.0  # refuse a coil moment this far from its configured axis
    # --- static distortion and pose quality (firmware_py.model.distortion, firmware_py.track.quality)
    distortion_apply: bool = True           # apply the calibration file's [distortion] map in the signal model
    quality_error_scale_m: float = 0.01     # m: the estimated position error at which the quality is 128
    quality_quiet_sigma_t: float = 2e-6     # T: tolerance of the quiet field's |B| against earth_field_t (0: unused)
    # --- [raab_cost] Raab's tracker at noise level (coiltrack.firmware.pose.raab; docs/raab.md, Work)
    raab_step_sigma: float = 0.05           # a linearly converging update also stops when its position and
                                            #   orientation steps are below this fraction of the smallest
                                            #   standard deviations of the last covariance (what remains is about
                                            #   one step: <= 0.05 sigma adds < 0.3 % to the variance); 0: off
    # --- compact IMU on the wire (protocol v2 IMU_DELTA; firmware_py/receive.py)
    imu_delta_rate_hz: float = 10.0         # nominal IMU_DELTA pairs per second per node (the bus budget: 16
                                            # sensors at 10 Hz); a pair 3.5 intervals after the last only anchors
    # a pair gives its twelve 120 Hz steps back at once: the fusion pipeline runs at most this many
    # IMU steps per sensor in one tick (the rest wait, 1 ms each), so a pair's arrival does not
    # make one tick twelve strapdown and covariance steps long; >= 2 keeps up with 1 kHz IMUs
    imu_steps_per_tick: int = 2
    # --- receive budget (firmware_py/receive.py): at most this many frames decoded and routed in one
    # tick, the rest left queued for the next ticks (counted); sixteen sensors' samples of one instant
    # are spread over two ticks instead of one 16-frame tick; one sensor's traffic (<= 3 frames a tick)
    # never reaches it; 0: no bound
    rx_frames_per_tick: int = 8
    # bytes the receive queue holds at most (a board's RX buffer); beyond it the queue is dropped and
    # counted (the decoder resynchronises at the next delimiter)
    rx_queue_bytes: int = 16384
    # --- [tight] the tightly coupled tracker (coiltrack.firmware.track.tight_fusion; docs/bodyworn.md)
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
    # --- [lm] when the pose solver's Levenberg-Marquardt stops (coiltrack.firmware.pose.solver): a step
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
    # --- [core] the numeric core (coiltrack.firmware.core): "compiled" (the C99 kernels; the Python
    # core, said once, where the extension is not built) or "python" (the reference)
    impl: str = "compiled"

    def validate(self) -> "FirmwareConfig":
        """Return self, or raise ConfigError naming the first bad key."""
        def need(key, ok, msg):
            if not ok:
                raise ConfigError(key, msg)

        for name in ("tick_us", "pulse_us", "cycle_us", "spacing_us", "lead_us", "heartbeat_us",
                     "baseline_us", "ring_capacity", "stale_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0,
                 f"must be a positive integer, got {v!r}")
        for name in ("track_budget_evals", "replay_budget_steps", "windows_budget"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v >= 1,
                 f"must be a positive integer, got {v!r}")
        for name in ("window_evals", "imu_sample_evals"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 1_000_000,
                 f"must be an integer in 0..1000000 (field evaluations), got {v!r}")
        need("solve_ahead", isinstance(self.solve_ahead, bool), f"must be true or false, got {self.solve_ahead!r}")
        for name in ("node_id", "coil_driver_id"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 255,
                 f"must be a node id in 1..255 (one byte of the frame header), got {v!r}")
        for name in ("settle_us", "fall_us", "guard_us", "first_cycle_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and v >= 0, f"must be a non-negative integer, got {v!r}")
        need("coils", 1 <= len(self.coils) <= 16, f"need 1..16 coils, got {len(self.coils)}")
        for i, c in enumerate(self.coils):
            k = f"coils[{i}]"
            need(k + ".radius", c.radius > 0 and math.isfinite(c.radius), f"must be > 0, got {c.radius!r}")
            need(k + ".turns", isinstance(c.turns, int) and c.turns > 0, f"must be a positive integer, got {c.turns!r}")
            need(k + ".axis", len(c.axis) == 3 and math.hypot(*c.axis) > 1e-9, "must be a non-zero 3-vector")
            need(k + ".center", len(c.center) == 3 and all(math.isfinite(v) for v in c.center), "must be a finite 3-vector")
            need(k + ".current", 0 < abs(c.current) <= self.max_current_a,
                 f"must be non-zero and within max_current_a={self.max_current_a}, got {c.current!r}")
            need(k + ".resistance", c.resistance > 0, f"must be > 0, got {c.resistance!r}")
        need("field_model", self.field_model in ("exact", "dipole"), f"must be 'exact' or 'dipole', got {self.field_model!r}")
        need("hemisphere", len(self.hemisphere) == 3 and math.hypot(*self.hemisphere) > 0, "must be a non-zero 3-vector")
        need("sensor_ids", len(self.sensor_ids) >= 1 and all(0 < s < 256 for s in self.sensor_ids),
             "must list 1..255 node ids")
        need("mag_sigma_t", self.mag_sigma_t > 0, f"must be > 0, got {self.mag_sigma_t!r}")
        need("mag_rate_hz", self.mag_rate_hz > 0, f"must be > 0, got {self.mag_rate_hz!r}")
        need("pulse_us", self.pulse_us > self.settle_us + self.guard_us,
             "must be longer than settle_us + guard_us")
        n = len(self.coils)
        need("spacing_us", n == 1 or self.spacing_us >= self.pulse_us + self.fall_us + self.baseline_us + self.guard_us,
             "the quiet gap between pulses must hold fall_us + baseline_us + guard_us")
        need("cycle_us", self.cycle_us >= (n - 1) * self.spacing_us + self.pulse_us + self.fall_us + self.baseline_us,
             "cycle too short for all pulses and the trailing baseline")
        need("lead_us", self.lead_us < self.cycle_us, "must be shorter than cycle_us")
        samples_per_cycle = self.cycle_us * 1e-6 * self.mag_rate_hz
        need("ring_capacity", self.ring_capacity >= 2 * samples_per_cycle,
             f"must hold two cycles of samples (>= {int(2 * samples_per_cycle)})")
        self._validate_actuation(need)
        self._validate_fusion(need)
        self._validate_signing(need)
        self._validate_pose(need)
        self._validate_recovery(need)
        self._validate_ac(need)
        self._validate_gietler(need)
        self._validate_body_motion(need)
        self._validate_calibration(need)
        self._validate_quality(need)
        self._validate_raab_cost(need)
        need("impl", self.impl in ("compiled", "python"), f"must be 'compiled' or 'python', got {self.impl!r}")
        need("imu_delta_rate_hz", isinstance(self.imu_delta_rate_hz, (int, float))
             and not isinstance(self.imu_delta_rate_hz, bool) and 0.0 < self.imu_delta_rate_hz <= 10_000.0,
             f"must be a rate in (0, 10000] Hz, got {self.imu_delta_rate_hz!r}")
        v = self.imu_steps_per_tick
        need("imu_steps_per_tick", isinstance(v, int) and not isinstance(v, bool) and 2 <= v <= 1000,
             f"must be an integer in 2..1000 (IMU steps per sensor per tick), got {v!r}")
        v = self.rx_frames_per_tick
        need("rx_frames_per_tick", isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 100_000,
             f"must be an integer in 0..100000 (0: no bound), got {v!r}")
        v = self.rx_queue_bytes
        need("rx_queue_bytes", isinstance(v, int) and not isinstance(v, bool) and 1024 <= v <= 1 << 24,
             f"must be an integer in 1024..16777216 bytes, got {v!r}")
        self._validate_tight(need)
        for name in ("lm_step_tol", "lm_cost_tol"):
            v = getattr(self, name)
            need(name, isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 < v < 1,
                 f"must be a number in (0, 1), got {v!r}")
        v = self.lm_step_sigma
        need("lm_step_sigma", isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and 0 <= v <= 1,
             f"must be a number in [0, 1] (standard deviations; 0: not used), got {v!r}")
        return self

    def _validate_tight(self, need) -> None:
        """Keys of the tightly coupled tracker (section ``tight``)."""
        fin = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        for name in ("tight_fusion", "tight_source_bias_states"):
            need(name, isinstance(getattr(self, name), bool), f"must be true or false, got {getattr(self, name)!r}")
        v = self.tight_source_imu_position_m
        need("tight_source_imu_position_m", len(v) == 3 and all(fin(c) and abs(c) <= 1.0 for c in v),
             f"must be a finite 3-vector within 1 m of the coil centre, got {v!r}")
        v = self.tight_acc_noise
        need("tight_acc_noise", fin(v) and 0 <= v <= 100, f"must be a density in [0, 100] m/s^2/sqrt(Hz), got {v!r}")
        v = self.tight_init_sigma_vel
        need("tight_init_sigma_vel", fin(v) and 0 < v <= 100, f"must be a speed in (0, 100] m/s, got {v!r}")
        v = self.tight_valid_sigma_m
        need("tight_valid_sigma_m", fin(v) and 0 <= v <= 10, f"must be a distance in [0, 10] m (0: off), got {v!r}")
        v = self.tight_quiet_every
        need("tight_quiet_every", isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 100_000,
             f"must be a number of IMU steps in [0, 100000] (0: no quiet-field update), got {v!r}")
        v = self.tight_quiet_sigma_t
        need("tight_quiet_sigma_t", fin(v) and 0 < v < 1e-3, f"must be a field in T, 0 < sigma < 1e-3, got {v!r}")
        v = self.tight_lost_sigma_m
        need("tight_lost_sigma_m", fin(v) and 0 < v <= 10, f"must be a distance in (0, 10] m, got {v!r}")
        need("tight_fusion", not self.tight_fusion or (self.actuation == "fixed" and self.excitation == "pulsed"
                                                       and not self.single_coil_fusion),
             "needs the fixed pulsed cycle (actuation = 'fixed', excitation = 'pulsed', single_coil_fusion = false)")

    def _validate_signing(self, need) -> None:
        need("signing_key", isinstance(self.signing_key, str), f"must be a string, got {self.signing_key!r}")
        need("signing_link_id", isinstance(self.signing_link_id, int) and not isinstance(self.signing_link_id, bool)
             and 0 <= self.signing_link_id <= 255, f"must be an integer in 0..255, got {self.signing_link_id!r}")

    def signing_key_bytes(self) -> bytes:
        """The signing key (empty: commands unsigned); see :func:`coiltrack.protocol.signing.key_from_text`."""
        from coiltrack.protocol.signing import key_from_text

        return key_from_text(self.signing_key) if self.signing_key else b""

    def _validate_pose(self, need) -> None:
        """Keys of the pose solver (``coiltrack.firmware.compose``, ``pose.raab``)."""
        fin = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        need("pose_solver", self.pose_solver in ("lm", "raab"), f"must be 'lm' or 'raab', got {self.pose_solver!r}")
        for name in ("raab_iterations", "raab_acquire_iterations"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 1000,
                 f"must be an integer in 1..1000, got {v!r}")
        for name in ("raab_step_tol", "raab_refresh"):
            v = getattr(self, name)
            need(name, fin(v) and 0 < v < 1, f"must be a number in (0, 1), got {v!r}")
        need("raab_correction", isinstance(self.raab_correction, bool),
             f"must be true or false, got {self.raab_correction!r}")
        for name in ("raab_start_position", "raab_start_euler_deg"):
            v = getattr(self, name)
            need(name, len(v) == 3 and all(fin(c) for c in v), "must be a finite 3-vector")
        need("working_range_m", fin(self.working_range_m) and self.working_range_m > 0,
             f"must be a positive number of metres, got {self.working_range_m!r}")

    def _validate_recovery(self, need) -> None:
        """Keys of the ``recovery`` section."""
        for name in ("dead_reckon_after_us", "dead_reckon_limit_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0,
                 f"must be a positive integer, got {v!r}")
        need("dead_reckon_limit_us", self.dead_reckon_limit_us >= self.dead_reckon_after_us,
             f"must be at least dead_reckon_after_us ({self.dead_reckon_after_us})")
        need("recovery_keep_biases", isinstance(self.recovery_keep_biases, bool),
             f"must be true or false, got {self.recovery_keep_biases!r}")
        v = self.recovery_bias_gate_sigmas
        need("recovery_bias_gate_sigmas", isinstance(v, (int, float)) and not isinstance(v, bool)
             and math.isfinite(v) and v > 0, f"must be a positive number, got {v!r}")

    def _validate_ac(self, need) -> None:
        """Keys of the AC excitation; the frequency plan is checked by
        :func:`coiltrack.firmware.actuate.ac_plan.check_plan`."""
        from coiltrack.firmware.actuate.ac_plan import check_plan

        fin = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        need("excitation", self.excitation in ("pulsed", "ac"), f"must be 'pulsed' or 'ac', got {self.excitation!r}")
        for name in ("ac_window_us", "ac_hop_us", "ac_lead_us", "ac_status_timeout_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0, f"must be a positive integer, got {v!r}")
        for name in ("ac_start_us", "ac_settle_us", "mag_integration_us", "ac_harmonics", "mains_harmonics"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v >= 0,
                 f"must be a non-negative integer, got {v!r}")
        need("ac_current_a", fin(self.ac_current_a) and 0.0 <= self.ac_current_a <= self.max_current_a,
             f"must be in [0, max_current_a={self.max_current_a}], got {self.ac_current_a!r}")
        need("ac_min_separation_hz", fin(self.ac_min_separation_hz) and self.ac_min_separation_hz > 0,
             f"must be a positive number, got {self.ac_min_separation_hz!r}")
        need("ac_distortion_ratio", fin(self.ac_distortion_ratio) and self.ac_distortion_ratio > 0,
             f"must be a positive number, got {self.ac_distortion_ratio!r}")
        need("ac_distortion_probability", self.ac_distortion_probability in (0.99, 0.999, 0.9999, 1.0)
             and (self.ac_distortion_probability == 1.0 or 3 * len(self.coils) <= 12),
             f"must be 0.99, 0.999, 0.9999 (up to 4 coils) or 1.0 (no test), got {self.ac_distortion_probability!r}")
        need("mains_hz", all(fin(f) and f > 0 for f in self.mains_hz), "must list positive frequencies (Hz)")
        need("ac_window_us", self.ac_window_us % self.ac_hop_us == 0, "must be a multiple of ac_hop_us")
        if self.excitation != "ac":
            return
        need("actuation", self.actuation == "fixed" and not self.single_coil_fusion,
             "AC excitation drives every coil all the time: needs actuation = 'fixed', single_coil_fusion = false")
        bad = check_plan(self.ac_freqs_hz, len(self.coils), self.mag_rate_hz, self.ac_window_us,
                         self.ac_min_separation_hz, self.ac_harmonics, self.mains_hz, self.mains_harmonics)
        if bad is not None:
            raise ConfigError(*bad)
        need("ring_capacity", self.ring_capacity >= 4 * self.ac_window_us * 1e-6 * self.mag_rate_hz,
             f"must hold four demodulation blocks of samples (>= {int(4 * self.ac_window_us * 1e-6 * self.mag_rate_hz)})")

    def _validate_fusion(self, need) -> None:
        """Keys of the orientation filter and the magnetic-inertial fusion
        (``coiltrack.firmware.estimate.orientation``, ``coiltrack.firmware.estimate.magnetic_inertial``)."""
        fin = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        for name in ("acc_motion_sigma", "bias_tau_s", "xi_var_scale", "mag_var_scale", "earth_field_t",
                     "theta0_sigma", "freefall_tolerance", "qm_sigma", "psi_sigma", "meas_sigma"):
            v = getattr(self, name)
            need(name, fin(v) and v > 0, f"must be a positive number, got {v!r}")
        for name in ("dist_smoothing", "acc_corr_time_s", "dist_sigma", "dist_norm_gain", "dist_dip_gain", "xi_sigma_floor",
                     "xi_heading_sigma_floor"):
            v = getattr(self, name)
            need(name, fin(v) and v >= 0, f"must be a non-negative number, got {v!r}")
        need("dist_corr", fin(self.dist_corr) and 0.0 <= self.dist_corr <= 1.0,
             f"must be in [0, 1], got {self.dist_corr!r}")
        for name in ("mag_learn_samples", "ori_update_every", "fusion_reinit_after", "imu_ring_capacity",
                     "fusion_replay_capacity",
                     "fusion_history_capacity", "pose_output_capacity"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v >= 1,
                 f"must be a positive integer, got {v!r}")
        need("compass_guard_us", isinstance(self.compass_guard_us, int) and not isinstance(self.compass_guard_us, bool)
             and self.compass_guard_us >= 0, f"must be a non-negative integer, got {self.compass_guard_us!r}")
        for name in ("fusion", "motion_compensation"):
            need(name, isinstance(getattr(self, name), bool), f"must be true or false, got {getattr(self, name)!r}")
        need("measurement_model", self.measurement_model in (1, 2, 3) and not isinstance(self.measurement_model, bool),
             f"must be 1 (eq 6.18), 2 (eq 6.20) or 3 (eq 6.21), got {self.measurement_model!r}")
        need("fusion_gate_probability", self.fusion_gate_probability in (0.99, 0.999, 0.9999, 1.0),
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.fusion_gate_probability!r}")
        need("source_imu_id", isinstance(self.source_imu_id, int) and not isinstance(self.source_imu_id, bool)
             and 0 <= self.source_imu_id < 256 and self.source_imu_id not in self.sensor_ids
             and self.source_imu_id not in (self.node_id, self.coil_driver_id),
             f"must be 0 (none) or a node id other than the sensors', the driver's and the firmware's, "
             f"got {self.source_imu_id!r}")
        g = math.sqrt(sum(v * v for v in self.gravity_mps2)) if len(self.gravity_mps2) == 3 else 0.0
        need("gravity_mps2", g > 1.0, "must be a 3-vector of the local gravity, |g| > 1 m/s^2")
        period_us = 1e6 / self.imu_rate_hz
        need("fusion_replay_capacity", self.fusion_replay_capacity * period_us >= self.cycle_us,
             f"must hold a cycle of IMU samples (>= {int(math.ceil(self.cycle_us / period_us))})")
        need("fusion_history_capacity", self.fusion_history_capacity * period_us >= self.cycle_us,
             f"must hold a cycle of inertial poses (>= {int(math.ceil(self.cycle_us / period_us))})")
        need("source_acceleration", isinstance(self.source_acceleration, bool),
             f"must be true or false, got {self.source_acceleration!r}")
        need("source_acc_sigma", isinstance(self.source_acc_sigma, (int, float))
             and not isinstance(self.source_acc_sigma, bool) and math.isfinite(self.source_acc_sigma)
             and self.source_acc_sigma >= 0, f"must be a non-negative number, got {self.source_acc_sigma!r}")

    def _validate_actuation(self, need) -> None:
        """Keys of the adaptive mode and the inertial model (``coiltrack.firmware.track.single_coil_tracker``)."""
        fin = lambda v: isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)  # noqa: E731
        need("actuation", self.actuation in ("fixed", "adaptive"),
             f"must be 'fixed' or 'adaptive', got {self.actuation!r}")
        need("single_coil_fusion", isinstance(self.single_coil_fusion, bool),
             f"must be true or false, got {self.single_coil_fusion!r}")
        for name in ("sigma_max_pos_m", "sigma_min_pos_m", "sigma_max_ori_deg", "sigma_min_ori_deg",
                     "adaptive_min_current_a", "adaptive_max_current_a", "mag_range_t", "imu_rate_hz",
                     "imu_acc_sigma", "imu_gyro_sigma", "acquire_sigma_m", "init_sigma_vel"):
            v = getattr(self, name)
            need(name, fin(v) and v > 0, f"must be a positive number, got {v!r}")
        for name in ("sigma_range_ref_m", "sigma_range_exp_pos", "sigma_range_exp_ori",
                     "adaptive_pos_noise", "field_model_rel_sigma", "current_tolerance_a", "earth_field_max_t",
                     "init_sigma_ori_deg",
                     "imu_acc_bias_sigma",
                     "imu_gyro_bias_sigma", "imu_acc_bias_rw", "imu_gyro_bias_rw"):
            v = getattr(self, name)
            need(name, fin(v) and v >= 0, f"must be a non-negative number, got {v!r}")
        need("sigma_min_pos_m", self.sigma_min_pos_m <= self.sigma_max_pos_m, "must not exceed sigma_max_pos_m")
        need("sigma_min_ori_deg", self.sigma_min_ori_deg <= self.sigma_max_ori_deg,
             "must not exceed sigma_max_ori_deg")
        need("adaptive_max_current_a", self.adaptive_max_current_a <= self.max_current_a,
             f"must be within max_current_a={self.max_current_a}")
        need("adaptive_currents_a", all(fin(c) and 0 < c <= self.adaptive_max_current_a
                                        for c in self.adaptive_currents_a),
             f"every candidate current must be in (0, adaptive_max_current_a={self.adaptive_max_current_a}]")
        for name in ("single_coil_iterations", "adaptive_current_levels", "adaptive_lead_us", "adaptive_max_interval_us", "nis_window",
                     "reacquire_after", "pose_every", "imu_timeout_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0,
                 f"must be a positive integer, got {v!r}")
        need("adaptive_pulse_us", isinstance(self.adaptive_pulse_us, int) and (
            self.adaptive_pulse_us == 0 or self.adaptive_pulse_us > self.settle_us + self.guard_us),
             "must be 0 (use pulse_us) or longer than settle_us + guard_us")
        if self.actuation == "adaptive":
            # the settled part of a pulse must hold min_pulse_samples besides the first and last
            pl = self.adaptive_pulse_us or self.pulse_us
            n = int((pl - self.settle_us - self.guard_us) * 1e-6 * self.mag_rate_hz) - 1
            need("adaptive_pulse_us" if self.adaptive_pulse_us else "pulse_us", n >= self.min_pulse_samples,
                 f"a {pl} us pulse gives about {max(n, 0)} usable samples at {self.mag_rate_hz} Hz, "
                 f"fewer than min_pulse_samples={self.min_pulse_samples}")
        need("coil_max_duty", fin(self.coil_max_duty) and 0 < self.coil_max_duty <= 1,
             f"must be in (0, 1], got {self.coil_max_duty!r}")
        need("coil_duty_window_us", isinstance(self.coil_duty_window_us, int)
             and not isinstance(self.coil_duty_window_us, bool) and self.coil_duty_window_us > 0,
             f"must be a positive integer, got {self.coil_duty_window_us!r}")
        need("saturation_margin", fin(self.saturation_margin) and 0 < self.saturation_margin <= 1,
             f"must be in (0, 1], got {self.saturation_margin!r}")
        need("solve_gate_probability", self.solve_gate_probability in (0.99, 0.999, 0.9999, 1.0),
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.solve_gate_probability!r}")
        need("nis_gate_probability", self.nis_gate_probability in (0.99, 0.999, 0.9999, 1.0),
             f"must be 0.99, 0.999, 0.9999 or 1.0 (no gate), got {self.nis_gate_probability!r}")
        need("gravity_mps2", len(self.gravity_mps2) == 3 and all(fin(v) for v in self.gravity_mps2),
             "must be a finite 3-vector")
        self._validate_policy(need, fin)

    def _validate_policy(self, need, fin) -> None:
        """Keys of section ``adaptive_policy``."""
        need("accuracy_target", self.accuracy_target in ("stated", "fixed"),
             f"must be 'stated' or 'fixed', got {self.accuracy_target!r}")
        need("bound_on", self.bound_on in ("axis", "trace"), f"must be 'axis' or 'trace', got {self.bound_on!r}")
        need("pulse_length", self.pulse_length in ("fixed", "chosen"),
             f"must be 'fixed' or 'chosen', got {self.pulse_length!r}")
        need("nis_feedback", isinstance(self.nis_feedback, bool), f"must be true or false, got {self.nis_feedback!r}")
        for name in ("fixed_accuracy_ratio", "reference_avg_s", "reference_catchup", "nis_linear_fraction",
                     "nis_alarm_z",
                     "saturation_sigmas"):
            v = getattr(self, name)
            need(name, fin(v) and v > 0, f"must be a positive number, got {v!r}")
        for name in ("nis_feedback_max", "nis_alarm_excess", "nis_max_scale"):
            v = getattr(self, name)
            need(name, fin(v) and v >= 1, f"must be a number >= 1, got {v!r}")
        for name in ("adaptive_min_ratio", "duty_margin"):
            v = getattr(self, name)
            need(name, fin(v) and 0 < v <= 1, f"must be in (0, 1], got {v!r}")
        for name in ("reference_warmup_us", "nis_feedback_updates", "nis_forget_us", "no_imu_us", "flip_every_us",
                     "decision_refresh_us"):
            v = getattr(self, name)
            need(name, isinstance(v, int) and not isinstance(v, bool) and v > 0,
                 f"must be a positive integer, got {v!r}")

    def _validate_gietler(self, need) -> None:
        """Keys of Gietler's Brownian-motion tracker (``coiltrack.firmware.estimate.brownian``)."""
        for name in ("gietler_dt_s", "gietler_sigma_v", "gietler_sigma_w", "gietler_noise_var", "gietler_p0",
                     "gietler_iter_tol", "gietler_diverge_m"):
            v = getattr(self, name)
            need(name, isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0,
                 f"must be a positive number, got {v!r}")
        v = self.gietler_iterations
        need("gietler_iterations", isinstance(v, int) and not isinstance(v, bool) and 1 <= v <= 100,
             f"must be an integer in 1..100 (1: the plain EKF), got {v!r}")

    def _validate_body_motion(self, need) -> None:
        """Keys of the body-worn motion handling (section ``body_motion``)."""
        need("baseline_gyro", isinstance(self.baseline_gyro, bool), f"must be true or false, got {self.baseline_gyro!r}")
        need("compass_heading_only", isinstance(self.compass_heading_only, bool),
             f"must be true or false, got {self.compass_heading_only!r}")
        v = self.acc_adapt_gain
        need("acc_adapt_gain", isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v >= 0,
             f"must be a finite number >= 0 (0: off), got {v!r}")
        v = self.acc_adapt_tau_s
        need("acc_adapt_tau_s", isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and v > 0,
             f"must be a positive number of seconds, got {v!r}")

    def _validate_calibration(self, need) -> None:
        """Keys of section ``calibration`` (the file itself is checked when it is read)."""
        need("calibration_file", isinstance(self.calibration_file, str),
             f"must be a path (string), got {self.calibration_file!r}")
        for name in ("calibration_source", "calibration_sensors"):
            need(name, isinstance(getattr(self, name), bool), f"must be true or false, got {getattr(self, name)!r}")
        v = self.calibration_max_gain_error
        need("calibration_max_gain_error", isinstance(v, (int, float)) and not isinstance(v, bool)
             and 0 < v < 1, f"must be a number in (0, 1), got {v!r}")
        v = self.calibration_max_tilt_deg
        need("calibration_max_tilt_deg", isinstance(v, (int, float)) and not isinstance(v, bool)
             and 0 < v <= 90, f"must be a number of degrees in (0, 90], got {v!r}")

    def _validate_quality(self, need) -> None:
        """Keys of sections ``distortion`` and ``quality``."""
        need("distortion_apply", isinstance(self.distortion_apply, bool),
             f"must be true or false, got {self.distortion_apply!r}")
        v = self.quality_error_scale_m
        need("quality_error_scale_m", isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= 10.0,
             f"must be a distance in m, 0 < d <= 10, got {v!r}")
        v = self.quality_quiet_sigma_t
        need("quality_quiet_sigma_t", isinstance(v, (int, float)) and not isinstance(v, bool) and 0 <= v < 1e-3,
             f"must be a field in T, 0 <= sigma < 1e-3 (0: no quiet-field term), got {v!r}")

    def _validate_raab_cost(self, need) -> None:
        """Keys of Raab's tracker's work (``coiltrack.firmware.pose.raab``)."""
        v = self.raab_step_sigma
        need("raab_step_sigma", isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
             and 0 <= v < 1, f"must be a number in [0, 1) (0: no noise-level stop), got {v!r}")


#: the sections of the configuration and their keys (TOML tables of the same names)
SECTIONS: dict[str, tuple[str, ...]] = {
    "link": ("node_id", "coil_driver_id", "sensor_ids", "source_imu_id", "heartbeat_us", "stale_us"),
    "source": ("coils", "field_model", "hemisphere"),
    "timing": ("tick_us", "pulse_us", "cycle_us", "spacing_us", "lead_us", "first_cycle_us"),
    "pulse": ("settle_us", "fall_us", "guard_us", "baseline_us", "min_pulse_samples", "min_baseline_samples",
              "drift_limit_t", "mag_sigma_t", "mag_rate_hz", "ring_capacity", "mag_range_t", "saturation_margin",
              "earth_field_max_t"),
    "limits": ("max_current_a", "coil_max_duty", "coil_duty_window_us", "current_tolerance_a"),
    "budget": ("track_budget_evals", "replay_budget_steps", "solve_gate_probability", "windows_budget",
               "solve_ahead", "window_evals", "imu_sample_evals"),
    "adaptive": ("actuation", "single_coil_fusion", "sigma_max_pos_m", "sigma_min_pos_m", "sigma_max_ori_deg",
                 "sigma_min_ori_deg", "sigma_range_ref_m", "sigma_range_exp_pos", "sigma_range_exp_ori",
                 "adaptive_currents_a", "adaptive_min_current_a", "adaptive_max_current_a",
                 "adaptive_current_levels", "adaptive_pulse_us", "adaptive_lead_us", "adaptive_max_interval_us",
                 "adaptive_pos_noise", "field_model_rel_sigma", "nis_window", "nis_gate_probability",
                 "reacquire_after", "acquire_sigma_m", "pose_every", "init_sigma_vel", "init_sigma_ori_deg",
                 "single_coil_iterations"),
    "imu": ("imu_rate_hz", "imu_acc_sigma", "imu_gyro_sigma", "imu_acc_bias_sigma", "imu_gyro_bias_sigma",
            "imu_acc_bias_rw", "imu_gyro_bias_rw", "imu_timeout_us", "gravity_mps2", "imu_ring_capacity"),
    "orientation": ("acc_motion_sigma", "acc_corr_time_s", "dist_corr", "dist_sigma", "dist_norm_gain",
                    "dist_dip_gain", "mag_learn_samples", "compass_guard_us", "ori_update_every", "earth_field_t",
                    "dist_smoothing", "theta0_sigma", "freefall_tolerance"),
    "fusion": ("fusion", "measurement_model", "motion_compensation", "bias_tau_s", "fusion_gate_probability",
               "fusion_reinit_after", "xi_sigma_floor", "xi_heading_sigma_floor", "xi_var_scale", "mag_var_scale",
               "fusion_replay_capacity", "fusion_history_capacity", "pose_output_capacity", "qm_sigma",
               "psi_sigma", "meas_sigma"),
    "signing": ("signing_key", "signing_link_id"),
    "body": ("source_acceleration", "source_acc_sigma"),
    "pose": ("pose_solver", "raab_iterations", "raab_acquire_iterations", "raab_step_tol", "raab_refresh",
             "raab_correction", "raab_start_position", "raab_start_euler_deg", "working_range_m"),
    "recovery": ("dead_reckon_after_us", "dead_reckon_limit_us", "recovery_keep_biases", "recovery_bias_gate_sigmas"),
    "ac": ("excitation", "ac_freqs_hz", "ac_current_a", "ac_window_us", "ac_hop_us", "ac_start_us", "ac_lead_us", "ac_settle_us",
           "ac_status_timeout_us",
           "ac_min_separation_hz", "ac_harmonics", "mains_hz", "mains_harmonics", "mag_integration_us",
           "ac_distortion_ratio", "ac_distortion_probability"),
    "adaptive_policy": ("accuracy_target", "fixed_accuracy_ratio", "adaptive_min_ratio", "bound_on",
                        "reference_avg_s", "reference_warmup_us", "reference_catchup",
                        "nis_feedback",
                        "nis_feedback_updates", "nis_feedback_max", "nis_linear_fraction", "nis_forget_us",
                        "nis_alarm_z", "nis_alarm_excess", "nis_max_scale", "no_imu_us", "flip_every_us",
                        "duty_margin", "saturation_sigmas", "decision_refresh_us", "pulse_length"),
    "gietler": ("gietler_dt_s", "gietler_sigma_v", "gietler_sigma_w", "gietler_noise_var", "gietler_p0",
                "gietler_iterations", "gietler_iter_tol", "gietler_diverge_m"),
    "body_motion": ("baseline_gyro", "acc_adapt_gain", "acc_adapt_tau_s", "compass_heading_only"),
    "calibration": ("calibration_file", "calibration_source", "calibration_sensors", "calibration_max_gain_error",
                    "calibration_max_tilt_deg"),
    "distortion": ("distortion_apply",),
    "quality": ("quality_error_scale_m", "quality_quiet_sigma_t"),
    "raab_cost": ("raab_step_sigma",),
    "imu_delta": ("imu_delta_rate_hz", "imu_steps_per_tick"),
    "receive": ("rx_frames_per_tick", "rx_queue_bytes"),
    "tight": ("tight_fusion", "tight_source_imu_position_m", "tight_acc_noise", "tight_source_bias_states",
              "tight_lost_sigma_m", "tight_init_sigma_vel", "tight_valid_sigma_m", "tight_quiet_every",
              "tight_quiet_sigma_t"),
    "lm": ("lm_step_tol", "lm_cost_tol", "lm_step_sigma"),
    "core": ("impl",),
}
SECTION_OF = {k: sec for sec, keys in SECTIONS.items() for k in keys}
_SIMPLE = {f.name for f in fields(FirmwareConfig)} - {"coils"}
_COIL_KEYS = {f.name for f in fields(CoilConfig)}
assert set(SECTION_OF) == _SIMPLE | {"coils"}, set(SECTION_OF) ^ (_SIMPLE | {"coils"})


def qualified(key: str) -> str:
    """``pulse_us`` -> ``timing.pulse_us``; ``coils[0].radius`` -> ``source.coils[0].radius``."""
    head = key.split("[", 1)[0].split(".", 1)[0]
    sec = SECTION_OF.get(head)
    return f"{sec}.{key}" if sec and not key.startswith(sec + ".") else key


def config_to_dict(cfg: FirmwareConfig) -> dict:
    """The configuration as TOML-shaped sections (lists for tuples)."""
    out: dict = {}
    for sec, keys in SECTIONS.items():
        d = {}
        for k in keys:
            v = getattr(cfg, k)
            if k == "coils":
                v = [{f.name: (list(getattr(c, f.name)) if isinstance(getattr(c, f.name), tuple)
                               else getattr(c, f.name)) for f in fields(CoilConfig)} for c in v]
            elif isinstance(v, tuple):
                v = list(v)
            d[k] = v
        out[sec] = d
    return out


def config_from_dict(d: dict, base: FirmwareConfig | None = None) -> FirmwareConfig:
    """Build and validate a config from a TOML-shaped dict of sections
    (``{"timing": {"pulse_us": 40000}, ...}``) over ``base``; unknown
    sections and keys, and keys outside their section, are refused."""
    flat = {}
    for sec, table in d.items():
        if sec not in SECTIONS:
            where = SECTION_OF.get(sec)
            raise ConfigError(sec, f"belongs in section [{where}]" if where else "unknown section")
        if not isinstance(table, dict):
            raise ConfigError(sec, "must be a table")
        for key, value in table.items():
            if SECTION_OF.get(key) != sec:
                where = SECTION_OF.get(key)
                raise ConfigError(f"{sec}.{key}", f"belongs in section [{where}]" if where else "unknown key")
            flat[key] = value
    return _from_flat(flat, base)


def _from_flat(d: dict, base: FirmwareConfig | None) -> FirmwareConfig:
    base = base or FirmwareConfig()
    kw = {}
    for key, value in d.items():
        if key == "coils":
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
            kw["coils"] = tuple(coils)
        elif key in _SIMPLE:
            default = getattr(base, key)
            if isinstance(default, tuple):
                if not isinstance(value, list):
                    raise ConfigError(key, f"must be an array, got {value!r}")
                value = tuple(value)
            elif isinstance(default, bool):
                if not isinstance(value, bool):
                    raise ConfigError(key, f"must be true or false, got {value!r}")
            elif isinstance(default, int):
                if not isinstance(value, int) or isinstance(value, bool):
                    raise ConfigError(key, f"must be an integer, got {value!r}")
            elif isinstance(default, float):
                if not isinstance(value, (int, float)) or isinstance(value, bool):
                    raise ConfigError(key, f"must be a number, got {value!r}")
                value = float(value)
            elif isinstance(default, str) and not isinstance(value, str):
                raise ConfigError(key, f"must be a string, got {value!r}")
            kw[key] = value
        else:
            raise ConfigError(key, "unknown key")
    return replace(base, **kw).validate()


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
