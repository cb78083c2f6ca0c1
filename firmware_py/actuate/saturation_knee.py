"""A current cap where a pulse's information stops paying for its energy (``[adaptive] saturation_knee``).

Schepers & Veltink 2010 (``seeds/000_e46ec0e8bf7ea271.txt``) eq 4 with the single-coil filter's
measurement covariance (``estimate.single_coil``, ``update_single_coil``): a pulse of coil ``c`` at
current ``I`` has, per axis,

    r(I) = a + b I^2,     a = var_amp + tau^2 |h_c|^2,     b = (rho |h_c|)^2

(``var_amp`` the white noise of the window's samples, ``tau`` the current's std, ``rho`` the
field model's relative error, ``h_c`` the coil's field per ampere at the sensor), so its Fisher
information is ``I^2 / (a + b I^2)`` times ``H_u^T H_u`` and its information per joule
``1 / (a + b I^2)``: it falls as the current grows and halves where ``b I^2 = a`` (the model error
as large as the noise). Near the source the fixed cycle's 0.91 A pulses are past that point
(``tools/analyses/energy_bound.py``: 16-44 % of its coil-windows), and the least-energy schedule
(the bound's optimum, ``tools/analyses/pulse_cost.py``) answers with more, weaker pulses, its time
full, at an rms current of 0.58 A against the policy's 0.76 A (seed 2, ``tools/analyses/adaptive_gap``).
A policy that asks one pulse for a fixed step of the variance instead raises the current into
saturation where that step is dear, or (``unreached_share``) takes most of what the largest
current gives, paying the most for the last of it.

The knee: each coil's current limit is lowered to the current at which the model error's
variance is ``kappa`` times the white one,

    I_knee = sqrt(kappa a / b) = sqrt(kappa (var_amp + tau^2 |h|^2)) / (rho |h|),

where a pulse's information per joule is ``1 / (1 + kappa)`` of the unsaturated one. A goal the
capped current does not reach becomes an unreached pulse at the knee (``coil_choice.CoilChooser``);
the variance left is taken by the next pulse, sooner. ``kappa = 0`` (default): no cap.
"""
from __future__ import annotations

import math

__all__ = ["knee_current", "cap_at_knee"]


def knee_current(h0: float, h1: float, h2: float, var_amp: float, rel_model: float, current_sigma: float,
                 kappa: float) -> float:
    """``I_knee`` (A) of a coil whose field per ampere at the sensor is ``(h0, h1, h2)`` (T/A), for
    an amplitude variance ``var_amp`` (T^2 per axis), relative model error ``rel_model`` and current
    std ``current_sigma`` (A); ``inf`` without model error or field, or with ``kappa <= 0``."""
    hn2 = h0 * h0 + h1 * h1 + h2 * h2
    b = rel_model * rel_model * hn2
    if not (kappa > 0.0 and b > 0.0):
        return math.inf
    a = var_amp + current_sigma * current_sigma * hn2
    return math.sqrt(kappa * a / b)


def cap_at_knee(lim, h, var_amp: float, rel_model: float, current_sigma: float, kappa: float) -> None:
    """Lower each coil's current limit ``lim[c]`` (A) to its ``knee_current`` (``h`` (n, 3): the
    coils' fields per ampere). Nothing for ``kappa <= 0``; no array is made."""
    if not kappa > 0.0:
        return
    for c in range(len(lim)):
        i = knee_current(float(h[c, 0]), float(h[c, 1]), float(h[c, 2]), var_amp, rel_model, current_sigma, kappa)
        if i < lim[c]:
            lim[c] = i
