"""Pictures of a result: orthogonal slices with the contour, a 3D view of
the mesh and, for sequences, the volume curve.  Matplotlib, no screen."""

from __future__ import annotations

import os

import numpy as np

from .._compiled.raster import surface_mask
from ..surfaces.surface import Surface
from ..volumes.volume import Volume

__all__ = ["report_figure", "save_report", "report_parts", "parts_figure", "save_parts", "draw_bullseye"]


def report_parts(volume: Volume, surface: Surface, *, mask=None, volumes_ml=None, ed_frame=None, es_frame=None,
                 title: str = "", truth_mask=None, wall_thickness_mm=None, epicardium_mask=None) -> dict:
    """What :func:`report_figure` draws, as plain arrays (small: three
    slices, not the volume), so that another process can draw it.
    ``epicardium_mask`` (bool ``[z, y, x]``): the region inside the
    epicardium, whose contour is drawn beside the endocardium's."""
    if mask is None:
        mask = surface_mask(surface, volume.grid)
    points, faces = surface.mesh(48, 24)
    centre = points.mean(0)
    k, j, i = np.clip(np.round(volume.world_to_index(centre)[::-1]).astype(int), 0, np.array(volume.shape) - 1)
    sx, sy, sz = volume.spacing
    slices = []
    for name, index, aspect in ((f"axial (z = {k})", np.s_[k], sx / sy), (f"coronal (y = {j})", np.s_[:, j], sx / sz),
                                (f"sagittal (x = {i})", np.s_[:, :, i], sy / sz)):
        slices.append({"title": name, "image": volume.array[index], "mask": np.asarray(mask[index]),
                       "truth": None if truth_mask is None else np.asarray(truth_mask[index]), "aspect": aspect,
                       "epicardium": None if epicardium_mask is None else np.asarray(epicardium_mask[index])})
    return {"slices": slices, "points": points, "faces": faces, "centre": centre, "volume_ml": surface.volume_ml(),
            "volumes_ml": None if volumes_ml is None else np.asarray(volumes_ml, dtype=float), "ed_frame": ed_frame,
            "es_frame": es_frame, "title": title,
            "wall_thickness_mm": None if wall_thickness_mm is None else np.asarray(wall_thickness_mm, dtype=float)}


def parts_figure(parts: dict):
    """The matplotlib figure of :func:`report_parts`."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    wall = parts.get("wall_thickness_mm")
    n_cols = (5 if parts["volumes_ml"] is not None else 4) + (wall is not None)
    fig = plt.figure(figsize=(4 * n_cols, 4.2))
    for c, view in enumerate(parts["slices"]):
        ax = fig.add_subplot(1, n_cols, c + 1)
        ax.imshow(view["image"], cmap="gray", aspect=1 / view["aspect"], interpolation="nearest")
        if view["mask"].any():
            ax.contour(view["mask"], [0.5], colors="yellow", linewidths=1.0)
        if view.get("epicardium") is not None and view["epicardium"].any():
            ax.contour(view["epicardium"], [0.5], colors="deepskyblue", linewidths=1.0)
        if view["truth"] is not None and view["truth"].any():
            ax.contour(view["truth"], [0.5], colors="red", linewidths=0.8)
        ax.set_title(view["title"], fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    points, faces, centre = parts["points"], parts["faces"], parts["centre"]
    ax3 = fig.add_subplot(1, n_cols, 4, projection="3d")
    ax3.plot_trisurf(points[:, 0], points[:, 1], points[:, 2], triangles=faces, color="tab:orange", alpha=0.85,
                     linewidth=0.1, edgecolor="k")
    span = np.ptp(points, axis=0).max() / 2
    for setter, c in zip((ax3.set_xlim, ax3.set_ylim, ax3.set_zlim), centre):
        setter(c - span, c + span)
    ax3.invert_zaxis()  # depth grows downwards, as in the slices
    ax3.set_box_aspect(None, zoom=0.85)  # its z label inside its panel (the margins are fixed)
    ax3.set_title(f"cavity {parts['volume_ml']:.1f} mL", fontsize=9)
    ax3.set_xlabel("x (mm)", fontsize=7)
    ax3.set_ylabel("y (mm)", fontsize=7)
    ax3.set_zlabel("z (mm)", fontsize=7)
    if parts["volumes_ml"] is not None:
        ax = fig.add_subplot(1, n_cols, 5)
        v = parts["volumes_ml"]
        ax.plot(np.arange(len(v)), v, "o-", color="tab:blue")
        for frame, label, colour in ((parts["ed_frame"], "ED", "tab:red"), (parts["es_frame"], "ES", "tab:green")):
            if frame is not None:
                ax.plot(frame, v[frame], "s", color=colour, markersize=9)
                ax.annotate(f"{label} {v[frame]:.0f} mL", (frame, v[frame]), textcoords="offset points",
                            xytext=(5, 5), fontsize=8)
        ax.set_xlabel("frame")
        ax.set_ylabel("volume (mL)")
        ax.set_title("cavity volume", fontsize=9)
        ax.grid(alpha=0.3)
    if wall is not None:
        ax = fig.add_subplot(1, n_cols, n_cols)
        draw_bullseye(ax, wall, label="wall thickness (mm)")
        ax.set_title("17 segments, seen from the apex", fontsize=9)
    if parts["title"]:
        fig.suptitle(parts["title"], fontsize=10)
    # fixed margins for the one row of panels: tight_layout would draw the
    # figure once more only to measure it
    fig.subplots_adjust(left=0.01, right=0.98, bottom=0.1, top=0.86, wspace=0.3)
    return fig


def report_figure(volume: Volume, surface: Surface, **kwargs):
    """A matplotlib figure: three slices through the cavity centre with the
    contour (yellow; truth red when given), the mesh in 3D, with
    ``volumes_ml`` the volume curve with ED and ES marked, and with
    ``wall_thickness_mm`` (17 values) the bull's-eye of the wall thickness
    (:func:`draw_bullseye`).  Keywords as :func:`report_parts`."""
    return parts_figure(report_parts(volume, surface, **kwargs))


def save_parts(path: str | os.PathLike, parts: dict) -> None:
    """Write :func:`parts_figure` as a PNG, atomically."""
    import matplotlib.pyplot as plt

    from . import write_atomically

    fig = parts_figure(parts)
    try:
        write_atomically(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"))
    finally:
        plt.close(fig)


def save_report(path: str | os.PathLike, volume: Volume, surface: Surface, **kwargs) -> None:
    """Write :func:`report_figure` as a PNG, atomically."""
    save_parts(path, report_parts(volume, surface, **kwargs))


def draw_bullseye(ax, values=None, *, label: str = "", cmap: str = "viridis", numbers: bool = True):
    """The 17-segment bull's-eye (Cerqueira et al. 2002) on a matplotlib
    axes: the apex in the centre, the apical, mid and basal rings around it,
    seen from the apex with the anterior wall at the top and the septum on
    the left (``psi`` of :mod:`spheroseg.myocardium` anticlockwise from the
    anterior RV insertion, at 120 degrees on the page).

    Parameters
    ----------
    values : array (17,), optional
        A value per segment, coloured by ``cmap`` (NaN: grey); none: white.
    label : str
        The colour bar's label.
    """
    from matplotlib import cm, colormaps, colors
    from matplotlib.patches import Wedge

    values = None if values is None else np.asarray(values, dtype=float)
    if values is not None and np.isfinite(values).any():
        norm = colors.Normalize(np.nanmin(values), np.nanmax(values))
        colour = lambda k: colormaps[cmap](norm(values[k])) if np.isfinite(values[k]) else "0.8"  # noqa: E731
    else:
        norm, colour = None, lambda k: "white"  # noqa: E731
    # (ring's inner and outer radius, first segment, count, psi where segment 1 of the ring starts)
    rings = ((3, 4, 1, 6, -60.0), (2, 3, 7, 6, -60.0), (1, 2, 13, 4, -75.0))
    for inner, outer, first, count, start in rings:
        width = 360.0 / count
        for s in range(count):
            a0 = 120.0 + start + s * width
            ax.add_patch(Wedge((0, 0), outer, a0, a0 + width, width=outer - inner, facecolor=colour(first - 1 + s),
                               edgecolor="black", linewidth=1))
            if numbers:
                mid, r = np.radians(a0 + width / 2), (inner + outer) / 2
                ax.text(r * np.cos(mid), r * np.sin(mid), str(first + s), ha="center", va="center", fontsize=8)
    ax.add_patch(Wedge((0, 0), 1, 0, 360, facecolor=colour(16), edgecolor="black", linewidth=1))
    if numbers:
        ax.text(0, 0, "17", ha="center", va="center", fontsize=8)
    ax.set_xlim(-4.3, 4.3)
    ax.set_ylim(-4.3, 4.3)
    ax.set_aspect("equal")
    ax.axis("off")
    if norm is not None:
        ax.figure.colorbar(cm.ScalarMappable(norm=norm, cmap=cmap), ax=ax, shrink=0.7, label=label)
