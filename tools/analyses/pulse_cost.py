"""What a coil's pulses cost in energy for the information they bring (``energy_bound``'s pulse model).

A pulse of current ``I`` and length ``T`` with quiet baselines of length ``B``
on each side is one amplitude measurement ``y = I u + noise`` (``u`` the coil's
field per ampere in the sensor frame). The firmware's extraction
(``firmware_py/measure/pulse.py``; Schepers & Veltink 2010,
``../shared/seeds/000_*`` sec. 3.1: "all samples except the first and the last
of each pulse") averages ``n_u`` in-pulse samples and subtracts a baseline
fitted to ``n_b`` quiet samples, so the filter's measurement variance per axis
(``firmware_py/estimate/single_coil.py``, ``update_single_coil``) is::

    r(I) = sigma^2 (1/n_u + 1/n_b) + (rho^2 I^2 + tau^2) |u|^2
         = a + b I^2,   a = sigma^2 c + tau^2 |u|^2,   b = rho^2 |u|^2

with ``sigma`` the per-sample noise (``mag_sigma_t``), ``rho`` the field
model's relative error (``field_model_rel_sigma``) and ``tau`` the current's
(``current_tolerance_a``, relative ``tau / I``). ``r`` is the same on the three
axes, so the pulse's Fisher information is ``s(I) J~`` with ``J~ = H_u^T H_u``
(``H_u`` the Jacobian per ampere, Schepers eqs 9-11) and the scalar weight
``s(I) = I^2 / (a + b I^2)``, which tends to ``1 / b = 1 / (rho |u|)^2`` as the
current grows: near the source the model error, not the noise, sets what a
pulse can tell.

**Cost of information in one window.** In a window of duration ``D`` a policy
gives coil ``k`` the information weight ``x_k`` with ``m`` pulses of one kind
(``T``, ``B``) at equal current (equal is cheapest: the cost below is convex
in ``s``). Then ``I^2 = a x / (m - b x)`` and the energy is the perspective
``m T a (x/m) / (1 - b x/m)``, jointly convex in ``(x, m)``; the pulses need
the time ``m (T + fall + B + guard)`` (consecutive pulses share a baseline:
the firmware's ``spacing_us >= pulse + fall + baseline + guard``), one coil at
a time, at most ``D`` in all, and ``I <= I_max`` (the driver's
``max_current_a`` and the magnetometer's range). ``m`` is relaxed to a real
number and kinds may be mixed: a relaxation, so the least energy found is a
lower bound. With a price ``mu`` on time, writing ``m = x (b + delta)``, the
least cost of ``x`` is linear in ``x``::

    c(mu) = T a (1 + b/delta) + mu (T + g) (b + delta),
    delta = max(sqrt(T a b / (mu (T + g))), a / I_max^2)

and the window's least energy is the concave dual
``E(x) = max_mu [sum_k x_k min_kind c_k(mu) - mu D]`` (strong duality: the
primal is convex and strictly feasible), with gradient ``dE/dx_k = c_k(mu*)``.
Every value returned is the dual at a ``mu``, which never exceeds the primal.
Without model error (``b = 0``) and with the limits slack, ``c = T a``: the
information per joule of a pulse of fixed length does not depend on its
current, as in the bound before.

**Samples per pulse.** :func:`pulse_samples` counts the used samples as the
extraction does, over the magnetometer's sample phase: in ``[start + settle,
end - guard]`` and neither the first nor the last sample inside ``[start,
end]``. At 100 Hz with the 3 ms settle and 2 ms guard a 60 ms pulse uses 4
samples at every phase (not 5.5: the first and last samples are dropped even
when past the settle time), so a pulse of length ``T`` uses ``T / 10 ms - 2``
on average; the two 35 ms baselines give 6.8 (``(2 B - guard) / 10 ms``).
``phase = "mean"`` is a policy that does not time its pulses to the
magnetometer's samples (the firmware's): the counts averaged over a uniform
phase (the weight is concave in the counts, so this over-states the mean
information: the bound stays below). ``"aligned"`` gives every pulse the best
phase (a policy that times its pulses to the samples). A window with fewer used samples than the
extraction accepts (``Timing.min_used``, ``min_pulse_samples``) counts none: it is refused.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: bisection on log(mu) between these (A^2; the fixed cycle's pulses are about 1 A^2)
MU_RANGE = (1e-9, 1e9)
MU_STEPS = 40                 # 41 e-folds / 2^40: mu to 4e-11 relative


@dataclass(frozen=True)
class Timing:
    """The extraction's timing (seconds), the magnetometer's rate (Hz) and the fewest used in-pulse
    samples it accepts (``min_pulse_samples``: a window with fewer is refused and brings nothing)."""

    rate_hz: float
    settle_s: float
    guard_s: float
    fall_s: float
    min_used: int = 1

    @classmethod
    def from_config(cls, cfg) -> "Timing":
        return cls(float(cfg.pulse.mag_rate_hz), cfg.pulse.settle_us * 1e-6, cfg.pulse.guard_us * 1e-6, cfg.pulse.fall_us * 1e-6,
                   int(cfg.pulse.min_pulse_samples))

    def gap_s(self, baseline_s: float) -> float:
        """Quiet time a pulse needs after it before the next: fall + baseline + guard."""
        return self.fall_s + baseline_s + self.guard_s


def _counts(phi: float, T: float, B: float, tm: Timing) -> tuple[int, int]:
    """Used in-pulse and baseline samples when a sample falls at ``phi + j / rate`` (pulse starts at 0)."""
    per = 1.0 / tm.rate_hz
    j = np.arange(int(np.floor((-B - phi) / per)) - 1, int(np.ceil((T + tm.fall_s + B - phi) / per)) + 2)
    t = phi + j * per
    inside = t[(t >= 0.0) & (t <= T)]
    used = (t >= tm.settle_s) & (t <= T - tm.guard_s)
    if inside.size:
        used &= (t != inside[0]) & (t != inside[-1])
    before = (t >= -B) & (t <= -tm.guard_s)
    after = (t >= T + tm.fall_s) & (t <= T + tm.fall_s + B)
    n_used = int(used.sum())
    return (n_used if n_used >= tm.min_used else 0), int(before.sum() + after.sum())


def pulse_samples(T: float, B: float, tm: Timing, phase: str = "mean") -> tuple[float, float]:
    """``(n_u, n_b)`` of a pulse of ``T`` s with baselines of ``B`` s: averaged over a uniform
    sample phase (``"mean"``) or at the phase that maximises ``1 / (1/n_u + 1/n_b)`` (``"aligned"``).

    The counts are piecewise constant in the phase, with steps where a sample meets an edge;
    they are evaluated at the middle of every step, so the mean is exact."""
    per = 1.0 / tm.rate_hz
    edges = np.array([0.0, T, tm.settle_s, T - tm.guard_s, -B, -tm.guard_s, T + tm.fall_s, T + tm.fall_s + B])
    br = np.unique(np.concatenate([np.mod(edges, per), [0.0, per]]))
    br = br[(br >= 0.0) & (br <= per)]
    mids, lens = 0.5 * (br[1:] + br[:-1]), np.diff(br)
    keep = lens > 1e-12 * per
    counts = np.array([_counts(float(m), T, B, tm) for m in mids[keep]], dtype=float)
    w = lens[keep] / per
    if phase == "mean":
        return float(w @ counts[:, 0]), float(w @ counts[:, 1])
    if phase == "aligned":
        nu, nb = counts[:, 0], counts[:, 1]
        info = np.where((nu > 0) & (nb > 0), 1.0 / (1.0 / np.maximum(nu, 1e-300) + 1.0 / np.maximum(nb, 1e-300)), 0.0)
        i = int(np.argmax(info))
        return float(nu[i]), float(nb[i])
    raise ValueError(f"phase must be 'mean' or 'aligned', got {phase!r}")


@dataclass(frozen=True)
class Kinds:
    """Pulse kinds a policy may use, arrays of shape (L,): ``T`` (s) and the time slot ``T + gap`` (s),
    ``c = 1/n_u + 1/n_b`` (the white noise of one pulse in per-sample variances) and ``tc``, the factor
    of ``sigma^2`` in the energy per weight ``T a`` (``T c`` for one length; at most that over an
    interval of lengths)."""

    T: np.ndarray
    slot: np.ndarray
    c: np.ndarray
    tc: np.ndarray
    baseline: np.ndarray

    @classmethod
    def fixed(cls, T: float, B: float, tm: Timing, phase: str = "mean") -> "Kinds":
        """One kind: pulses of ``T`` s, baselines of ``B`` s."""
        nu, nb = pulse_samples(T, B, tm, phase)
        if nu <= 0 or nb <= 0:
            raise ValueError(f"a {T * 1e3:g} ms pulse with {B * 1e3:g} ms baselines uses no sample")
        c = 1.0 / nu + 1.0 / nb
        return cls(np.array([T]), np.array([T + tm.gap_s(B)]), np.array([c]), np.array([T * c]), np.array([B]))

    @classmethod
    def chosen(cls, lengths_s, baselines_s, tm: Timing, phase: str = "mean", sub: int = 8) -> "Kinds":
        """Any pulse length between consecutive values of the sorted grid ``lengths_s``, with any of
        ``baselines_s``: per grid interval ``[T0, T1]`` one optimistic kind whose cost is below that of
        every length in it: the time of ``T0``, the white noise ``c`` of ``T1`` (the counts never fall
        with the length) and ``tc = min T/n_u + T0/n_b``. ``T/n_u`` is monotone where ``n_u`` is affine
        in ``T`` (the mean count is, away from the shortest pulses: checked on ``sub`` points), so its
        least is at an end; elsewhere ``T0/n_u(T1)``. Intervals whose longer end uses no sample are
        left out."""
        Ts = np.sort(np.asarray(lengths_s, dtype=float))
        out = {"T": [], "slot": [], "c": [], "tc": [], "baseline": []}
        for B in baselines_s:
            for lo, hi in zip(Ts[:-1], Ts[1:]):
                nu, nb = pulse_samples(float(hi), float(B), tm, phase)
                if nu <= 0 or nb <= 0:
                    continue
                tn = lo / nu
                pts = np.linspace(lo, hi, sub + 1)
                n = np.array([pulse_samples(float(t), float(B), tm, phase)[0] for t in pts])
                if n[0] > 0 and np.allclose(n, np.linspace(n[0], n[-1], sub + 1), rtol=0, atol=1e-9):
                    tn = min(lo / n[0], hi / n[-1])
                out["T"].append(lo)
                out["slot"].append(lo + tm.gap_s(B))
                out["c"].append(1.0 / nu + 1.0 / nb)
                out["tc"].append(tn + lo / nb)
                out["baseline"].append(B)
        if not out["T"]:
            raise ValueError("no pulse length of the grid uses a sample")
        return cls(*(np.array(out[k], dtype=float) for k in ("T", "slot", "c", "tc", "baseline")))

    @classmethod
    def grid(cls, lengths_s, baselines_s, tm: Timing, phase: str = "mean") -> "Kinds":
        """Exactly the lengths of the grid (each a real pulse: the optimum over them is at or above
        the optimum over every length, the companion of :meth:`chosen` from above)."""
        ks = [cls.fixed(float(t), float(B), tm, phase) for B in baselines_s for t in np.sort(lengths_s)
              if min(pulse_samples(float(t), float(B), tm, phase)) > 0]
        return cls(*(np.concatenate([getattr(k, f) for k in ks]) for f in ("T", "slot", "c", "tc", "baseline")))


def pulse_weight(I, a, b):
    """Information weight ``s = I^2 / (a + b I^2)`` of one pulse (``J = s J~``)."""
    I2 = np.square(I)
    return I2 / (a + b * I2)


class WindowCost:
    """Least energy (A^2 s: ``I^2 T``, the coil resistance left out) of the information weights
    ``x`` (W, K) in W windows of ``D`` s, as the module docstring derives.

    kinds: :class:`Kinds` (L); sigma2: per-sample variance (T^2); u2 (W, K): ``|u|^2`` (T^2/A^2);
    rho, tau: relative field-model and absolute current errors; imax (W, K): current limit (A)."""

    def __init__(self, kinds: Kinds, sigma2: float, u2, rho: float, tau: float, imax, D: float):
        self.kinds, self.D = kinds, float(D)
        u2 = np.asarray(u2, dtype=float)
        self.a = sigma2 * kinds.c[None, None, :] + tau * tau * u2[..., None]          # (W, K, L)
        self.b = (rho * rho * u2)[..., None]                                          # (W, K, 1)
        self.Ta = sigma2 * kinds.tc + kinds.T * tau * tau * u2[..., None]
        self.dmin = self.a / np.square(np.asarray(imax, dtype=float))[..., None]
        # the most information a window's time can hold per unit of x: slot / s_max
        self.psi = np.min(kinds.slot * (self.b + self.dmin), axis=-1)                 # (W, K)

    def _at(self, mu):
        """Per (W, K) at the prices ``mu`` (W,): least cost per information, its time and energy parts."""
        m = np.asarray(mu, dtype=float)[:, None, None]
        slot = self.kinds.slot
        with np.errstate(divide="ignore", invalid="ignore"):
            dstar = np.sqrt(self.Ta * self.b / (m * slot))
        d = np.maximum(np.nan_to_num(dstar, nan=0.0, posinf=np.inf), self.dmin)
        with np.errstate(divide="ignore", invalid="ignore"):
            energy = self.Ta * (1.0 + np.where(self.b > 0, self.b / d, 0.0))
        time = slot * (self.b + np.where(np.isfinite(d), d, 0.0))
        time = np.where(np.isfinite(d), time, np.inf)
        cost = energy + m * np.where(np.isfinite(time), time, 0.0)
        cost = np.where(np.isfinite(time) | (m == 0), cost, np.inf)
        best = np.argmin(cost, axis=-1)[..., None]
        take = lambda A: np.take_along_axis(np.broadcast_to(A, cost.shape), best, axis=-1)[..., 0]  # noqa: E731
        return take(cost), take(time), take(energy), best[..., 0], take(d)

    def prices(self, x) -> np.ndarray:
        """The time price ``mu*`` (W,) of each window: where the pulses fill the window's time."""
        x = np.asarray(x, dtype=float)
        W = x.shape[0]
        lo, hi = np.full(W, np.log(MU_RANGE[0])), np.full(W, np.log(MU_RANGE[1]))
        for _ in range(MU_STEPS):
            mid = 0.5 * (lo + hi)
            used = np.sum(x * self._at(np.exp(mid))[1], axis=1)
            over = used > self.D
            lo, hi = np.where(over, mid, lo), np.where(over, hi, mid)
        mu = np.exp(hi)
        # time not binding even at the lowest price: mu* = 0
        slack = np.sum(x * self._at(np.zeros(W))[1], axis=1) <= self.D
        return np.where(slack, 0.0, mu)

    def energy(self, x):
        """``(E (W,), dE/dx (W, K), detail)``: the dual value at ``mu*`` (a lower value of the primal
        whatever the bisection's error) and its gradient; detail has the primal's per-(W, K) energy,
        time, kind index and current."""
        x = np.asarray(x, dtype=float)
        mu = self.prices(x)
        cost, time, energy, best, d = self._at(mu)
        E = np.sum(x * cost, axis=1) - mu * self.D
        a_best = np.take_along_axis(self.a, best[..., None], axis=-1)[..., 0]
        with np.errstate(divide="ignore", invalid="ignore"):
            current = np.sqrt(np.where(np.isfinite(d) & (d > 0), a_best / d, 0.0))
        return E, cost, {"mu": mu, "energy": x * energy, "time": x * time, "kind": best, "current": current}
