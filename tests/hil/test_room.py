"""The steel table's self-consistent magnetisation (hil.room) against closed forms."""
import numpy as np
import pytest

pytest.importorskip("magpylib")

from coiltrack.hil import physics  # noqa: E402
from coiltrack.hil.room import SteelTable, cuboid_cells_field, solve_polarisation  # noqa: E402


def _voxel_sphere(a, nr):
    d = a / nr
    g = (np.arange(-nr, nr) + 0.5) * d
    X, Y, Z = np.meshgrid(g, g, g, indexing="ij")
    P = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    P = P[np.linalg.norm(P, axis=1) <= a]
    a_eq = (3.0 * P.shape[0] * d ** 3 / (4.0 * np.pi)) ** (1.0 / 3.0)     # the voxels' volume as a sphere
    return P, d, a_eq


@pytest.mark.parametrize("mu_r, tol", [(5.0, 0.03), (200.0, 0.10)])
def test_voxel_sphere_matches_the_permeable_sphere(mu_r, tol):
    """A voxelised permeable sphere in a uniform field: its moment and outside field match the
    closed form ``m = 4 pi a^3 / mu0 (mu_r - 1)/(mu_r + 2) B0`` (``hil.physics.FerroSphere``) of
    the sphere of equal volume within 3 % (mu_r 5) / 10 % (mu_r 200, the staircase surface
    matters more when the shape sets the response). Catches a dropped or mis-signed self
    (demagnetising) term, which gives (mu_r - 1) B0 V / mu0, 2.3x (mu_r 5) to 67x too much, and a
    wrong chi (mu_r instead of mu_r - 1)."""
    P, d, a_eq = _voxel_sphere(0.05, 5)
    B0 = np.array([10e-6, 0.0, 50e-6])
    J = solve_polarisation(P, [d, d, d], mu_r, np.broadcast_to(B0, P.shape))
    m = J.sum(axis=0) * d ** 3 / physics.MU0
    sphere = physics.FerroSphere(np.zeros(3), a_eq, mu_r)
    m_exact = sphere.moment(B0)
    assert np.linalg.norm(m - m_exact) <= tol * np.linalg.norm(m_exact)
    pts = np.array([[0.0, 0.1, 0.15], [0.2, 0.0, 0.0]])
    Bn = cuboid_cells_field(pts, P, np.tile([d, d, d], (P.shape[0], 1)), J)
    Be = sphere.field(pts, B0)
    assert np.all(np.linalg.norm(Bn - Be, axis=1) <= tol * np.linalg.norm(Be, axis=1))


def test_table_field_is_linear_in_the_currents_and_seeded():
    """The table's field for given currents is the sum of the per-ampere responses plus the
    earth-field part (linearity: catches an applied field that mixes the coils or drops the earth
    term), and the placement is seeded (same seed, same table; another seed, another)."""
    from coiltrack.hil import motion
    from coiltrack.hil.world import World

    tab = SteelTable(seed=3, cells=(12, 9))
    w = World(physics.thesis_source(), motion.StaticPose(np.array([0.3, 0.1, -0.2]), np.eye(3)), objects=[tab])
    p = np.array([0.3, 0.1, -0.2])
    I = np.array([1.5, -0.7, 0.3])
    total = tab.response(w, p, np.append(I, 1.0))[0]
    parts = sum(I[k] * tab.coil_unit_field(w, k, p, None) for k in range(3)) + tab.response(w, p, [0, 0, 0, 1.0])[0]
    assert np.allclose(total, parts, rtol=1e-9, atol=1e-18)
    assert np.allclose(SteelTable(seed=3).centre, tab.centre)
    assert not np.allclose(SteelTable(seed=4).centre, tab.centre)
