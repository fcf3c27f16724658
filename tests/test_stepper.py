"""The level state machine: the schedule is data that no frame rewrites."""

import numpy as np
import pytest

from spheroseg import Tracker
from spheroseg.descent.dataterms import GlobalMeans, LocalMeans, shell_offsets
from spheroseg.descent.options import SegmentOptions
from spheroseg.synthetic.phantom import make_phantom
from spheroseg.descent.stepper import Level, held_points, schedule
from spheroseg.descent.backends import NumpyBackend
from spheroseg.geometry.coords import Pose


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=11, spacing=2.0)


def test_a_frame_caps_its_finest_levels_without_rewriting_the_schedule(phantom):
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, mode="local")
    levels = schedule(tracker.options)
    assert tracker.levels == levels and isinstance(levels, tuple)
    tracker.run()
    result = tracker.next_frame(phantom.volume, max_iterations=3)
    assert tracker.levels == levels  # the frame's cap lives beside the schedule
    stepper = tracker  # a Tracker is the stepper of its frame
    assert [stepper.max_iterations(k) for k in range(len(levels))] == [60, 60, 3]
    assert result.parameters["max_iterations"] == 3 and result.parameters["coarse_to_fine"] is False
    assert tracker.level == len(levels) - 1 and result.status in (0, 1)


def test_a_schedule_of_ones_own(phantom):
    levels = [Level((4, 4), GlobalMeans(), 5, 0.1), Level((8, 8), LocalMeans(), 4, 0.05)]
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base, levels=levels)
    result = tracker.run()
    assert tracker.levels == tuple(levels) and tracker.patches == (8, 8)
    assert result.iterations <= 9 and result.surface.grid.n1 == 8


def test_a_level_given_a_data_term_class_warns_and_takes_its_object():
    with pytest.warns(DeprecationWarning, match=r"pass GlobalMeans\(\), not the class .* until 0\.3\.0"):
        level = Level((4, 4), GlobalMeans, 5, 0.1)
    assert level.data_term == GlobalMeans()


def test_held_points_keep_the_cavity_side_and_the_apex():
    pose = Pose.from_apex_base(np.array([0.0, 0, 80]), np.zeros(3))  # x1 along +z
    landmarks = np.array([[10.0, 0, 20], [10.0, 0, -5]])  # the second is beyond the base plane
    options = SegmentOptions(landmark_weight=3.0, apex_weight=2.0)
    points, weights = held_points(pose, landmarks, np.array([0.0, 0, 80]), options)
    np.testing.assert_array_equal(points, [[10.0, 0, 20], [0.0, 0, 80]])
    np.testing.assert_array_equal(weights, [3.0, 2.0])
    assert held_points(pose, landmarks[1:], np.zeros(3), SegmentOptions(apex_weight=0.0)) == (None, None)


def test_a_result_before_any_iteration_reports_the_start_region_means(phantom):
    """Stopped before its first iteration, a frame's levels are the region
    means about its initial surface (measured only then): the cavity's
    below the blood's grey-level ceiling, the shell's above it."""
    tracker = Tracker(phantom.volume, phantom.apex, phantom.base)
    descent = tracker.descent  # still at its start
    reference = NumpyBackend(descent.backend.model)
    means = reference.region_means(phantom.volume, reference.observe(descent.p, phantom.volume),
                                   shell_offsets(tracker.options.band_out))
    descent.backend.observe(0.9 * descent.p, phantom.volume)  # a compiled backend writes over its arrays
    tracker.stop()
    result = tracker.result()
    np.testing.assert_allclose((result.c_in, result.c_out), means, rtol=1e-9)
    assert tracker.start_means == (result.c_in, result.c_out)
    assert result.iterations == 0 and result.status == 2 and result.c_in < result.c_out

