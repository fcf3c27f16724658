"""The descent's step solves the least-squares problem of its docstring, and a
level run in one compiled loop equals its iterations."""

from types import SimpleNamespace

import numpy as np
import pytest

from spheroseg import Tracker, Volume
from spheroseg._compiled._runtime import compiled_available
from spheroseg.descent.dataterms import FixedInterface, GlobalMeans, IntensityInterface, LocalMeans
from spheroseg.descent.stepper import freeze_samples
from spheroseg.descent.descent import Descent
from spheroseg.geometry.discretisation import ROUGHNESS_SCALE
from spheroseg.tracking.epicardium import wall_term
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.surfaces.surface import Surface


#: the tests of the compiled loop, where the package is built (not a source tree)
needs_compiled = pytest.mark.skipif(not compiled_available(), reason="the compiled kernels are not built")


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
    term = LocalMeans()
    state = term.start(np.linspace(0, 100, 50))
    obs = d.observe(ph.volume, term.reads(state))
    force = term.force(obs, state)
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



def _stepped(descent, volume, term, state, *, tol, max_iterations):
    """The reference of :meth:`Descent.run`: observe, force, iterate."""
    for iteration in range(1, max_iterations + 1):
        obs = descent.observe(volume, term.reads(state))
        force = term.force(obs, state)
        motion = descent.iterate(obs, force)
        if motion < tol:
            break
    return iteration, motion, motion < tol, obs, force


@pytest.mark.parametrize("term, patches, adaptive_step",
                         [(GlobalMeans(), (2, 2), True), (GlobalMeans(), (4, 4), False), (LocalMeans(), (8, 8), True),
                          (IntensityInterface(), (8, 8), True), (FixedInterface(), (4, 4), True),
                          (wall_term(15.0), (8, 8), True), (wall_term(), (8, 8), True)])
@needs_compiled
def test_a_level_in_one_compiled_loop_equals_its_iterations(phantom, term, patches, adaptive_step):
    """:meth:`Descent.run` (one compiled loop) against observe, force and
    iterate repeated, from the same start with two landmarks: the same
    iterations, and to rounding (the loop's sums are plain loops, not
    numpy's pairwise ones nor BLAS's) the same motion, parameters, step (halved on
    the way), scale-factor floor, observation, force and region means; to a
    cap and to a tolerance.  The epicardium's term (a bright inside) on the
    phantom's grey levels reflected, with the half-way intensity and
    with the midpoint."""
    ph = phantom
    if getattr(term, "polarity", 1.0) < 0:
        ph = SimpleNamespace(volume=Volume(255.0 - ph.volume.array, spacing=ph.volume.spacing,
                                           origin=ph.volume.origin), apex=ph.apex, base=ph.base)
    start = Surface.from_apex_base(ph.apex, ph.base, patches=patches)
    axis = (ph.base - ph.apex) / np.linalg.norm(ph.base - ph.apex)
    side = np.cross(axis, [1.0, 0.0, 0.0])
    landmarks = np.array([ph.apex, ph.apex + 0.6 * (ph.base - ph.apex) + 12.0 * side / np.linalg.norm(side)])
    samples = ph.volume.sample(start.points(*np.meshgrid(np.linspace(0, 6, 20), np.linspace(0.3, 1.5, 10))))
    samples = samples[np.isfinite(samples)]
    step = 3.0 if adaptive_step else 1.0
    for tol, cap in ((0.0, 4), (0.05, 60)):
        runs = []
        for _ in range(2):
            # a step of 3 mm overshoots the walls: the adaptive step halves it (to its floor, 3/8, with the local means)
            d = Descent(start, start, order=8, step=step, smoothness=1.0, landmarks=landmarks,
                        landmark_weights=np.array([10.0, 1.0]), adaptive_step=adaptive_step)
            state = term.start(samples)
            if isinstance(term, IntensityInterface):  # frozen on a first observation, as its stage does
                obs = d.observe(ph.volume, term.reads(state))
                state = term.freeze(state, obs, *obs.band_means,
                                    freeze_samples(d.backend, ph.volume, obs, term.freeze_reads(state)))
                d.iterate(obs, term.force(obs, state))
            runs.append((d, state))
        (d, state), (d_ref, state_ref) = runs
        before, state_before = dict(vars(term)), dict(vars(state))
        run = d.run(ph.volume, term, state, tol=tol, max_iterations=cap)
        assert vars(term).keys() == before.keys() and all(vars(term)[k] is v for k, v in before.items())
        assert all(vars(state)[k] is v for k, v in state_before.items())
        iterations, motion, converged, obs, force = _stepped(d_ref, ph.volume, term, state_ref, tol=tol,
                                                             max_iterations=cap)
        assert (run.iterations, run.converged) == (iterations, converged) and iterations > 1
        assert converged == (tol > 0)
        close = dict(rtol=1e-11, atol=1e-12)
        np.testing.assert_allclose(run.motion, motion, **close)
        np.testing.assert_allclose(d.p, d_ref.p, **close)
        assert (d.step, d.h0_floor) == pytest.approx((d_ref.step, d_ref.h0_floor), rel=1e-12)
        # a wall settles without halving the step
        assert (d.step < step) == adaptive_step or getattr(term, "polarity", 1.0) < 0
        for name in ("f", "h0", "u", "world", "normal"):
            np.testing.assert_allclose(getattr(run.observation, name), getattr(obs, name), **close, err_msg=name)
        for a, b in zip(run.force[:5], force[:5]):
            np.testing.assert_allclose(a, b, **close)
        for a, b in zip(run.force.grey_means, force.grey_means):
            np.testing.assert_allclose(a, b, **close)

@needs_compiled
def test_a_compiled_loop_without_image_data_says_so(phantom):
    """The local means off the image: the loop's error is the reference's."""
    ph = phantom
    trackers = [Tracker(ph.volume, ph.apex, ph.base) for _ in range(2)]
    blank = Volume(np.zeros(ph.volume.shape[::-1], np.float32), spacing=ph.volume.spacing, origin=ph.volume.origin,
                   no_data_mask=np.ones(ph.volume.shape[::-1], bool))
    for tracker in trackers:
        while tracker.levels[tracker.level].data_term != LocalMeans():
            tracker.iterate()
        tracker.volume = blank
    with pytest.raises(ValueError, match="no image data around the surface") as looped:
        trackers[0].run_level()
    with pytest.raises(ValueError, match="no image data around the surface") as stepped:
        trackers[1].iterate()
    assert str(looped.value) == str(stepped.value)


@pytest.mark.parametrize("options", [{"backend": "numpy"}, {"nu": 0.1}])
def test_a_level_runs_in_one_loop_only_where_it_computes_the_same(phantom, options):
    """The numpy reference and the area term step iteration by iteration:
    ``run_level`` runs nothing there."""
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, **options)
    start = tracker.surface.coefficients.copy()
    assert not tracker.run_level()
    assert tracker.iteration == 0 and np.array_equal(tracker.surface.coefficients, start)
