"""The quality report, and robustness on image formations that broke round 1."""

import numpy as np
import pytest

from spheroseg import segment
from spheroseg.metrics import dice
from spheroseg.phantom import FORMATIONS, make_phantom
from spheroseg.quality import quality_report


def test_report_flags_what_is_out_of_the_ordinary():
    good = quality_report(contrast=2.0, low_contrast_fraction=0.0, no_data_fraction=0.0, converged=True,
                          apex_shift_mm=1.0, volume_ratio=1.1)
    assert not good["poor"] and good["warnings"] == []
    bad = quality_report(contrast=0.2, low_contrast_fraction=0.5, no_data_fraction=0.3, converged=False,
                         apex_shift_mm=25.0, volume_ratio=0.2)
    assert bad["poor"] and len(bad["warnings"]) == 6
    assert any("apex moved 25 mm" in w for w in bad["warnings"])


@pytest.mark.parametrize("formation", ["clutter_strong", "contrast_low", "dropout"])
def test_no_collapse_on_hard_image_formations(formation):
    """Strong near-field clutter in the cavity, a dim myocardium, a dark wall
    region: a ventricle-shaped result (Dice >= 0.85), the apex where clicked."""
    ph = make_phantom(seed=0, spacing=1.5, formation=FORMATIONS[formation])
    r = segment(ph.volume, ph.apex, ph.base)
    assert dice(r.mask(ph.volume), ph.truth_mask) >= 0.85
    assert r.quality["apex_shift_mm"] < 5.0


def test_a_click_5_mm_off_is_survived():
    ph = make_phantom(seed=0, spacing=1.5, formation=FORMATIONS["default"])
    rng = np.random.default_rng(3)
    for _ in range(2):
        offsets = rng.normal(size=(2, 3))
        offsets *= 5.0 / np.linalg.norm(offsets, axis=1, keepdims=True)
        r = segment(ph.volume, ph.apex + offsets[0], ph.base + offsets[1])
        assert dice(r.mask(ph.volume), ph.truth_mask) >= 0.85


def test_a_collapse_is_reported():
    """With the apex free to move (round 1's weak hold), strong clutter pulls
    the surface towards the base: the report says so."""
    ph = make_phantom(seed=0, spacing=1.5, formation=FORMATIONS["clutter_strong"])
    weak = segment(ph.volume, ph.apex, ph.base, apex_weight=1.0)
    assert weak.quality["poor"] and weak.quality["apex_shift_mm"] > 10
    held = segment(ph.volume, ph.apex, ph.base)
    assert not held.quality["poor"], held.quality


def test_one_warning_line_for_the_cli():
    from types import SimpleNamespace

    from spheroseg.quality import quality_warning

    fine = SimpleNamespace(quality={"poor": False, "warnings": []})
    poor = SimpleNamespace(quality={"poor": True, "warnings": ["the apex moved 31 mm from the clicked point"]})
    assert quality_warning([fine]) is None
    assert quality_warning([poor]) == "check this segmentation: the apex moved 31 mm from the clicked point"
    line = quality_warning([fine, poor, poor])
    assert "\n" not in line and line.startswith("check frame(s) 1, 2:")
