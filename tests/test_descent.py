"""The descent's step solves the least-squares problem of its docstring."""

import numpy as np
import pytest

from spheroseg.dataterms import LocalMeans
from spheroseg.descent import Descent
from spheroseg.discretisation import ROUGHNESS_SCALE
from spheroseg.phantom import make_phantom
from spheroseg.surface import Surface


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=3, spacing=2.0)


@pytest.mark.parametrize("backend", ["compiled", "numpy"])
def test_step_solves_the_least_squares_system(phantom, backend):
    """After one iteration, ``p+`` solves

        (M + a T + L^T Omega L) p+ = M p + B^T W dv0 + a T p_ref + L^T Omega (L p + r)

    with every matrix built here from the grid's sparse basis (not the
    discretisation's cached inverses), a reference unlike the start and two
    landmarks, one too far to reach in a step (its residual clipped)."""
    ph = phantom
    start = Surface.from_apex_base(ph.apex, ph.base, patches=(4, 4))
    reference = start.with_coefficients(start.coefficients * 1.1)
    axis = (ph.base - ph.apex) / np.linalg.norm(ph.base - ph.apex)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    landmarks = np.array([ph.apex + 2.0 * axis, ph.apex + 0.6 * (ph.base - ph.apex) + 9.0 * side])
    weights = np.array([1.0, 3.0])
    smoothness, step = 2.0, 1.0
    d = Descent(start, reference, order=8, step=step, smoothness=smoothness, landmarks=landmarks,
                landmark_weights=weights, backend=backend)
    term = LocalMeans(np.linspace(0, 100, 50))
    obs = d.observe(ph.volume, term)
    force = term.force(d.backend, ph.volume, obs)
    p = d.p.copy()
    motion = d.iterate(obs, force)

    grid, disc = start.grid, d.discretisation
    a = grid.constraints
    b = (grid.basis_matrix(disc.v1, disc.v2) @ a).toarray()
    w = disc.weights
    mass = b.T @ (w[:, None] * b)
    thin_plate = smoothness * w.sum() / ROUGHNESS_SCALE * grid.roughness_matrix().toarray()
    v0, v1, v2 = start.system.from_cartesian(start.pose.to_local(landmarks))
    rows = (grid.basis_matrix(v1, v2) @ a).toarray()
    h0 = start.system.scale_factors(v0, v1, v2)[0]
    omega = d.omega  # the weights times an area (a definition): only their ratios are checked
    np.testing.assert_allclose(omega / omega[0], weights / weights[0], rtol=1e-12)
    residual = np.clip((v0 - rows @ p) * h0, -step, step) / h0
    assert abs(residual[1]) < abs(v0 - rows @ p)[1]  # the far landmark is clipped
    wdv0 = d.backend.displacement(obs, force.c_in, force.c_out, force.scale, step=step, h0_floor=d.h0_floor,
                                  clip=force.clip, u=force.u)
    p_ref = np.linalg.lstsq(a.toarray(), reference.coefficients.ravel(), rcond=None)[0]
    system = mass + thin_plate + rows.T @ (omega[:, None] * rows)
    rhs = mass @ p + b.T @ wdv0 + thin_plate @ p_ref + rows.T @ (omega * (rows @ p + residual))
    expected = np.linalg.solve(system, rhs)
    np.testing.assert_allclose(d.p, expected, rtol=0, atol=1e-10 * np.abs(expected).max())
    # the motion it returns: the RMS of h0 B dp over the domain
    moved = obs.h0 * (b @ (expected - p))
    assert motion == pytest.approx(np.sqrt(w @ moved**2 / w.sum()), rel=1e-9)
