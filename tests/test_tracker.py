"""The stepper: the restructured descent reproduces the pinned results, and
segment()/track() are loops over it."""

import ast
import doctest
import sys
from pathlib import Path

import numpy as np
import pytest

from spheroseg import Tracker, track
from spheroseg import segment
from spheroseg.descent.dataterms import FixedInterface, GlobalMeans, IntensityInterface, LocalMeans
from spheroseg.descent.options import SegmentOptions
from spheroseg.synthetic.phantom import make_phantom, make_sequence
from spheroseg.surfaces.surface import Surface
from spheroseg.tracking.tracker import BASE_RING_MM, schedule

DATA = Path(__file__).parent / "data"
# the sources under test, from the repository (an installed package lies elsewhere)
SRC = Path(__file__).resolve().parents[1] / "src" / "spheroseg"
# options added after the reference was recorded, as they reproduce the descent it recorded
LEGACY = dict(adaptive_step=False, coarse_tol=0.05)
KERNEL_MODULES = ("_kernels",)
NAMEDTUPLE_API = ("_replace", "_asdict", "_fields", "_make")  # public, despite the underscore
STDLIB_API = ("os._exit", "sys._current_frames")  # public, despite the underscore


@pytest.fixture(scope="module")
def reference():
    sys.path.insert(0, str(DATA))
    try:
        import make_descent_reference as ref
    finally:
        sys.path.remove(str(DATA))
    return ref, np.load(DATA / "descent_reference.npz")


def test_results_equal_the_recorded_reference(reference):
    """6 phantom families x 3 data terms, and a tracked sequence with a
    landmark: iteration counts equal and coefficients to 1e-10 of what the
    code computed before the descent was split into parts (92d46fa)."""
    ref, data = reference
    for name, volume, apex, base, extra in ref.cases():
        res = segment(volume, apex, base, **ref.OPTIONS, **LEGACY, **extra)
        assert res.iterations == int(data[f"{name}/iterations"]), name
        np.testing.assert_allclose(res.surface.coefficients, data[f"{name}/coefficients"], rtol=0, atol=1e-10,
                                   err_msg=name)
    seq = ref.sequence()
    first = seq.frames[0]
    landmark = first.base + 0.6 * (first.apex - first.base) + np.array([0.0, 14.0, 0.0])
    tr = track(seq.volumes, first.apex, first.base, landmarks=[landmark], iterations_per_frame=5, **ref.OPTIONS,
               **LEGACY, mode="local", follow_base=False)  # the defaults then
    np.testing.assert_array_equal([f.iterations for f in tr.frames], data["track/iterations"])
    np.testing.assert_allclose(np.stack([f.surface.coefficients for f in tr.frames]), data["track/coefficients"],
                               rtol=0, atol=1e-10)


def test_schedule_is_data():
    levels = schedule(SegmentOptions())
    assert [(lv.patches, lv.data_term, lv.max_iterations, lv.tol) for lv in levels] == [
        ((2, 2), GlobalMeans(), 60, 0.1), ((4, 4), GlobalMeans(), 60, 0.1), ((8, 8), LocalMeans(), 60, 0.05),
        ((8, 8), IntensityInterface(), 60, 0.05)]
    assert [lv.tol for lv in schedule(SegmentOptions(tol=0.02, coarse_tol=0.3))] == [0.3, 0.3, 0.02, 0.02]
    assert schedule(SegmentOptions(mode="local"))[-1].data_term == LocalMeans()
    assert [lv.data_term for lv in schedule(SegmentOptions(mode="fast"))] == [FixedInterface()] * 3
    assert schedule(SegmentOptions(mode="fast", interface=12.0))[0].data_term == FixedInterface(interface=12.0)
    bright = LocalMeans(polarity=-1.0, boundary_nepers=12.0)  # a term with parameters: the coarse levels' means
    assert [lv.data_term for lv in schedule(SegmentOptions(mode=bright))] == [GlobalMeans()] * 2 + [bright]
    assert [lv.patches for lv in schedule(SegmentOptions(patches=(6, 8), mode="local"))] == [(3, 4), (6, 8)]
    assert [lv.data_term for lv in schedule(SegmentOptions(coarse_to_fine=False))] == [LocalMeans(),
                                                                                      IntensityInterface()]


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=11, spacing=2.0)


def test_iterating_by_hand_equals_segment(phantom):
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base)
    assert tracker.status is None and tracker.iteration == 0 and tracker.patches == (2, 2)
    motions, ends = [], []
    while tracker.status is None:
        level = tracker.level
        motions.append(tracker.iterate())
        if tracker.level != level or tracker.status is not None:
            ends.append((motions[-1], tracker.levels[level].tol))
    by_hand = tracker.result()
    # each level stopped below its own tolerance: the coarse ones' is twice tol,
    # and they stopped before the finest one's
    assert all(motion < tol for motion, tol in ends) and ends[0][1] == 0.1 and ends[-1][1] == 0.05
    assert max(motion for motion, _ in ends[:2]) >= 0.05
    whole = segment(phantom.volume, phantom.apex, phantom.base)  # each level in one compiled loop
    assert by_hand.iterations == whole.iterations == len(motions)
    # equal to rounding: the loop's sums are plain loops, not numpy's pairwise ones nor BLAS's
    np.testing.assert_allclose(by_hand.surface.coefficients, whole.surface.coefficients, rtol=0, atol=1e-12)
    assert motions[-1] < 0.05 and tracker.patches == (8, 8)
    with pytest.raises(RuntimeError, match="stopped"):
        tracker.iterate()


def test_a_callback_every_k_iterations_runs_the_compiled_loop_between(phantom):
    """``callback_every``: the callback at every k-th iteration and at each
    level's end, the same surface as a run without a callback (the same
    compiled loop, cut into pieces), and a StopIteration still stops it."""
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base)
    whole = tracker.run()
    assert whole.quality is not None and tracker.result(report=False).quality is None
    assert tracker.result(report=False).volume_ml == whole.volume_ml  # only the report left out
    seen = []
    chunked = Tracker(phantom.volume, phantom.apex, phantom.base).run(
        lambda it: seen.append((it.iteration, it.level)), callback_every=4)
    assert chunked.iterations == whole.iterations and chunked.status == whole.status == 0
    np.testing.assert_allclose(chunked.surface.coefficients, whole.surface.coefficients, rtol=0, atol=1e-12)
    steps = np.diff([0] + [i for i, _ in seen])
    assert seen[-1][0] == whole.iterations and np.all((steps >= 1) & (steps <= 4))
    levels = [level for _, level in seen]  # through the schedule in order, ending on the finest
    assert levels == sorted(levels) and levels[-1] == len(tracker.levels) - 1 and len(set(levels)) >= 3
    assert len(seen) < whole.iterations  # not at every iteration

    calls = []

    def stop_after(intermediate):
        calls.append(intermediate.iteration)
        if intermediate.iteration >= 6:
            raise StopIteration

    stopped = Tracker(phantom.volume, phantom.apex, phantom.base).run(stop_after, callback_every=3)
    assert stopped.status == 2 and stopped.iterations == calls[-1] and 6 <= calls[-1] < 9
    with pytest.raises(ValueError, match="callback_every must be a positive integer, got 0"):
        Tracker(phantom.volume, phantom.apex, phantom.base).run(stop_after, callback_every=0)


def test_the_interface_starts_from_the_local_means(monkeypatch):
    """The intensity stage is handed the local means' last band means, on
    every frame: it measures none itself, and its region means are theirs."""
    reads = IntensityInterface.reads

    def reads_no_bands(term, state):
        if reads(term, state).band_offsets is not None:
            pytest.fail("the interface measured band means again")
        return reads(term, state)

    monkeypatch.setattr(IntensityInterface, "reads", reads_no_bands)

    def run_by_hand(tracker):
        while tracker.status is None:
            stage = tracker.levels[tracker.level].data_term
            tracker.iterate()
            if stage == LocalMeans():
                c_in, c_out = tracker.c_in.copy(), tracker.c_out.copy()  # the local means' fields
            elif stage == IntensityInterface():
                np.testing.assert_array_equal(tracker.c_in, c_in)
                np.testing.assert_array_equal(tracker.c_out, c_in + np.maximum(c_out - c_in, 0.0))
        assert tracker.levels[tracker.level].data_term == IntensityInterface() and tracker.status == 0

    seq = make_sequence(seed=5, n_frames=2, spacing=2.0)
    first = seq.frames[0]
    tracker = Tracker(seq.volumes[0], first.apex, first.base)
    run_by_hand(tracker)
    assert tracker.next_frame(seq.volumes[1], max_iterations=4).iterations > 0  # a new frame: handed over again
    run_by_hand(Tracker(seq.volumes[1], first.apex, first.base, init=tracker.surface))


def test_the_interface_stage_takes_twice_the_step(phantom):
    """The interface stage starts at the wall, its force linear in the
    distance: it moves by up to twice the step option (the other stages by
    up to the step, here all under it)."""
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, step=0.5)
    motions = {}
    while tracker.status is None:
        stage = tracker.levels[tracker.level].data_term
        motions.setdefault(stage, []).append(tracker.iterate())
    assert IntensityInterface.step_factor == 2.0 and LocalMeans.step_factor == GlobalMeans.step_factor == 1.0
    assert 0.55 < motions[IntensityInterface()][0] <= 1.0
    assert max(motions[GlobalMeans()] + motions[LocalMeans()]) < 0.5


def test_stepping_frames_equals_track():
    seq = make_sequence(seed=5, n_frames=3, spacing=2.0)
    first = seq.frames[0]
    tracker = Tracker(seq.volumes[0], first.apex, first.base)
    frames = [tracker.run()] + [tracker.next_frame(v, max_iterations=6, follow_base=True) for v in seq.volumes[1:]]
    tr = track(seq.volumes, first.apex, first.base, iterations_per_frame=6)
    for a, b in zip(frames, tr.frames):
        assert a.iterations == b.iterations
        np.testing.assert_array_equal(a.surface.coefficients, b.surface.coefficients)
    assert tr.frames[1].parameters["max_iterations"] == 6 and not tr.frames[1].parameters["coarse_to_fine"]
    assert tr.frames[0].parameters["max_iterations"] == 60


def test_track_keeps_its_start_surface(phantom):
    """track() used to drop init silently; it is the first frame's start."""
    start = segment(phantom.volume, phantom.apex, phantom.base).surface
    tr = track([phantom.volume] * 2, phantom.apex, phantom.base, init=start, iterations_per_frame=3)
    assert tr.frames[0].iterations < 10  # already converged: a few iterations at 8 x 8
    assert tr.frames[0].parameters["patches"] == [8, 8]


def test_landmarks_set_while_running_pull_the_surface(phantom):
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, landmark_weight=5.0)
    free = tracker.run()
    point = free.surface.points(1.0, 1.0)
    inward = (phantom.base + 0.5 * (phantom.apex - phantom.base)) - point
    landmark = point - 4.0 * inward / np.linalg.norm(inward)
    tracker.set_landmarks([landmark])
    assert tracker.status is None
    held = tracker.run()
    v0, v1, v2 = held.surface.model_coordinates(landmark[None])
    h0 = held.surface.system.scale_factors(v0, v1, v2)[0][0]
    gap = lambda s: abs(s.evaluate(v1, v2)[0] - v0[0]) * h0  # noqa: E731
    assert gap(held.surface) < 1.0 < gap(free.surface)


def test_no_private_name_is_used_across_modules():
    """A private name (leading underscore) is used only by its own module and
    class: no ``from .x import _y`` and no ``obj._y`` but on ``self`` or
    ``cls`` (or ``other`` of the same class, in a comparison), in the package,
    the tests or the benchmarks (the compiled kernels' modules are reached
    through their public functions)."""
    offences = []
    for root in (SRC, SRC.parents[1] / "tests", SRC.parents[1] / "benchmarks"):
        for path in root.rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("spheroseg")):
                    offences += [f"{path.name}:{node.lineno} imports {a.name}" for a in node.names
                                 if a.name.startswith("_") and not a.name.startswith("__") and a.name not in KERNEL_MODULES]
                if (isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__")
                        and node.attr not in NAMEDTUPLE_API and ast.unparse(node) not in STDLIB_API
                        and not (isinstance(node.value, ast.Name) and node.value.id in ("self", "cls", "other"))):
                    offences.append(f"{path.name}:{node.lineno} {ast.unparse(node)}")
    assert not offences, offences


def test_examples_in_docstrings_run():
    import importlib

    # (spheroseg.segment is the function; the modules by name)
    for module in map(importlib.import_module, ("spheroseg.tracking.segment", "spheroseg.tracking.tracker")):
        failures, tried = doctest.testmod(module, optionflags=doctest.ELLIPSIS)
        assert tried > 0 and failures == 0, module.__name__


def test_no_speckle_falls_back_to_the_local_means_and_says_so():
    """A noise-free image (piecewise constant: no speckle to measure the log
    compression from) in the default mode: the local means' wall, a warning
    naming the fallback, instead of an error."""
    from spheroseg.surfaces.metrics import dice
    from spheroseg.volumes.volume import Volume

    ph = make_phantom(seed=1, spacing=2.0)
    flat = Volume(np.where(ph.truth_mask, 20.0, 120.0), spacing=ph.volume.spacing, origin=ph.volume.origin)
    r = segment(flat, ph.apex, ph.base)
    assert r.parameters["mode"] == "intensity"
    assert r.quality["poor"] and any("no speckle" in w and "mode='local'" in w for w in r.quality["warnings"])
    local = segment(flat, ph.apex, ph.base, mode="local")
    assert r.volume_ml == local.volume_ml  # the local means' wall, as mode='local' finds it
    assert dice(r.mask(flat), ph.truth_mask) >= 0.9


def test_base_radii_of_the_initial_half_ellipsoid(phantom):
    """The initial surface's base ring is the half-ellipsoid's base circle:
    ``radius_ratio * |apex - base|`` at every angle."""
    start = Surface.from_apex_base(phantom.apex, phantom.base, radius_ratio=0.3)
    length = np.linalg.norm(phantom.apex - phantom.base)
    np.testing.assert_allclose(start.base_radii(16), 0.3 * length, rtol=1e-6)


def low_contrast_base(ph, depth_mm=20.0):
    """The phantom's image with every voxel within ``depth_mm`` of the base
    plane (cavity and wall) at the grey level half way between blood and
    myocardium: no contrast at the base."""
    from spheroseg.volumes.volume import Volume

    s = ph.volume.spacing[0]
    img = ph.volume.array.astype(float)
    z, y, x = np.indices(img.shape) * s
    axis = (ph.apex - ph.base) / np.linalg.norm(ph.apex - ph.base)
    d = (np.stack([x, y, z], -1) - ph.base) @ axis
    data = img > 0
    wall = ~ph.truth_mask & data & (abs(d) < 40)
    img[(d < depth_mm) & data] = 0.5 * (np.median(img[ph.truth_mask & data]) + np.median(img[wall]))
    return Volume(img.astype(np.uint8), spacing=ph.volume.spacing, no_data_value=0)


def test_a_low_contrast_base_stays_a_ring():
    """Started from a surface narrowing towards the base (ring 8.6 mm) on an
    image with no contrast over the basal 20 mm, the descent closed the base
    into a point (ring 0 mm, volume +32 %); held at the annulus range's
    lower end it stays a ring of about 10 mm."""
    ph = make_phantom(seed=0, spacing=1.5)
    start = Surface.from_apex_base(ph.apex, ph.base)
    lo, hi = start.grid.v2_range
    apex_end = lo if start.base_v2 == hi else hi
    v0 = float(start.coefficients[0, 0, 0])
    pinched = Surface.from_function(start.system, start.pose, start.grid,
                                    lambda v2: v0 * (1 - 0.85 * ((v2 - apex_end) / (start.base_v2 - apex_end)) ** 6))
    assert pinched.base_radii().min() < BASE_RING_MM[0]
    image = low_contrast_base(ph)
    r = segment(image, ph.apex, ph.base, init=pinched)
    assert r.surface.base_radii().min() > 0.95 * BASE_RING_MM[0]
    assert abs(r.volume_ml / ph.truth_volume_ml - 1) < 0.08
    # the check left out (as for the epicardium, held outside the endocardium): the ring closes
    unheld = Tracker(image, ph.apex, ph.base, init=pinched).run(base_ring=False)
    assert unheld.surface.base_radii().min() < 0.5 * BASE_RING_MM[0]


@pytest.fixture(scope="module")
def six_frames():
    """A 6-frame cycle (seed 1, annulus descending 10 mm, 1.5 mm voxels)."""
    return make_sequence(seed=1, n_frames=6, base_descent=10.0, spacing=1.5)


def tracked_ef_error(frames) -> float:
    tr = track([f.volume for f in frames], frames[0].apex, frames[0].base)
    truth = np.array([f.truth_volume_ml for f in frames])
    return tr.ef - (truth.max() - truth.min()) / truth.max() * 100


def test_a_six_frame_cycle_gives_the_ef(six_frames):
    """Six frames a cycle (the wall moves up to 9 mm between frames):
    EF within 3 points (-1.6 on seed 1; seeds 0 and 2: -2.0, -1.7)."""
    assert abs(tracked_ef_error(six_frames.frames)) < 3.0


def test_end_diastole_to_end_systole_directly_gives_the_ef(six_frames):
    """ED and ES alone: the stepped surface stays near the end-diastolic
    wall (ESV +69 %, EF 25 points low); segmented again from the coarse
    data term and kept by energy, EF within 3 points (-2.3 on seed 1;
    seeds 0 and 2: -3.0, -2.8)."""
    frames = six_frames.frames
    assert abs(tracked_ef_error([frames[0], frames[3]])) < 3.0


def test_a_wall_left_behind_is_replaced_by_a_candidate_on_the_wall():
    """Time-gain compensation too weak at depth darkens the basal wall:
    from end-diastole to end-systole directly the stepped surface keeps
    that wall inside, and the energy's scalar levels prefer it to the
    candidates (by 1.6 %); the check that found the wall left behind picks
    a candidate on the wall instead: EF within 3 points (was 19 low)."""
    from spheroseg.synthetic.phantom import FORMATIONS

    pair = make_sequence(seed=0, n_frames=2, spacing=1.5, base_descent=10.0, formation=FORMATIONS["tgc_under"])
    assert abs(tracked_ef_error(pair.frames)) < 3.0  # -1.1


def test_a_wall_left_behind_where_the_check_does_not_look_is_segmented_again(monkeypatch):
    """Strong near-field clutter reads as tissue in the apical cavity, where
    the check of the wall's sides does not look: from end-diastole to
    end-systole directly the stepped surface followed the basal wall and
    kept the apical one at end-diastole (ESV +21 %, EF 7 points low).  Its
    wall moved by 6.8 mm on the whole, more than half the local means'
    band: segmented again, kept by energy, EF within 3 points."""
    from spheroseg.synthetic.phantom import FORMATIONS

    again = []
    segment_again = Tracker.segment_again
    monkeypatch.setattr(Tracker, "segment_again",
                        lambda tracker, start, **kw: again.append(kw) or segment_again(tracker, start, **kw))
    pair = make_sequence(seed=0, n_frames=2, spacing=1.5, base_descent=10.0, formation=FORMATIONS["clutter_strong"])
    assert abs(tracked_ef_error(pair.frames)) < 3.0  # +0.2
    assert again == [{"left_behind": False}]  # followed where the check looks


def test_only_a_frame_whose_wall_was_left_behind_is_segmented_again(six_frames, monkeypatch):
    """Consecutive frames of a six-frame cycle are followed by the stepped
    descent; end-systole reached from end-diastole directly (the base
    plane followed, as :func:`spheroseg.track` does) leaves the
    basal wall behind and is segmented again (and then within 3 EF points,
    the test above)."""
    again = []
    segment_again = Tracker.segment_again
    monkeypatch.setattr(Tracker, "segment_again",
                        lambda tracker, start, **kw: again.append(kw) or segment_again(tracker, start, **kw))
    frames = six_frames.frames
    tracker = Tracker(frames[0].volume, frames[0].apex, frames[0].base)
    tracker.next_frame(frames[1].volume, max_iterations=20, follow_base=True)
    assert again == []
    tracker = Tracker(frames[0].volume, frames[0].apex, frames[0].base)
    tracker.next_frame(frames[3].volume, max_iterations=20, follow_base=True)
    assert again == [{"left_behind": True}]  # settled, yet not on the wall


def test_step_is_a_deprecated_alias_of_next_frame(phantom):
    trackers = [Tracker(phantom.volume, phantom.apex, phantom.base, mode="local", coarse_to_fine=False)
                for _ in range(2)]
    expected = trackers[0].next_frame(phantom.volume, max_iterations=3)
    with pytest.warns(DeprecationWarning, match="next_frame"):
        result = trackers[1].step(phantom.volume, max_iterations=3)
    assert result.iterations == expected.iterations
    np.testing.assert_array_equal(result.surface.coefficients, expected.surface.coefficients)


def test_a_frame_whose_descent_did_not_settle_is_flagged(six_frames):
    """Every level capped at 2 iterations: no candidate of the end-systolic
    frame (stepped, or segmented again) settles, and the frame kept says
    so, whichever it is."""
    frames = six_frames.frames
    tr = track([frames[0].volume, frames[3].volume], frames[0].apex, frames[0].base, max_iterations=2)
    es = tr.frames[1]
    assert not es.converged and es.quality["poor"]
    assert "still moving" in es.quality["warnings"][0]


def test_the_tracker_is_its_stepper_and_the_old_name_warns(phantom):
    """One object owns the state and steps (no pass-through to a second);
    ``Tracker.stepper``, as 0.1 had it, is the tracker itself, with a
    warning."""
    from spheroseg.descent.stepper import Stepper

    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, mode="local")
    assert isinstance(tracker, Stepper)
    assert not [name for name, value in vars(Tracker).items() if isinstance(value, property) and name != "stepper"]
    with pytest.warns(DeprecationWarning, match="the tracker itself since spheroseg 0.2.0; it goes in 0.3.0"):
        assert tracker.stepper is tracker
