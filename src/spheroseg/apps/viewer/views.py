"""Standard views of a segmented ventricle: planes through its long axis
(apical 4-, 2- and 3-chamber) and across it (short axis at three levels),
resampled from the image, with the surface's contour on each.

The long axis is the surface's (``surface.pose``: from the base point towards
the apex).  Nothing in the image says where the right ventricle is, so the
4-chamber plane is taken as the long-axis plane nearest the probe's
left-right (azimuth) plane, as an apical acquisition is usually aligned; the
2- and 3-chamber planes are turned 60 and 120 degrees from it about the
axis.  The page says so beside the views.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

#: long-axis views: name and angle about the long axis from the 4-chamber plane (degrees)
LONG_AXIS = (("4C", 0.0), ("2C", 60.0), ("3C", 120.0))
#: short-axis views: name and level, the fraction of the base-to-apex length from the base
SHORT_AXIS = (("SAX basal", 0.2), ("SAX mid", 0.5), ("SAX apical", 0.8))


@dataclass(frozen=True)
class View:
    """A plane sampled as an image of ``rows`` x ``cols`` pixels of
    ``pixel_mm``: pixel (col, row) is at ``centre + (col - (cols - 1) / 2)
    * pixel_mm * u - (row - (rows - 1) / 2) * pixel_mm * v`` (world mm; ``v``
    points up the image: towards the apex on a long-axis view)."""

    name: str
    centre: np.ndarray
    u: np.ndarray
    v: np.ndarray
    pixel_mm: float
    rows: int
    cols: int

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.u, self.v)

    def to_world(self, col, row) -> np.ndarray:
        """World points (..., 3) of pixel coordinates (col, row)."""
        col, row = np.asarray(col, float), np.asarray(row, float)
        a = (col - (self.cols - 1) / 2) * self.pixel_mm
        b = ((self.rows - 1) / 2 - row) * self.pixel_mm
        return self.centre + a[..., None] * self.u + b[..., None] * self.v

    def to_pixel(self, world) -> np.ndarray:
        """(col, row) of world points (..., 3) projected onto the plane."""
        d = np.asarray(world, float) - self.centre
        return np.stack([d @ self.u / self.pixel_mm + (self.cols - 1) / 2,
                         (self.rows - 1) / 2 - d @ self.v / self.pixel_mm], axis=-1)

    def as_json(self) -> dict:
        return {"name": self.name, "centre": self.centre.tolist(), "u": self.u.tolist(), "v": self.v.tolist(),
                "pixel_mm": self.pixel_mm, "rows": self.rows, "cols": self.cols}


def standard_views(surface, *, pixels: int = 160, reference=(1.0, 0.0, 0.0)) -> list[View]:
    """The six standard views of ``surface``: 4C, 2C, 3C, then the short-axis
    views from base to apex, each ``pixels`` square, wide enough for the
    cavity with a margin of half its size.

    Parameters
    ----------
    surface : Surface
        The cavity; its pose gives the long axis and the base point.
    pixels : int
        Image size (pixels a side).
    reference : (3,) world direction
        The 4-chamber plane contains the long axis and this direction's part
        perpendicular to it (default: the image's x axis, left-right in LPS).
    """
    axis = surface.pose.axis
    base = surface.pose.origin
    vertices = surface.mesh(48, 24)[0]
    local = (vertices - base) @ axis
    length = float(local.max())  # the apex's distance from the base point along the axis
    radius = float(np.linalg.norm((vertices - base) - np.outer(local, axis), axis=1).max())
    r = np.asarray(reference, float)
    r = r - (r @ axis) * axis
    if np.linalg.norm(r) < 1e-6:  # the axis along the reference: any perpendicular
        r = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    side = np.cross(axis, r)
    width = 1.5 * max(length, 2 * radius)
    pixel_mm = width / pixels
    views = []
    for name, degrees in LONG_AXIS:
        t = np.radians(degrees)
        u = np.cos(t) * r + np.sin(t) * side
        views.append(View(name, base + 0.5 * length * axis, u, axis.copy(), pixel_mm, pixels, pixels))
    for name, level in SHORT_AXIS:
        views.append(View(name, base + level * length * axis, r.copy(), side.copy(), pixel_mm, pixels, pixels))
    return views


def sample(volume, view: View, *, lo: float, hi: float) -> np.ndarray:
    """``volume`` on ``view``'s pixels, trilinear, scaled from ``lo``-``hi``
    to 0-255 (uint8, rows x cols); outside the image and in its no-data
    region 0."""
    rows, cols = np.mgrid[0:view.rows, 0:view.cols]
    world = view.to_world(cols, rows)
    index = volume.world_to_index(world.reshape(-1, 3))[:, ::-1].T  # (z, y, x) for the array
    values = ndimage.map_coordinates(volume.array.astype(np.float32), index, order=1, mode="constant", cval=lo)
    if volume.no_data_mask is not None:
        empty = ndimage.map_coordinates(volume.no_data_mask.astype(np.float32), index, order=0, mode="constant",
                                        cval=1.0)
        values[empty > 0.5] = lo
    scale = 255.0 / (hi - lo) if hi > lo else 1.0
    return np.clip(np.rint((values - lo) * scale), 0, 255).astype(np.uint8).reshape(view.rows, view.cols)


def contour(vertices, faces, view: View) -> np.ndarray:
    """The mesh's cut by the view's plane: segments (k, 4) as pixel
    coordinates (col0, row0, col1, row1)."""
    d = (np.asarray(vertices, float) - view.centre) @ view.normal
    segments = []
    for triangle in np.asarray(faces):
        cut = []
        for e in range(3):
            i, j = triangle[e], triangle[(e + 1) % 3]
            if (d[i] < 0) != (d[j] < 0):
                s = d[i] / (d[i] - d[j])
                cut.append(vertices[i] + s * (vertices[j] - vertices[i]))
        if len(cut) == 2:
            segments.append(np.concatenate([view.to_pixel(cut[0]), view.to_pixel(cut[1])]))
    return np.reshape(segments, (-1, 4))
