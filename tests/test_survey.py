"""The distortion survey's fit (tools.calibration.survey) on a constructed room."""
import numpy as np
import pytest

pytest.importorskip("scipy")

from coiltrack.firmware.config import FirmwareConfig  # noqa: E402
from coiltrack.tools.calibration import survey  # noqa: E402

MU0_4PI = 1e-7


def _dip(p, q, m):
    d = p - q
    r = np.linalg.norm(d, axis=1, keepdims=True)
    return MU0_4PI * (3.0 * d * (d @ m)[:, None] / r ** 2 - m) / r ** 3


def test_survey_recovers_known_equivalent_dipoles_within_their_sigma():
    """Amplitudes built from the nominal coils plus one known image dipole per coil (the dipole
    formula written out here) and 3 nT of noise: the fit finds each dipole's position and moment
    within 4 of its reported sigmas (99.99 % for a Gaussian estimate), and the residual RMS is the
    noise's within 30 %. Catches a residual taken in the sensor frame instead of the source frame
    (R vs R^T), a wrong current scaling, and sigmas not scaled by the residual."""
    cfg = FirmwareConfig()
    p, R = survey.jig_poses(radii=(0.2, 0.4, 0.7), n_az=4, n_el=3, seed=3)
    cur = np.array([c.current for c in cfg.source.coils])
    nom = survey._nominal_fields(cfg, p)
    truth_q = [np.array([-0.5, 0.02, 0.01]), np.array([-0.52, -0.03, 0.0]), np.array([-0.48, 0.0, 0.04])]
    truth_m = [np.array([-0.09, 0.0, 0.0]), np.array([0.0, -0.1, 0.0]), np.array([0.0, 0.0, -0.1])]
    rng = np.random.default_rng(11)
    noise = 3e-9
    S = np.zeros((p.shape[0], 3, 3))
    for k in range(3):
        B = (nom[k] + _dip(p, truth_q[k], truth_m[k])) * cur[k]
        S[:, :, k] = np.einsum("mji,mj->mi", R, B) + rng.normal(0.0, noise, B.shape)
    table, summary = survey.fit_survey(cfg, p, R, S, cur, dipoles_per_coil=1, start_distances_m=(0.6,))
    for k in range(3):
        q = np.array(table[f"coil{k}_position_m"][0])
        m = np.array(table[f"coil{k}_moment_am2_per_a"][0])
        sq = np.array(table[f"coil{k}_position_m_sigma"][0])
        sm = np.array(table[f"coil{k}_moment_am2_per_a_sigma"][0])
        assert np.all(np.abs(q - truth_q[k]) <= 4 * sq), (k, q, truth_q[k], sq)
        assert np.all(np.abs(m - truth_m[k]) <= 4 * sm), (k, m, truth_m[k], sm)
    per_amp = noise / cur.mean()
    assert abs(summary["residual_rms_t_per_a"] / per_amp - 1.0) < 0.3
