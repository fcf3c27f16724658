"""Pictures of a result: orthogonal slices with the contour, a 3D view of
the mesh and, for sequences, the volume curve.  Matplotlib, no screen."""

from __future__ import annotations

import os

import numpy as np

from .surface import Surface
from .volume import Volume

__all__ = ["report_figure", "save_report"]


def _slices(ax_row, volume: Volume, mask: np.ndarray, centre_world, truth: np.ndarray | None = None):
    k, j, i = np.clip(np.round(volume.world_to_index(centre_world)[::-1]).astype(int), 0, np.array(volume.shape) - 1)
    sx, sy, sz = volume.spacing
    views = [
        ("axial (z = %d)" % k, volume.array[k], mask[k], None if truth is None else truth[k], sx / sy),
        ("coronal (y = %d)" % j, volume.array[:, j], mask[:, j], None if truth is None else truth[:, j], sx / sz),
        ("sagittal (x = %d)" % i, volume.array[:, :, i], mask[:, :, i], None if truth is None else truth[:, :, i], sy / sz),
    ]
    for ax, (title, image, m, t, aspect) in zip(ax_row, views):
        ax.imshow(image, cmap="gray", aspect=1 / aspect, interpolation="nearest")
        if m.any():
            ax.contour(m, [0.5], colors="yellow", linewidths=1.0)
        if t is not None and t.any():
            ax.contour(t, [0.5], colors="red", linewidths=0.8)
        ax.set_title(title, fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])


def report_figure(volume: Volume, surface: Surface, *, mask=None, volumes_ml=None, ed_frame=None, es_frame=None,
                  title: str = "", truth_mask=None):
    """A matplotlib figure: three slices through the cavity centre with the
    contour (yellow; truth red when given), the mesh in 3D and, with
    ``volumes_ml``, the volume curve with ED and ES marked."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    if mask is None:
        mask = surface.mask(volume.grid)
    n_cols = 5 if volumes_ml is not None else 4
    fig = plt.figure(figsize=(4 * n_cols, 4.2))
    axes = [fig.add_subplot(1, n_cols, c + 1) for c in range(3)]
    points, faces = surface.mesh(48, 24)
    centre = points.mean(0)
    _slices(axes, volume, mask, centre, truth_mask)
    ax3 = fig.add_subplot(1, n_cols, 4, projection="3d")
    ax3.plot_trisurf(points[:, 0], points[:, 1], points[:, 2], triangles=faces, color="tab:orange", alpha=0.85,
                     linewidth=0.1, edgecolor="k")
    span = np.ptp(points, axis=0).max() / 2
    for setter, c in zip((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim), centre):
        setter(c - span, c + span)
    ax3.invert_zaxis()  # depth grows downwards, as in the slices
    ax3.set_title(f"cavity {surface.volume_ml():.1f} mL", fontsize=9)
    ax3.set_xlabel("x (mm)", fontsize=7)
    ax3.set_ylabel("y (mm)", fontsize=7)
    ax3.set_zlabel("z (mm)", fontsize=7)
    if volumes_ml is not None:
        ax = fig.add_subplot(1, n_cols, 5)
        v = np.asarray(volumes_ml)
        ax.plot(np.arange(len(v)), v, "o-", color="tab:blue")
        for frame, label, colour in ((ed_frame, "ED", "tab:red"), (es_frame, "ES", "tab:green")):
            if frame is not None:
                ax.plot(frame, v[frame], "s", color=colour, markersize=9)
                ax.annotate(f"{label} {v[frame]:.0f} mL", (frame, v[frame]), textcoords="offset points",
                            xytext=(5, 5), fontsize=8)
        ax.set_xlabel("frame")
        ax.set_ylabel("volume (mL)")
        ax.set_title("cavity volume", fontsize=9)
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def save_report(path: str | os.PathLike, volume: Volume, surface: Surface, **kwargs) -> None:
    """Write :func:`report_figure` as a PNG, atomically."""
    import matplotlib.pyplot as plt

    from .io import write_atomically

    fig = report_figure(volume, surface, **kwargs)
    try:
        write_atomically(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    finally:
        plt.close(fig)
