import json

import pytest

from spheroseg.descent.options import SegmentOptions, format_point


def test_defaults_round_trip_through_json():
    opts = SegmentOptions()
    params = json.loads(json.dumps(opts.as_parameters()))
    assert params["patches"] == [8, 8] and params["mode"] == "intensity" and params["backend"] == "auto"
    assert SegmentOptions(**params) == opts
    assert set(params) == set(SegmentOptions.names())


@pytest.mark.parametrize("changes, message", [
    (dict(mode="levelset"), "mode must be one of"),
    (dict(system="polar"), "system must be one of"),
    (dict(patches=(8,)), "patches must be two integers >= 2"),
    (dict(patches=(8, 2.5)), "patches must be two integers >= 2"),
    (dict(step=-1.0), "step must be a positive number, got -1.0"),
    (dict(tol=float("nan")), "tol must be a positive number"),
    (dict(coarse_tol=0.0), "coarse_tol must be a positive number"),
    (dict(smoothness_reference="initial"), "smoothness_reference must be one of .*'start', 'fitted'.*, got 'initial'"),
    (dict(max_iterations=True), "max_iterations must be an integer"),
    (dict(order=0), "order must be from 3 to 16"),
    (dict(patches=(200, 200)), "patches must be at most 32 in each direction"),
    (dict(patches=(32, 32), order=16), "at most 65536"),
    (dict(step=1e9), "step must be at most 10 mm, got 1e[+]09"),
    (dict(band=1e6), "band must be at most 50 mm"),
    (dict(band_out=51.0), "band_out must be at most 50 mm"),
    (dict(max_iterations=0), "max_iterations must be from 1 to 10000, got 0"),
    (dict(max_iterations=-1), "max_iterations must be from 1 to 10000, got -1"),  # one message for one range
    (dict(max_iterations=10**9), "max_iterations must be from 1 to 10000"),
    (dict(nu=-0.1), "nu must be a number >= 0"),
    (dict(radius_ratio=1.5), r"radius_ratio must be in \(0, 1\)"),
    (dict(interface=float("inf")), "interface must be a finite grey level"),
    (dict(threads=0), r"threads must be a positive integer \(or None: the default\), got 0"),
    (dict(threads=2.0), "threads must be a positive integer"),
    (dict(threads=True), "threads must be a positive integer"),
])
def test_bad_options_are_refused_with_their_name(changes, message):
    with pytest.raises(ValueError, match=message):
        SegmentOptions(**changes)
    with pytest.raises(ValueError, match=message):
        SegmentOptions().replace(**changes)


def test_unknown_option_is_a_type_error():
    with pytest.raises(TypeError):
        SegmentOptions(smoothnes=1.0)


def test_format_point():
    import numpy as np

    assert format_point(np.array([1.0, -2.345, 1e3])) == "(1.00, -2.35, 1000.00)"
    assert format_point(np.array([1.0, -1e308, 2.5e6])) == "(1.00, -1e+308, 2.5e+06)"


def test_parameters_are_the_dataclass_fields():
    """as_parameters is dataclasses.asdict with the patches as a list, a
    fresh dict each time."""
    from dataclasses import asdict

    opts = SegmentOptions(patches=(6, 4), interface=12.5, threads=2, mode="local")
    expected = {**asdict(opts), "patches": [6, 4]}
    assert opts.as_parameters() == expected
    assert list(opts.as_parameters()) == list(expected)
    first = opts.as_parameters()
    first["patches"].append(3)
    assert opts.as_parameters()["patches"] == [6, 4]


@pytest.mark.parametrize("step", [1e-9, 0.001, 0.05, 0.1])
def test_a_step_the_tolerance_cannot_see_is_refused(step):
    """A level stops when an iteration's RMS motion is below its tolerance
    (tol, the coarse levels twice it) and no iteration moves the wall more
    than the step: at or below it every level stopped at once and returned
    the start as converged (round 4: --step 0.001 gave the initial shape)."""
    with pytest.raises(ValueError, match=r"step must be more than .*0\.1 mm, got"):
        SegmentOptions(step=step)
    SegmentOptions(step=step, tol=step / 4, coarse_tol=step / 2)  # a smaller tol sees it
    SegmentOptions(step=0.11)
    with pytest.raises(ValueError, match=r"step must be more than tol, 0\.05 mm"):
        SegmentOptions(step=0.05, coarse_to_fine=False)
