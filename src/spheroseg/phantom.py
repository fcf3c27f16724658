"""Deprecated alias of :mod:`spheroseg.synthetic.phantom` (moved there in 0.4;
this name goes in the next release)."""

import sys
import warnings

from .synthetic import phantom as _moved

warnings.warn("spheroseg.phantom moved to spheroseg.synthetic.phantom; the old name goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
