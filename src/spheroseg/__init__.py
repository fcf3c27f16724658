"""spheroseg: real-time left-ventricle segmentation in 3D echocardiography
with an explicit bicubic Hermite surface in prolate spheroidal coordinates.

>>> import spheroseg
>>> vol = spheroseg.load("case.mhd")                      # doctest: +SKIP
>>> res = spheroseg.segment(vol, apex=(x, y, z), base=(x, y, z))  # doctest: +SKIP
>>> res.volume_ml, res.mask(vol), res.mesh()             # doctest: +SKIP

The package is in layers, each a folder that imports only the folders
listed above it:

- :mod:`spheroseg.geometry`: prolate spheroidal coordinates, Hermite
  interpolation, the discretisation and the energy terms.
- :mod:`spheroseg._compiled`: the compiled kernels and their runtime.
- :mod:`spheroseg.volumes`: images with their geometry, beam space.
- :mod:`spheroseg.surfaces`: the ventricle's surface on an image, the
  myocardium, fits and metrics.
- :mod:`spheroseg.synthetic`: synthetic echo with its truth.
- :mod:`spheroseg.descent`: the data terms and the descent of a surface.
- :mod:`spheroseg.tracking`: locating, segmenting and tracking the ventricle.
- :mod:`spheroseg.io`: the field's files, outputs and reports.
- :mod:`spheroseg.apps`: the command line, batches and the viewer.
"""

import importlib as _importlib
import sys as _sys
import typing as _typing

from ._moved import MOVED as _MOVED
from ._moved import install as _install_aliases
from ._version import __version__

#: each public name and the module it is read from, imported on first use
#: (PEP 562): ``import spheroseg`` loads neither numpy's neighbours (SciPy,
#: SimpleITK, matplotlib, meshio) nor the layers until a name is used
_PUBLIC = {
    "load": "io", "load_sequence": "io", "save_mask": "io", "save_volume": "io", "ImageFileError": "io",
    "segment": "tracking.segment", "track": "tracking.segment", "Tracker": "tracking.tracker",
    "SegmentOptions": "descent.options", "Intermediate": "descent.results",
    "SegmentationResult": "descent.results", "TrackingResult": "descent.results",
    "Volume": "volumes.volume", "ImageGrid": "volumes.volume", "Surface": "surfaces.surface",
    "Pose": "geometry.coords", "ProlateSpheroidal": "geometry.coords", "Spherical": "geometry.coords",
    "Cylindrical": "geometry.coords", "HermiteGrid": "geometry.hermite",
    "BeamGeometry": "volumes.beamspace", "BeamVolume": "volumes.beamspace", "scan_convert": "volumes.beamspace",
    "to_beam_space": "volumes.beamspace", "segment_many": "apps.batch",
    "locate": "tracking.locate", "Located": "tracking.locate", "NoVentricleError": "tracking.locate",
}

__all__ = [
    "load", "load_sequence", "save_mask", "segment", "track", "Tracker", "SegmentOptions", "Intermediate",
    "Volume", "Surface", "ImageGrid", "Pose", "ProlateSpheroidal", "Spherical", "Cylindrical", "HermiteGrid",
    "SegmentationResult", "TrackingResult", "ImageFileError", "BeamGeometry", "BeamVolume", "scan_convert",
    "to_beam_space", "save_volume", "segment_many", "locate", "Located", "NoVentricleError",
]

if _typing.TYPE_CHECKING:  # pragma: no cover - what type checkers and IDEs read
    from .apps.batch import segment_many
    from .descent.options import SegmentOptions
    from .descent.results import Intermediate, SegmentationResult, TrackingResult
    from .geometry.coords import Cylindrical, Pose, ProlateSpheroidal, Spherical
    from .geometry.hermite import HermiteGrid
    from .io import ImageFileError, load, load_sequence, save_mask, save_volume
    from .surfaces.surface import Surface
    from .tracking.locate import Located, NoVentricleError, locate
    from .tracking.segment import segment, track
    from .tracking.tracker import Tracker
    from .volumes.beamspace import BeamGeometry, BeamVolume, scan_convert, to_beam_space
    from .volumes.volume import ImageGrid, Volume


_install_aliases(_sys.modules[__name__])


def __getattr__(name: str):
    if name in _PUBLIC:
        value = getattr(_importlib.import_module(f"{__name__}.{_PUBLIC[name]}"), name)
        globals()[name] = value  # found once: later reads are plain attribute reads
        return value
    # ``from spheroseg import volume``: an old module path, as the finder serves it
    if name in _MOVED:
        return _importlib.import_module(f"{__name__}.{name}")
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
