"""Segmentation and tracking of beam-space volumes, sampled directly."""


import numpy as np
import pytest
from scipy.spatial import cKDTree

from spheroseg import track
from spheroseg._compiled._runtime import compiled_available
from spheroseg import segment
from spheroseg.volumes.beamspace import beam_mask, beam_mask_volume_ml, scan_convert, to_beam_space
from spheroseg.synthetic.phantom import FORMATIONS, make_phantom, make_sequence, probe_sector


def mean_distance(a, b):
    """Symmetric mean distance (mm) between two meshes' vertices."""
    pa, pb = a.mesh()[0], b.mesh()[0]
    return 0.5 * (cKDTree(pb).query(pa)[0].mean() + cKDTree(pa).query(pb)[0].mean())


@pytest.mark.parametrize("convention", ["tan", "sin"])
def test_beam_space_and_scan_converted_segmentations_agree(convention):
    ph = make_phantom(seed=1, spacing=1.5)
    beam = to_beam_space(ph.volume, probe_sector(ph.volume, convention=convention))
    # a 1 mm grid: the default (the beams' 1.4 mm spacing at mid depth) blurs
    # the edge more and moves the converted volume up by 1.9 % here, 2-3 %
    # on other phantoms (docs/benchmarks.md, "Beam space")
    cartesian = scan_convert(beam, beam.geometry.cartesian_grid(1.0))
    direct = segment(beam, ph.apex, ph.base)
    converted = segment(cartesian, ph.apex, ph.base)
    assert direct.status == converted.status == 0
    assert mean_distance(direct, converted) < 0.5
    assert direct.volume_ml == pytest.approx(converted.volume_ml, rel=0.02)
    assert direct.volume_ml == pytest.approx(ph.truth_volume_ml, rel=0.10)
    # the mask is drawn in world space, on the grid covering the sector
    mask = direct.mask(beam)
    assert mask.shape == beam.grid.shape
    assert mask.sum() * np.prod(beam.grid.spacing) / 1000 == pytest.approx(direct.volume_ml, rel=0.02)
    # or in beam space, each sample weighted by its cell's volume (the Jacobian)
    in_beams = beam_mask(direct.surface, beam.geometry)
    assert beam_mask_volume_ml(in_beams, beam.geometry) == pytest.approx(direct.volume_ml, rel=0.005)


def test_phantom_formed_in_beam_space():
    """Echo formed in beam space (speckle, PSF, attenuation), segmented there
    and after scan conversion to 1 mm: the surfaces agree to under 0.5 mm;
    the volumes differ by 1.4-2.2 % on seeds 1-4 (the converted one larger:
    its image went through one more interpolation; docs/benchmarks.md,
    "Beam space"), so this checks 2.5 %, not the 2 % the issue hoped for."""
    ph = make_phantom(seed=1, spacing=1.5, formation=FORMATIONS["default"], beam_space=True)
    beam = ph.beam_volume
    direct = segment(beam, ph.apex, ph.base)
    converted = segment(scan_convert(beam, beam.geometry.cartesian_grid(1.0)), ph.apex, ph.base)
    assert mean_distance(direct, converted) < 0.5
    assert direct.volume_ml == pytest.approx(converted.volume_ml, rel=0.025)
    assert direct.volume_ml == pytest.approx(ph.truth_volume_ml, rel=0.03)


@pytest.mark.skipif(not compiled_available(), reason="the compiled kernels are not built")
def test_beam_space_compiled_and_numpy_backends_agree():
    ph = make_phantom(seed=2, spacing=1.5)
    beam = to_beam_space(ph.volume, probe_sector(ph.volume, convention="sin"))
    for mode in ("intensity", "chan-vese"):
        fast = segment(beam, ph.apex, ph.base, mode=mode, backend="compiled")
        ref = segment(beam, ph.apex, ph.base, mode=mode, backend="numpy")
        np.testing.assert_allclose(fast.surface.coefficients, ref.surface.coefficients, atol=1e-6, err_msg=mode)


def test_tracking_a_beam_space_sequence():
    seq = make_sequence(n_frames=4, seed=4, spacing=2.0)
    apex, base = seq.frames[0].apex, seq.frames[0].base
    geometry = probe_sector(seq.volumes[0])
    frames = [to_beam_space(v, geometry) for v in seq.volumes]
    result = track(frames, apex, base)
    fine = geometry.cartesian_grid(1.0)  # finer than the default: less blur added by the conversion
    reference = track([scan_convert(f, fine) for f in frames], apex, base)
    np.testing.assert_allclose(result.volumes_ml, reference.volumes_ml, rtol=0.03)
    # the cycle is seen: end-diastole and end-systole where the truth has them
    assert np.argmax(result.volumes_ml) == np.argmax(seq.truth_volumes_ml)
    assert np.argmin(result.volumes_ml) == np.argmin(seq.truth_volumes_ml)
    # outside the sector: a clear error, not a NaN segmentation
    with pytest.raises(ValueError, match="outside the image"):
        segment(frames[0], apex - [0, 0, 40.0], base)
