"""spheroseg: real-time left-ventricle segmentation in 3D echocardiography
with an explicit bicubic Hermite surface in prolate spheroidal coordinates.

>>> import spheroseg
>>> vol = spheroseg.load("case.mhd")                      # doctest: +SKIP
>>> res = spheroseg.segment(vol, apex=(x, y, z), base=(x, y, z))  # doctest: +SKIP
>>> res.volume_ml, res.mask(vol), res.mesh()             # doctest: +SKIP
"""

from ._version import __version__

from .beamspace import BeamGeometry, BeamVolume, scan_convert, to_beam_space
from .coords import Cylindrical, Pose, ProlateSpheroidal, Spherical
from .hermite import HermiteGrid
from .batch import segment_many
from .io import ImageFileError, load, load_sequence, save_mask, save_volume
from .locate import Located, NoVentricleError, locate
from .options import SegmentOptions
from .results import Intermediate, SegmentationResult, TrackingResult
from .segment import segment, track
from .surface import Surface
from .tracker import Tracker
from .volume import ImageGrid, Volume

__all__ = [
    "load", "load_sequence", "save_mask", "segment", "track", "Tracker", "SegmentOptions", "Intermediate",
    "Volume", "Surface", "ImageGrid", "Pose", "ProlateSpheroidal", "Spherical", "Cylindrical", "HermiteGrid",
    "SegmentationResult", "TrackingResult", "ImageFileError", "BeamGeometry", "BeamVolume", "scan_convert",
    "to_beam_space", "save_volume", "segment_many", "locate", "Located", "NoVentricleError",
]
