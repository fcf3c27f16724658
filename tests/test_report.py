import numpy as np

from spheroseg.myocardium import SegmentConvention, segment_labels


def test_bullseye_places_and_colours_the_segments_as_defined():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib import colormaps

    from spheroseg.report import draw_bullseye

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
