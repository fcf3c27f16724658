"""Deprecated alias of :mod:`spheroseg.synthetic.echo` (moved there in 0.4;
this name goes in the next release)."""

import sys
import warnings

from .synthetic import echo as _moved

warnings.warn("spheroseg.echo moved to spheroseg.synthetic.echo; the old name goes in the next release",
              DeprecationWarning, stacklevel=2)
sys.modules[__name__] = _moved
