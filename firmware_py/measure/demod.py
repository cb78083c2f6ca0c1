"""Synchronous demodulation of AC excitation: per coil and axis, in-phase and quadrature amplitudes.

Raab et al. 1979 (``004_86267342cd7488ce.txt``, sec. II and eq 7) measure the
coupling of each source coil to each sensor axis by synchronous detection of
the carrier. Here the coils run at their own frequencies ``f_k`` (frequency
division) and the magnetometer samples all of them at once; per block of
``T_w`` (``ac_window_us``) the samples ``b(t)`` (T, (3,) each axis) are fitted
by weighted least squares with the model

    b(t) = c0 + c1 tau + sum_k [ a_k cos(w_k (t - t_ref)) + q_k sin(w_k (t - t_ref)) ],

``tau = (t - t_start)/T_w - 1/2``, ``w_k = 2 pi f_k``: the earth field (and the
sensor's offset) is the DC term ``c0`` and its change while the sensor turns
the ramp ``c1``, both rejected; ``p = 2 + 2 n`` unknowns per axis, the same
normal matrix ``G = sum phi phi^T`` for the three axes. A new block starts
every ``ac_hop_us`` (a block holds ``T_w / hop`` hops: sliding blocks, each
sample added to every block it lies in as it arrives, so the work per sample
is bounded and no sample is read twice).

The fitted phasor of coil ``k`` is ``Z_k = a_k - i q_k`` (``b = Re[Z e^{i w (t - t_ref)}]``).
Corrected for the magnetometer's response ``H(f) = sinc(f T_i) e^{-i pi f T_i}``
(averaging over ``T_i`` = ``mag_integration_us`` before the sample instant;
the bench's MMC5983MA model, ``hil/magnetometers.py``) and for the driver's
measured current phasor ``A_k e^{i phi_k}`` (``AC_DRIVE_STATUS``, the same
phase reference ``t_ref`` on the shared clock), the coupling at the current
amplitude ``A_k`` is

    W_k = Z_k / (H(f_k) e^{i phi_k}),   in-phase S[:, k] = Re W_k,   quadrature Q[:, k] = Im W_k   (T).

A coil's field follows its current, so ``Q`` is zero without conductors; an
eddy current lags and shows in ``Q`` (the distortion indicator). The sign of
``S`` comes from the phase reference: a sensor axis opposite to the coil's
field gives a negative in-phase amplitude, as a DC pulse does. Variances:
``sigma^2 G^-1`` with the stated per-sample noise ``sigma`` (``mag_sigma_t``),
rotated by the same phase: ``var(Re W) = |g|^2 (c^2 V_aa + s^2 V_qq + 2 c s V_aq)``
with ``g = 1/(H e^{i phi}) = |g| (c + i s)``.

Everything is allocated in the constructor; :meth:`Demodulator.push` and
:meth:`Demodulator.finish` create no numpy array (memoryviews, Python floats).
Work: a sample costs ``m (p (p + 1)/2 + 3 p)`` multiply-adds (``m`` blocks per
sample), a finished block one ``p x p`` Cholesky factorisation, its inverse and
three solves.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.linalg import chol_inverse, chol_solve, cholesky
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_TOO_FEW, SAMPLE_SATURATED

_TWO_PI = 2.0 * math.pi


def mag_response(f_hz: float, integration_s: float) -> tuple[float, float]:
    """``H(f) = sinc(f T) e^{-i pi f T}`` of a magnetometer that averages over ``T`` (s): (real, imag)."""
    u = f_hz * integration_s
    if u == 0.0:
        return 1.0, 0.0
    s = math.sin(math.pi * u) / (math.pi * u)
    return s * math.cos(math.pi * u), -s * math.sin(math.pi * u)


class Demodulator:
    """Sliding-block least-squares demodulation of one magnetometer (see module docstring).

    ``freqs_hz`` (n,), ``window_us`` = ``m hop_us``, ``sigma_t`` per-sample
    noise (T), ``integration_us`` the magnetometer's averaging time.
    :meth:`start` sets the block grid and the current phasors; :meth:`push`
    adds one sample and returns the index of a block it completes (or -1);
    :meth:`finish` solves that block into ``S``, ``Q``, ``var``, ``dc``.
    """

    def __init__(self, freqs_hz, window_us: int, hop_us: int, sigma_t: float, integration_us: int):
        n = len(freqs_hz)
        if window_us % hop_us:
            raise ValueError("window_us must be a multiple of hop_us")
        self.n = n
        self.p = p = 2 + 2 * n
        self.m = m = window_us // hop_us
        self.slots = m + 1
        self.window_us, self.hop_us = int(window_us), int(hop_us)
        self.freqs = tuple(float(f) for f in freqs_hz)
        self.sigma2 = float(sigma_t) ** 2
        ti = integration_us * 1e-6
        self.h = tuple(mag_response(f, ti) for f in self.freqs)
        s = self.slots
        self.G = np.zeros((s, p * p))
        self.R = np.zeros((s, p * 3))
        self.BB = np.zeros((s, 3))
        self.count = np.zeros(s, dtype=np.int64)
        self.flags = np.zeros(s, dtype=np.int64)
        self.kslot = np.full(s, -1, dtype=np.int64)
        self._Gv = [memoryview(self.G[i]) for i in range(s)]
        self._Rv = [memoryview(self.R[i]) for i in range(s)]
        self._BBv = [memoryview(self.BB[i]) for i in range(s)]
        self._cv = memoryview(self.count)
        self._flv = memoryview(self.flags)
        self._kv = memoryview(self.kslot)
        self.phi = np.zeros(p)
        self._phv = memoryview(self.phi)
        self.Gf = np.zeros(p * p)
        self.L = np.zeros(p * p)
        self.Ginv = np.zeros(p * p)
        self.x = np.zeros(p)
        self.b = np.zeros(p)
        self.X = np.zeros((p, 3))
        self._Gfv, self._Lv, self._Giv = memoryview(self.Gf), memoryview(self.L), memoryview(self.Ginv)
        self._xv, self._bv, self._Xv = memoryview(self.x), memoryview(self.b), memoryview(self.X.reshape(-1))
        # results of the last finished block
        self.S = np.zeros((3, n))
        self.Q = np.zeros((3, n))
        self.var = np.zeros((3, n))
        self.qvar = np.zeros(n)              # variance of each coil's quadrature element (T^2)
        self.dc = np.zeros(3)
        self._Sv, self._Qv, self._varv, self._dcv = (memoryview(self.S.reshape(-1)), memoryview(self.Q.reshape(-1)),
                                                   memoryview(self.var.reshape(-1)), memoryview(self.dc))
        self._qvv = memoryview(self.qvar)
        self.block_k = -1
        self.block_flags = 0
        self.block_samples = 0
        self.residual_ratio = 0.0        # sqrt(RSS / ((N - p) sigma^2)) per axis, rms
        self.t0 = 0
        self.ref_us = 0
        self.amp = [0.0] * n
        self.cph = [1.0] * n             # cos, sin of the current phase
        self.sph = [0.0] * n
        self.next_k = 0                  # the next block to finish
        self.last_t = -(1 << 62)
        self.started = False

    # ------------------------------------------------------------ set-up
    def start(self, t0_us: int, ref_us: int, amplitude, phase) -> None:
        """Blocks ``k = 0, 1, ...`` span ``[t0 + k hop, t0 + k hop + T_w)``; the drive's phase
        reference ``ref_us`` and measured current phasors (A, rad) per coil."""
        self.t0 = int(t0_us)
        self.ref_us = int(ref_us)
        self.set_currents(amplitude, phase)
        self.kslot.fill(-1)
        self.next_k = 0
        self.started = True

    def set_currents(self, amplitude, phase) -> None:
        for j in range(self.n):
            self.amp[j] = float(amplitude[j])
            self.cph[j] = math.cos(phase[j])
            self.sph[j] = math.sin(phase[j])

    def block_mid(self, k: int) -> int:
        return self.t0 + k * self.hop_us + self.window_us // 2

    def block_end(self, k: int) -> int:
        return self.t0 + k * self.hop_us + self.window_us

    # ------------------------------------------------------------ samples
    def push(self, t: int, bx: float, by: float, bz: float, sample_flags: int) -> int:
        """Add one sample (T, sensor frame); returns a block index ``k`` that is now complete
        (the sample lies past its end; call :meth:`finish`), else -1. Samples before ``t0`` or
        not newer than the last are ignored."""
        if not self.started or t <= self.last_t or t < self.t0:
            return -1
        self.last_t = t
        done = -1
        if t >= self.block_end(self.next_k):
            done = self.next_k
        hop, W, p = self.hop_us, self.window_us, self.p
        rel = t - self.t0
        k_hi = rel // hop
        k_lo = (rel - W) // hop + 1
        if k_lo < 0:
            k_lo = 0
        if k_lo < self.next_k:
            k_lo = self.next_k
        ph = self._phv
        ph[0] = 1.0
        dt = (t - self.ref_us) * 1e-6
        for j in range(self.n):
            c = self.freqs[j] * dt
            c -= math.floor(c)
            a = _TWO_PI * c
            ph[2 + 2 * j] = math.cos(a)
            ph[3 + 2 * j] = math.sin(a)
        kv, cv, flv = self._kv, self._cv, self._flv
        sat = 1 if sample_flags & SAMPLE_SATURATED else 0
        for k in range(k_lo, k_hi + 1):
            s = k % self.slots
            if kv[s] != k:
                self._clear(s, k)
            ph[1] = (t - self.t0 - k * hop) / W - 0.5
            G, R, BB = self._Gv[s], self._Rv[s], self._BBv[s]
            for i in range(p):
                pi = ph[i]
                ip = i * p
                for j in range(i, p):
                    G[ip + j] += pi * ph[j]
                i3 = 3 * i
                R[i3] += pi * bx
                R[i3 + 1] += pi * by
                R[i3 + 2] += pi * bz
            BB[0] += bx * bx
            BB[1] += by * by
            BB[2] += bz * bz
            cv[s] += 1
            if sat:
                flv[s] |= PULSE_SATURATED
        return done

    def _clear(self, s: int, k: int) -> None:
        G, R, BB = self._Gv[s], self._Rv[s], self._BBv[s]
        for i in range(len(G)):
            G[i] = 0.0
        for i in range(len(R)):
            R[i] = 0.0
        BB[0] = BB[1] = BB[2] = 0.0
        self._cv[s] = 0
        self._flv[s] = 0
        self._kv[s] = k

    # ------------------------------------------------------------ a block
    def finish(self, k: int) -> bool:
        """Solve block ``k`` into ``S``, ``Q``, ``var`` (T, T, T^2, (3, n)) and ``dc`` (T, (3,),
        at the block's middle); ``block_flags``: ``PULSE_TOO_FEW`` when it holds fewer than
        ``p + 2`` samples or is singular, ``PULSE_SATURATED``. Returns True when solved."""
        self.next_k = k + 1
        s = k % self.slots
        p, n = self.p, self.n
        self.block_k = k
        if self._kv[s] != k or self._cv[s] < p + 2:
            self.block_flags = PULSE_TOO_FEW
            self.block_samples = self._cv[s] if self._kv[s] == k else 0
            return False
        self.block_flags = self._flv[s]
        self.block_samples = N = self._cv[s]
        G, R, BB = self._Gv[s], self._Rv[s], self._BBv[s]
        Gf, L, Gi, X, b, x = self._Gfv, self._Lv, self._Giv, self._Xv, self._bv, self._xv
        for i in range(p):
            ip = i * p
            for j in range(i, p):
                v = G[ip + j]
                Gf[ip + j] = v
                Gf[j * p + i] = v
        if not cholesky(Gf, p, L):
            self.block_flags |= PULSE_TOO_FEW
            return False
        rss = 0.0
        for ax in range(3):
            for i in range(p):
                b[i] = R[3 * i + ax]
            chol_solve(L, p, b, x)
            fit = 0.0
            for i in range(p):
                X[3 * i + ax] = x[i]
                fit += x[i] * b[i]
            rss += BB[ax] - fit
        dof = N - p
        self.residual_ratio = math.sqrt(max(rss, 0.0) / (3.0 * dof * self.sigma2)) if dof > 0 else 0.0
        chol_inverse(Gf, p, Gi, L)
        S, Q, V, dc = self._Sv, self._Qv, self._varv, self._dcv
        for ax in range(3):
            dc[ax] = X[ax]                    # tau = 0 at the block's middle
        for j in range(n):
            ia, iq = 2 + 2 * j, 3 + 2 * j
            hr, hi = self.h[j]
            # g = 1 / (H e^{i phi}) / A  ->  W = Z g (coupling at the current amplitude A)
            er = hr * self.cph[j] - hi * self.sph[j]
            ei = hr * self.sph[j] + hi * self.cph[j]
            d = er * er + ei * ei
            gr, gi = er / d, -ei / d
            vaa = self.sigma2 * Gi[ia * p + ia]
            vqq = self.sigma2 * Gi[iq * p + iq]
            vaq = self.sigma2 * Gi[ia * p + iq]
            # Z = a - i q;  Re(Z g) = a gr + q gi;  Im(Z g) = a gi - q gr
            v_in = vaa * gr * gr + vqq * gi * gi + 2.0 * vaq * gr * gi
            self._qvv[j] = vaa * gi * gi + vqq * gr * gr - 2.0 * vaq * gr * gi
            for ax in range(3):
                a = X[3 * ia + ax]
                q = X[3 * iq + ax]
                S[ax * n + j] = a * gr + q * gi
                Q[ax * n + j] = a * gi - q * gr
                V[ax * n + j] = v_in
        return True

    def flag_block(self, flags: int) -> None:
        """Add ``PULSE_*`` bits to the last finished block's ``block_flags`` (its reader's verdict,
        e.g. ``PULSE_TOO_FEW`` for a block without signal)."""
        self.block_flags |= flags

    def signal_chi2(self) -> float:
        """``sum S^2 / var(S)`` of the last block: chi-square with ``3 n`` degrees of freedom without a drive."""
        c = 0.0
        S, V = self._Sv, self._varv
        for i in range(3 * self.n):
            c += S[i] * S[i] / V[i]
        return c

    def quadrature_chi2(self) -> float:
        """``sum Q^2 / var(Q)`` of the last block: chi-square with ``3 n`` degrees of freedom without conductors."""
        c = 0.0
        Q, qv, n = self._Qv, self._qvv, self.n
        for ax in range(3):
            for j in range(n):
                q = Q[ax * n + j]
                c += q * q / qv[j]
        return c

    def quadrature_ratio(self) -> float:
        """``|Q| / |S|`` (Frobenius norms) of the last block: 0 without conductors."""
        ss = qq = 0.0
        S, Q = self._Sv, self._Qv
        for i in range(3 * self.n):
            ss += S[i] * S[i]
            qq += Q[i] * Q[i]
        return math.sqrt(qq / ss) if ss > 0.0 else 0.0
