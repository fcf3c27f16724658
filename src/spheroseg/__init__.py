"""spheroseg: real-time left-ventricle segmentation in 3D echocardiography
with an explicit bicubic Hermite surface in prolate spheroidal coordinates."""

from .coords import Cylindrical, Pose, ProlateSpheroidal, Spherical
from .hermite import HermiteGrid
from .surface import ImageGrid, Surface

__version__ = "0.1.0"
