"""The least-energy bound of ``tools/analyses/energy_bound.py`` against closed forms."""
import numpy as np
import pytest

from coiltrack.tools.analyses import energy_bound as eb


class _AxialDipole:
    """A one-coil source: a point dipole of 1e-7 T m^3 per A along z (mu0/4pi m = 1e-7), in closed form."""

    def __len__(self):
        return 1

    def unit_fields(self, points):
        p = np.atleast_2d(points)
        r = np.linalg.norm(p, axis=1)[:, None]
        m = np.array([0.0, 0.0, 1e-7])
        return ((3.0 * p * (p @ m)[:, None] / r ** 2 - m) / r ** 3)[None]


def test_pulse_information_on_the_dipole_axis():
    """On the axis of a z dipole at distance z the field is 2k/z^3 along z and dB/dp = diag(3, 3, -6) k / z^4:
    J = H^T H with H = [R^T G, [h]x]. Catches a dropped R^T, the cross-product block's sign or place, and a
    gradient with the wrong step (tolerance 1e-6 relative, the central difference's error at h = 1e-5 m)."""
    z, k = 0.3, 1e-7
    R = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])    # sensor turned 90 deg about x
    J = eb.pulse_information(_AxialDipole(), np.array([2.0]), np.array([[0.0, 0.0, z]]), R[None])[0, 0]
    G = np.diag([3.0, 3.0, -6.0]) * 2.0 * k / z ** 4
    h = R.T @ np.array([0.0, 0.0, 2.0 * 2.0 * k / z ** 3])
    hx = np.array([[0.0, -h[2], h[1]], [h[2], 0.0, -h[0]], [-h[1], h[0], 0.0]])
    H = np.hstack([R.T @ G, hx])
    np.testing.assert_allclose(J, H.T @ H, rtol=1e-6, atol=1e-6 * np.abs(H.T @ H).max())


def _closed_form(s, a, ratio):
    """Least energy for J_w = s_w I (one coil) and mse_w ~ (1 / (s_w e_w))^a: e_w ~ s_w^(-a/(a+1)) (Lagrange),
    fraction (mean s^(-a/(a+1)))^((a+1)/a) / (ratio^(2/a) (mean s^-a)^(1/a))."""
    s = np.asarray(s, float)
    return np.mean(s ** (-a / (a + 1))) ** ((a + 1) / a) / (ratio ** (2 / a) * np.mean(s ** -a) ** (1 / a))


@pytest.mark.parametrize("a,ratio", [(1.0, 1.0), (0.5, 1.0), (0.75, 1.1)])
def test_least_energy_matches_the_lagrange_solution(a, ratio):
    """Windows whose information differs by a factor 16 (range 2x, r^-4 in amplitude squared): the optimum
    spends less where a pulse buys more. Catches a constraint on the RMS instead of the mean square (ratio
    vs ratio^2), a wrong gradient (SLSQP then stops elsewhere) and a fraction normalised per coil-window
    wrongly. Tolerance 1e-4 relative (SLSQP's ftol 1e-10)."""
    s = np.array([1.0, 16.0, 4.0, 1.0, 2.0])
    Jk = s[:, None, None, None] * np.eye(6)[None, None]
    got = eb.least_energy(Jk, a, a, ratio)
    assert got["converged"]
    assert got["energy_fraction"] == pytest.approx(_closed_form(s, a, ratio), rel=1e-4)
    assert got["position_rms_ratio"] == pytest.approx(ratio, rel=1e-4)


def test_equal_windows_save_nothing_but_the_slack():
    """Every window alike and one coil: no policy beats the cycle except by the allowed RMS, fraction
    ratio^(-2/a). Catches a bound that invents a saving from nothing."""
    Jk = np.tile(np.eye(6), (8, 1, 1, 1))
    assert eb.least_energy(Jk, 0.75, 0.75, 1.0)["energy_fraction"] == pytest.approx(1.0, rel=1e-6)
    assert eb.least_energy(Jk, 0.75, 0.75, 1.1)["energy_fraction"] == pytest.approx(1.1 ** (-2 / 0.75), rel=1e-4)


def test_exponent_of_a_power_law():
    """rms ~ E^(-a/2) gives back a; catches an exponent of the RMS instead of the mean square."""
    assert eb.exponent(2.0, 2.0 * 4.0 ** (0.7 / 2), 8.0, 2.0) == pytest.approx(0.7, rel=1e-12)
