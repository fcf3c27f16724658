"""What a segmentation and a tracked sequence return."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._compiled.raster import surface_mask
from ..surfaces.myocardium import (
    SegmentConvention, lv_mass_g, myocardial_volume_ml, segment_table, systolic_dyssynchrony_index, times_to_minimum,
)
from ..surfaces.surface import Surface

__all__ = ["SegmentationResult", "TrackingResult", "Intermediate", "STATUS_MESSAGES"]

#: why a descent stopped, by ``status`` (as scipy's ``OptimizeResult``)
STATUS_MESSAGES = {
    0: "the surface stopped moving (RMS motion below tol)",
    1: "the iteration cap was reached before the surface stopped moving",
    2: "stopped by the caller before the surface stopped moving (iter_callback raised StopIteration)",
}


@dataclass
class SegmentationResult:
    """What :func:`spheroseg.segment` found (or one frame of :func:`spheroseg.track`).

    Attributes
    ----------
    surface : Surface
    iterations : int
        Iterations run, over all levels.
    converged : bool
        Whether the last level stopped on surface motion (not the cap).
    c_in, c_out : float
        Median region means at the end (image units).
    seconds : float
        Wall time of the segmentation.
    parameters : dict
        The options it ran with (:meth:`spheroseg.SegmentOptions.as_parameters`).
    status : int
        Why it stopped: 0 the surface stopped moving, 1 the iteration cap,
        2 ``iter_callback`` raised ``StopIteration``.
    message : str
        The same in words.
    quality : dict
        How far the result can be trusted (:mod:`spheroseg.quality`):
        ``contrast``, ``low_contrast_fraction``, ``no_data_fraction``,
        ``converged``, ``apex_shift_mm``, ``volume_ratio``, ``beyond_wall``
        and ``beyond_wall_fraction``, ``warnings`` and ``poor``; with an
        epicardium also ``epicardium``
        (:func:`spheroseg.quality.wall_report`).
    epicardium : Surface or None
        The epicardium (``segment(..., myocardium=True)``): same system,
        pose and grid as ``surface``, outside it.
    segment_convention : SegmentConvention
        Where segment 1 of the 17-segment model starts
        (:mod:`spheroseg.myocardium`).
    log_compression : float or None
        Grey levels per neper of echo intensity, as the intensity interface
        estimated them from the wall's speckle (``mode="intensity"``, the
        default; None with another data term, or where it found no speckle).
    """

    surface: Surface
    iterations: int
    converged: bool
    c_in: float
    c_out: float
    seconds: float
    parameters: dict = field(default_factory=dict)
    status: int = 0
    message: str = STATUS_MESSAGES[0]
    quality: dict | None = None
    #: how the segmentation was started (:func:`spheroseg.locate.initialise`)
    initialisation: dict | None = None
    epicardium: Surface | None = None
    segment_convention: SegmentConvention = field(default_factory=SegmentConvention)
    log_compression: float | None = None

    @property
    def volume_ml(self) -> float:
        """Volume of the cavity, closed at the base plane (mL)."""
        return self.surface.volume_ml()

    def _need_epicardium(self) -> Surface:
        if self.epicardium is None:
            raise ValueError("this result has no epicardium: segment with myocardium=True")
        return self.epicardium

    def myocardium_mask(self, volume) -> np.ndarray:
        """Boolean mask ``[z, y, x]`` of the myocardium (between the
        surfaces, below the mitral plane) on ``volume``'s grid."""
        return self._need_epicardium().mask(volume.grid) & ~self.surface.mask(volume.grid)

    @property
    def myocardial_volume_ml(self) -> float:
        """Volume of the myocardium below the mitral plane (mL)."""
        return myocardial_volume_ml(self.surface, self._need_epicardium())

    @property
    def lv_mass_g(self) -> float:
        """LV mass (g): the myocardial volume at 1.05 g/mL."""
        return lv_mass_g(self.myocardial_volume_ml)

    @property
    def segments(self) -> list[dict]:
        """The 17-segment table (:func:`spheroseg.myocardium.segment_table`):
        per segment ``segment``, ``name``, ``cavity_ml`` and, with an
        epicardium, ``myocardium_ml`` and ``wall_thickness_mm``."""
        return segment_table(self.surface, self.epicardium, convention=self.segment_convention)

    @property
    def wall_thickness_mm(self) -> np.ndarray:
        """Mean wall thickness of each of the 17 segments (mm, along ``v0``)."""
        self._need_epicardium()
        return np.array([row["wall_thickness_mm"] for row in self.segments])

    def mask(self, volume) -> np.ndarray:
        """Boolean mask ``[z, y, x]`` of the cavity on ``volume``'s grid."""
        return surface_mask(self.surface, volume.grid)

    def mesh(self, n_v1: int = 64, n_v2: int = 32, *, closed: bool = True):
        """Triangle mesh ``(points [n, 3] world mm, faces [m, 3])``."""
        return self.surface.mesh(n_v1, n_v2, closed=closed)


@dataclass
class TrackingResult:
    """Per-frame results of :func:`spheroseg.track`, and the clinical indices;
    ``start_frame``, the frame the points were placed on (tracked forwards
    and then backwards from it)."""

    frames: list[SegmentationResult]
    start_frame: int = 0

    @property
    def initialisation(self) -> dict | None:
        """How the start frame was started (:func:`spheroseg.tracking.locate.initialise`)."""
        return self.frames[self.start_frame].initialisation if self.frames else None

    @property
    def volumes_ml(self) -> np.ndarray:
        return np.array([f.volume_ml for f in self.frames])

    @property
    def ed_frame(self) -> int:
        """End-diastole: the frame of largest volume."""
        return int(np.argmax(self.volumes_ml))

    @property
    def es_frame(self) -> int:
        """End-systole: the frame of smallest volume."""
        return int(np.argmin(self.volumes_ml))

    @property
    def edv_ml(self) -> float:
        return float(self.volumes_ml.max())

    @property
    def esv_ml(self) -> float:
        return float(self.volumes_ml.min())

    @property
    def ef(self) -> float:
        """Ejection fraction in percent, ``100 (EDV - ESV) / EDV``."""
        return 100.0 * (self.edv_ml - self.esv_ml) / self.edv_ml

    @property
    def segment_volumes_ml(self) -> np.ndarray:
        """Cavity volume (mL) of each of the 17 segments at every frame,
        ``[frame, segment - 1]``, each frame cut by its own levels and base
        plane (segment 17, beyond the cavity, holds none)."""
        return np.array([[row["cavity_ml"] for row in segment_table(f.surface, convention=f.segment_convention)]
                         for f in self.frames])

    @property
    def times_to_minimum(self) -> np.ndarray:
        """Time of each of the 16 cavity segments' minimum volume, % of the
        cycle (the frames being one cycle from frame 0;
        :func:`spheroseg.myocardium.times_to_minimum`)."""
        return times_to_minimum(self.segment_volumes_ml[:, :16])

    @property
    def sdi(self) -> float:
        """Systolic dyssynchrony index, % of the cycle (Kapetanakis et al.
        2005): the standard deviation of :attr:`times_to_minimum`."""
        return systolic_dyssynchrony_index(self.segment_volumes_ml)

    @property
    def masses_g(self) -> np.ndarray:
        """LV mass (g) at every frame (``track(..., myocardium=True)``)."""
        return np.array([f.lv_mass_g for f in self.frames])

    @property
    def quality(self) -> dict:
        """The frames' quality reports: ``poor`` if any frame's is, their
        ``warnings`` prefixed with the frame, and ``frames`` (one each)."""
        reports = [f.quality or {} for f in self.frames]
        warnings = [f"frame {t}: {w}" for t, q in enumerate(reports) for w in q.get("warnings", [])]
        return {"poor": bool(warnings) or any(q.get("poor", False) for q in reports), "warnings": warnings,
                "frames": reports}


@dataclass(frozen=True)
class Intermediate:
    """What ``iter_callback`` receives after each iteration.

    Attributes
    ----------
    surface : Surface
        The surface after the iteration.
    iteration : int
        Iterations run so far in this frame (1 after the first).
    level : int
        Index of the coarse-to-fine level it ran on.
    patches : (int, int)
        That level's patches.
    motion : float
        RMS motion of the surface in the iteration (mm).
    """

    surface: Surface
    iteration: int
    level: int
    patches: tuple[int, int]
    motion: float
