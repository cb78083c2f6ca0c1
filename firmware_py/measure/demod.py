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
:meth:`Demodulator.feed` pushes a tick's new samples straight from the
channel's sample ring. On the compiled core (``coiltrack.firmware.core``,
chosen at construction) push, feed and finish are the C kernels of
``core/src/demod.c`` (``ct_demod_push``, ``ct_demod_feed``: one call per tick
and channel, ``ct_demod_finish``), which follow these methods operation by
operation and give the same results to the bit; the Python here is their
reference.
Work: a sample costs ``m (p (p + 1)/2 + 3 p)`` multiply-adds (``m`` blocks per
sample), a finished block one ``p x p`` Cholesky factorisation, its inverse and
three solves.
"""
from __future__ import annotations

import math

import numpy as np

from coiltrack.firmware.core import DEFAULT as _DEFAULT_CORE
from coiltrack.firmware.linalg import chol_inverse, chol_solve, cholesky
from coiltrack.firmware.measure.pulse import PULSE_SATURATED, PULSE_TOO_FEW, SAMPLE_SATURATED

_TWO_PI = 2.0 * math.pi

# the integer state, an int64 array (``Demodulator._st``; ``core/include/ct_ac.h``: CT_DM_*)
_T0, _REF, _NEXT_K, _LAST_T, _STARTED, _CURSOR, _PENDING, _BLOCK_K, _BLOCK_FLAGS, _BLOCK_SAMPLES = range(10)
_NST = 10
# the block's figures besides S, Q, var, dc, a float64 array (``Demodulator._out``; CT_DMO_*)
_RESID, _SIGNAL_CHI2, _QUAD_CHI2, _QUAD_RATIO = range(4)
_NOUT = 4
# :meth:`Demodulator.step`'s result bits (``ct_ac.h``: CT_DMS_*)
STEP_FINISHED, STEP_SOLVED, STEP_NO_SIGNAL, STEP_DISTORTED = 1, 2, 4, 8
_NO_TIME = -(1 << 62)


def mag_response(f_hz: float, integration_s: float) -> tuple[float, float]:
    """``H(f) = sinc(f T) e^{-i pi f T}`` of a magnetometer that averages over ``T`` (s): (real, imag)."""
    u = f_hz * integration_s
    if u == 0.0:
        return 1.0, 0.0
    s = math.sin(math.pi * u) / (math.pi * u)
    return s * math.cos(math.pi * u), -s * math.sin(math.pi * u)


class _DemodBuffers:
    """A demodulator's arrays, allocated once at construction (:class:`Demodulator`)."""

    def _accumulators(self, s: int, p: int) -> None:
        """The ``s`` block accumulators: ``G`` (normal matrix), ``R`` (right-hand sides), ``BB``
        (sums of squares), sample counts, flags and the block each slot holds."""
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

    def _solve_buffers(self, n: int, p: int) -> None:
        """A block's solve (``Gf``, ``L``, ``Ginv``, ``x``, ``b``, ``X``) and its results (``S``,
        ``Q``, ``var``, ``qvar``, ``dc``)."""
        self.Gf = np.zeros(p * p)
        self.L = np.zeros(p * p)
        self.Ginv = np.zeros(p * p)
        self.x = np.zeros(p)
        self.b = np.zeros(p)
        self.X = np.zeros((p, 3))
        self._Gfv, self._Lv, self._Giv = memoryview(self.Gf), memoryview(self.L), memoryview(self.Ginv)
        self._xv, self._bv, self._Xv = memoryview(self.x), memoryview(self.b), memoryview(self.X.reshape(-1))
        self.S = np.zeros((3, n))
        self.Q = np.zeros((3, n))
        self.var = np.zeros((3, n))
        self.qvar = np.zeros(n)              # variance of each coil's quadrature element (T^2)
        self.dc = np.zeros(3)
        self._Sv, self._Qv, self._varv, self._dcv = (memoryview(self.S.reshape(-1)), memoryview(self.Q.reshape(-1)),
                                                   memoryview(self.var.reshape(-1)), memoryview(self.dc))
        self._qvv = memoryview(self.qvar)


class Demodulator(_DemodBuffers):
    """Sliding-block least-squares demodulation of one magnetometer (see module docstring).

    ``freqs_hz`` (n,), ``window_us`` = ``m hop_us``, ``sigma_t`` per-sample
    noise (T), ``integration_us`` the magnetometer's averaging time; ``ring``
    the channel's ``measure.pulse.SampleRing`` that :meth:`feed` reads (None:
    samples only through :meth:`push`); ``core`` the numeric core
    (``coiltrack.firmware.core``): where it is compiled, :meth:`push`,
    :meth:`feed` and :meth:`finish` run the kernels of ``core/src/demod.c``
    (the same operations in the same order), bound once here to this
    object's buffers and the ring's; ``currents`` the drive's measured
    ``(amplitude, phase)`` arrays (n,) that :meth:`step` reads for each block
    it solves (the actuation's; None: no :meth:`step`, and :meth:`step` on the
    compiled core as well only with ``ring`` and ``currents``).
    :meth:`start` sets the block grid and the current phasors; :meth:`push`
    adds one sample and returns the index of a block it completes (or -1);
    :meth:`finish` solves that block into ``S``, ``Q``, ``var``, ``dc``.
    The integer state (``t0``, ``next_k``, the feed's cursor, the last
    block's flags ...) is the int64 array ``_st``, the block's residual and
    statistics the float64 array ``_out``: the compiled kernels share them.
    """

    def __init__(self, freqs_hz, window_us: int, hop_us: int, sigma_t: float, integration_us: int, ring=None,
                 core=_DEFAULT_CORE, currents=None):
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
        self._accumulators(self.slots, p)
        self._solve_buffers(n, p)
        self._st = np.zeros(_NST, dtype=np.int64)
        self._stv = st = memoryview(self._st)
        st[_LAST_T] = st[_CURSOR] = _NO_TIME
        st[_PENDING] = st[_BLOCK_K] = -1
        self._out = np.zeros(_NOUT)
        self._outv = memoryview(self._out)
        self.amp = [0.0] * n
        self._cph = np.ones(n)           # cos, sin of the current phase
        self._sph = np.zeros(n)
        self.cph, self.sph = memoryview(self._cph), memoryview(self._sph)
        self.ring = ring
        # the drive's measured current phasors (amplitude, phase: (n,) arrays the actuation owns) that
        # :meth:`step` takes for each block it solves
        self._currents = currents
        #: the numeric core this demodulator runs, bound once here (``coiltrack.firmware.core``)
        self.core = "python"
        if core.ext is not None and n <= 64:
            self._bind_compiled(core.ext)

    def _bind_compiled(self, ext) -> None:
        """Run :meth:`push`, :meth:`feed` and :meth:`finish` on the compiled kernels
        (``core/src/demod.c``): every buffer bound once; the methods are replaced on this
        instance, so no call tests the choice."""
        freqs = np.array(self.freqs)
        h = np.array([v for hv in self.h for v in hv])
        bufs = (freqs, h, self._cph, self._sph, self.G, self.R, self.BB, self.count, self.flags, self.kslot,
                self.phi, self.Gf, self.L, self.Ginv, self.x, self.b, self.X, self.S, self.Q, self.var, self.qvar,
                self.dc, self._st, self._out)
        r = self.ring
        ring = None if r is None else (r.t, r.b, r.flags)
        phase = None if self._currents is None else self._currents[1]
        self._ck = ext.Demod(self.n, self.slots, self.window_us, self.hop_us, self.sigma2, bufs, ring, phase)
        self._keep = (freqs, h)
        self.push = self._ck.push
        self.finish = self._ck.finish
        self.feed = self._feed_compiled
        if phase is not None and r is not None:
            self.step = self._step_compiled
        self.signal_chi2 = self._signal_chi2_compiled
        self.quadrature_chi2 = self._quadrature_chi2_compiled
        self.quadrature_ratio = self._quadrature_ratio_compiled
        self.core = "compiled"

    # ------------------------------------------------------------ state
    @property
    def t0(self) -> int:
        """Start of block 0 (us)."""
        return self._stv[_T0]

    @property
    def ref_us(self) -> int:
        """The drive's phase reference (us)."""
        return self._stv[_REF]

    @property
    def next_k(self) -> int:
        """The next block to finish."""
        return self._stv[_NEXT_K]

    @property
    def started(self) -> bool:
        return self._stv[_STARTED] != 0

    @property
    def pending(self) -> int:
        """The block the last :meth:`feed` completed (to :meth:`finish`), or -1."""
        return self._stv[_PENDING]

    @property
    def block_k(self) -> int:
        """The last finished block."""
        return self._stv[_BLOCK_K]

    @property
    def block_flags(self) -> int:
        """``PULSE_*`` flags of the last finished block."""
        return self._stv[_BLOCK_FLAGS]

    @property
    def block_samples(self) -> int:
        """Samples in the last finished block."""
        return self._stv[_BLOCK_SAMPLES]

    @property
    def residual_ratio(self) -> float:
        """``sqrt(RSS / ((N - p) sigma^2))`` of the last solved block, per axis, rms."""
        return self._outv[_RESID]

    # ------------------------------------------------------------ set-up
    def start(self, t0_us: int, ref_us: int, amplitude, phase) -> None:
        """Blocks ``k = 0, 1, ...`` span ``[t0 + k hop, t0 + k hop + T_w)``; the drive's phase
        reference ``ref_us`` and measured current phasors (A, rad) per coil."""
        st = self._stv
        st[_T0] = int(t0_us)
        st[_REF] = int(ref_us)
        self.set_currents(amplitude, phase)
        self.kslot.fill(-1)
        st[_NEXT_K] = 0
        st[_PENDING] = -1
        st[_STARTED] = 1

    def set_currents(self, amplitude, phase) -> None:
        for j in range(self.n):
            self.amp[j] = float(amplitude[j])
            self.cph[j] = math.cos(phase[j])
            self.sph[j] = math.sin(phase[j])

    def block_mid(self, k: int) -> int:
        return self._stv[_T0] + k * self.hop_us + self.window_us // 2

    def block_end(self, k: int) -> int:
        return self._stv[_T0] + k * self.hop_us + self.window_us

    def clear_pending(self) -> None:
        """The block :meth:`feed` completed is taken (or dropped)."""
        self._stv[_PENDING] = -1

    # ------------------------------------------------------------ samples
    def feed(self, left: int) -> bool:
        """Push the ring's samples newer than the last fed, at most ``left``, up to the first that
        completes a block (then True, its index in :attr:`pending`)."""
        ring = self.ring
        nr = len(ring)
        if nr == 0:
            return False
        st = self._stv
        idx = ring.index_at_or_after(st[_CURSOR] + 1)
        tv, bv, fv = ring.tv, ring.bv, ring.fv
        while idx < nr and left > 0:
            s = ring.slot(idx)
            t = tv[s]
            st[_CURSOR] = t
            j = 3 * s
            k = self.push(t, bv[j], bv[j + 1], bv[j + 2], fv[s])
            idx += 1
            left -= 1
            if k >= 0:
                st[_PENDING] = k
                return True
        return False

    def _feed_compiled(self, left: int) -> bool:
        ring = self.ring
        return self._ck.feed(len(ring), ring.last_pushed_slot(), left)

    def step(self, left: int, signal_gate: float, ratio_max: float, q_gate: float) -> int:
        """One tick of this channel (``measure.ac_blocks.ACBlockMeasurement``): the block the
        last :meth:`feed` completed is solved (:meth:`finish`) at the drive's current phasors of
        now (``currents``), else :meth:`feed` takes up to ``left`` new samples. A solved block
        whose ``signal_chi2`` is below ``signal_gate`` (no coil field: the drive is off) is
        flagged ``PULSE_TOO_FEW``; one whose ``quadrature_ratio`` exceeds ``ratio_max`` and
        whose ``quadrature_chi2`` exceeds ``q_gate`` is distorted. Returns the ``STEP_*`` bits
        (0: fed; ``block_k`` the block finished)."""
        k = self._stv[_PENDING]
        if k < 0:
            self.feed(left)
            return 0
        self._stv[_PENDING] = -1
        amplitude, phase = self._currents
        self.set_currents(amplitude, phase)
        if not self.finish(k):
            return STEP_FINISHED
        if self.signal_chi2() < signal_gate:
            self._stv[_BLOCK_FLAGS] |= PULSE_TOO_FEW
            return STEP_FINISHED | STEP_SOLVED | STEP_NO_SIGNAL
        if self.quadrature_ratio() > ratio_max and self.quadrature_chi2() > q_gate:
            return STEP_FINISHED | STEP_SOLVED | STEP_DISTORTED
        return STEP_FINISHED | STEP_SOLVED

    def _step_compiled(self, left: int, signal_gate: float, ratio_max: float, q_gate: float) -> int:
        ring = self.ring
        return self._ck.step(len(ring), ring.last_pushed_slot(), left, signal_gate, ratio_max, q_gate)

    def push(self, t: int, bx: float, by: float, bz: float, sample_flags: int) -> int:
        """Add one sample (T, sensor frame); returns a block index ``k`` that is now complete
        (the sample lies past its end; call :meth:`finish`), else -1. Samples before ``t0`` or
        not newer than the last are ignored."""
        st = self._stv
        t0, next_k = st[_T0], st[_NEXT_K]
        if not st[_STARTED] or t <= st[_LAST_T] or t < t0:
            return -1
        st[_LAST_T] = t
        done = -1
        hop, W, p = self.hop_us, self.window_us, self.p
        if t >= t0 + next_k * hop + W:
            done = next_k
        rel = t - t0
        k_hi = rel // hop
        k_lo = (rel - W) // hop + 1
        if k_lo < 0:
            k_lo = 0
        if k_lo < next_k:
            k_lo = next_k
        ph = self._phv
        ph[0] = 1.0
        dt = (t - st[_REF]) * 1e-6
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
            ph[1] = (t - t0 - k * hop) / W - 0.5
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
        st = self._stv
        st[_NEXT_K] = k + 1
        s = k % self.slots
        p = self.p
        st[_BLOCK_K] = k
        if self._kv[s] != k or self._cv[s] < p + 2:
            st[_BLOCK_FLAGS] = PULSE_TOO_FEW
            st[_BLOCK_SAMPLES] = self._cv[s] if self._kv[s] == k else 0
            return False
        st[_BLOCK_FLAGS] = self._flv[s]
        st[_BLOCK_SAMPLES] = N = self._cv[s]
        G, R, BB = self._Gv[s], self._Rv[s], self._BBv[s]
        Gf, L, Gi, X, b, x = self._Gfv, self._Lv, self._Giv, self._Xv, self._bv, self._xv
        for i in range(p):
            ip = i * p
            for j in range(i, p):
                v = G[ip + j]
                Gf[ip + j] = v
                Gf[j * p + i] = v
        if not cholesky(Gf, p, L):
            st[_BLOCK_FLAGS] |= PULSE_TOO_FEW
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
        self._outv[_RESID] = math.sqrt(max(rss, 0.0) / (3.0 * dof * self.sigma2)) if dof > 0 else 0.0
        chol_inverse(Gf, p, Gi, L)
        self._phasors(X, Gi)
        return True

    def _phasors(self, X, Gi) -> None:
        """The fitted coefficients ``X`` and the inverse normal matrix ``Gi`` of a block into ``S``,
        ``Q``, ``var``, ``qvar``, ``dc`` (the module docstring's ``W = Z / (H e^{i phi})``)."""
        p, n = self.p, self.n
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

    def flag_block(self, flags: int) -> None:
        """Add ``PULSE_*`` bits to the last finished block's ``block_flags`` (its reader's verdict,
        e.g. ``PULSE_TOO_FEW`` for a block without signal)."""
        self._stv[_BLOCK_FLAGS] |= flags

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

    # the compiled finish computes the block's statistics with it (``core/src/demod.c``)
    def _signal_chi2_compiled(self) -> float:
        return self._outv[_SIGNAL_CHI2]

    def _quadrature_chi2_compiled(self) -> float:
        return self._outv[_QUAD_CHI2]

    def _quadrature_ratio_compiled(self) -> float:
        return self._outv[_QUAD_RATIO]
