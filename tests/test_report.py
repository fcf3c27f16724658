import numpy as np

from spheroseg.surfaces.myocardium import SegmentConvention, segment_labels


def test_bullseye_places_and_colours_the_segments_as_defined():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import colormaps

    from spheroseg.io.report import draw_bullseye

    fig, ax = plt.subplots()
    values = np.arange(17.0)
    draw_bullseye(ax, values, label="x")
    wedges = ax.patches
    assert len(wedges) == 17
    # each ring wedge's centre on the page, turned back to psi and a height,
    # is labelled with its own segment (page angle = 120 degrees + psi)
    radius_to_height = {3.5: 0.1, 2.5: 0.5, 1.5: 0.8}
    for wedge in wedges[:16]:
        mid = np.radians((wedge.theta1 + wedge.theta2) / 2)
        r = wedge.r - wedge.width / 2
        psi = mid - np.radians(120.0)
        point = np.array([radius_to_height[r] * 90.0, np.cos(psi), np.sin(psi)])
        k = int(segment_labels(point, length=90.0, convention=SegmentConvention()))
        colour = colormaps["viridis"]((k - 1) / 16)
        np.testing.assert_allclose(wedge.get_facecolor(), colour, atol=1e-6)
    np.testing.assert_allclose(wedges[16].get_facecolor(), colormaps["viridis"](1.0), atol=1e-6)  # the apex
    plt.close(fig)


def test_the_report_draws_the_epicardium_beside_the_endocardium():
    """The slices carry the epicardium's region; the figure draws one
    contour more for it (blue), and none without it."""
    from spheroseg.synthetic.phantom import make_phantom
    from spheroseg.io.report import parts_figure, report_parts
    from spheroseg.surfaces.surface import Surface

    ph = make_phantom(seed=3, spacing=3.0)
    endo = Surface.from_apex_base(ph.apex, ph.base)
    from scipy import ndimage

    outer = ndimage.binary_dilation(endo.mask(ph.volume.grid), iterations=2)
    with_epi = report_parts(ph.volume, endo, epicardium_mask=outer)
    for view in with_epi["slices"]:
        assert view["epicardium"].shape == view["mask"].shape and view["epicardium"].sum() > view["mask"].sum()
    assert all(view["epicardium"] is None for view in report_parts(ph.volume, endo)["slices"])

    def contour_colours(parts):
        fig = parts_figure(parts)
        return [tuple(np.round(c.get_edgecolor()[0][:3], 3)) for ax in fig.axes[:3] for c in ax.collections]

    import matplotlib.colors as mcolors

    blue = tuple(np.round(mcolors.to_rgb("deepskyblue"), 3))
    assert sum(c == blue for c in contour_colours(with_epi)) == 3
    assert blue not in contour_colours(report_parts(ph.volume, endo))
