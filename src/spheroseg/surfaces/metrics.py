"""Agreement with a reference: Dice, surface distances, volumes, ejection
fraction, with the CETUS challenge's conventions (Bernard et al. 2016).

Surface distances are computed one documented way: each surface (a
triangle mesh of the endocardial wall, open at the mitral plane as the
CETUS references are) is sampled uniformly by area at about 0.3 mm spacing
plus its vertices; the distance from each sample of one surface to the
other is the distance to the nearest sample of the other (so it is exact to
about 0.15 mm).  Then

* mean surface distance = mean of the two directed mean distances,
* Hausdorff distance = the larger of the two directed maximum distances.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .fit import surface_sample

__all__ = ["dice", "surface_distances", "ejection_fraction", "mask_volume_ml"]


def dice(a: np.ndarray, b: np.ndarray) -> float:
    """Dice coefficient ``2 |A & B| / (|A| + |B|)`` of two boolean masks."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    if a.shape != b.shape:
        raise ValueError(f"masks differ in shape: {a.shape} and {b.shape}")
    total = a.sum() + b.sum()
    return float(2.0 * np.logical_and(a, b).sum() / total) if total else 1.0


def surface_distances(mesh_a, mesh_b, *, spacing: float = 0.3) -> dict:
    """Mean (symmetric) and Hausdorff distances between two meshes (mm).

    Parameters
    ----------
    mesh_a, mesh_b : (points [n, 3], faces [m, 3])

    Returns
    -------
    dict
        ``mean``: average of the two directed mean distances;
        ``hausdorff``: the larger directed maximum; ``a_to_b``,
        ``b_to_a``: the directed means.
    """
    sa = surface_sample(*mesh_a, spacing=spacing)
    sb = surface_sample(*mesh_b, spacing=spacing)
    d_ab = cKDTree(sb).query(sa)[0]
    d_ba = cKDTree(sa).query(sb)[0]
    return {
        "mean": float((d_ab.mean() + d_ba.mean()) / 2),
        "hausdorff": float(max(d_ab.max(), d_ba.max())),
        "a_to_b": float(d_ab.mean()),
        "b_to_a": float(d_ba.mean()),
    }


def ejection_fraction(edv_ml: float, esv_ml: float) -> float:
    """``100 (EDV - ESV) / EDV`` in percent."""
    if not edv_ml > 0:
        raise ValueError(f"EDV must be positive, got {edv_ml!r}")
    return 100.0 * (edv_ml - esv_ml) / edv_ml


def mask_volume_ml(mask: np.ndarray, spacing) -> float:
    """Volume of a boolean mask in mL (voxel count times voxel volume)."""
    return float(np.count_nonzero(mask) * np.prod(np.asarray(spacing, float)) / 1000.0)
