"""The options of a segmentation, validated once.

:class:`SegmentOptions` is what :func:`spheroseg.segment`,
:func:`spheroseg.track` and :class:`spheroseg.Tracker` take as keywords; a
result records it as ``parameters`` (:meth:`SegmentOptions.as_parameters`).
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING

import numpy as np

from .._moved import MOVED_IN, REMOVED_IN
from ..surfaces.surface import DEFAULT_RADIUS_RATIO

if TYPE_CHECKING:  # the data terms (and SciPy's optimize) load when a term is asked for: not for --help
    from .dataterms import DataTerm

__all__ = ["SegmentOptions", "MODES", "SYSTEMS", "BACKENDS", "LIMITS", "format_point"]

#: data terms (see :mod:`spheroseg.dataterms`)
MODES = ("intensity", "local", "chan-vese", "fast")
#: coordinate systems of the surface (see :mod:`spheroseg.coords`)
SYSTEMS = ("prolate", "spherical", "cylindrical")
#: array backends (see :mod:`spheroseg.backends`)
BACKENDS = ("auto", "compiled", "numpy")
#: what the finest level's smoothing measures the departure from
SMOOTHNESS_REFERENCES = ("start", "fitted")
#: upper bounds of the options that size memory or time: patches per
#: direction and sample points per patch and direction (32 x 32 patches of
#: 8 x 8 points hold 1.2 GB during a descent, and memory grows with the
#: number of points), band widths and step (mm: a ventricle's radius is some 25 mm;
#: a wider band or a longer step measures or moves past the heart)
#: and iterations per level
LIMITS = {"patches": 32, "order": 16, "sample_points": 32 * 32 * 8 * 8, "band": 50.0, "band_out": 50.0,
          "step": 10.0, "max_iterations": 10000, "smoothness": 1e6}


def _data_terms():
    from . import dataterms

    return dataterms


def format_point(point) -> str:
    """``(x, y, z)`` with two decimals (three significant digits beyond a
    million), for messages."""
    return "(" + ", ".join(f"{float(v):.2f}" if abs(float(v)) < 1e6 else f"{float(v):.3g}"
                           for v in np.ravel(point)) + ")"


@dataclass(frozen=True)
class SegmentOptions:
    """Options of a segmentation (all keyword arguments of :func:`spheroseg.segment`).

    Parameters
    ----------
    system : {"prolate", "spherical", "cylindrical"}
        Coordinate system of the surface (paper eq. 2).
    patches : (int, int)
        Hermite patches around (theta) and along (apex to base) the cavity;
        the paper's 8 x 8 by default.
    mode : {"intensity", "local", "chan-vese", "fast"} or DataTerm
        Data term (:mod:`spheroseg.descent.dataterms`); "intensity", the
        default, runs the local means and then moves the wall to the
        intensity interface.  A :class:`~spheroseg.descent.dataterms.DataTerm`
        object, a built-in one with parameters (``LocalMeans(polarity=-1.0)``)
        or one's own (its ``offsets`` and ``statistics``), runs at every
        level (the local means' coarse levels excepted).
    step : float
        Largest normal displacement of the surface per iteration, mm.  The
        default 1 mm is about 4 % of a ventricle's radius: the paper's
        ``dt = 0.04``.  The intensity mode's last stage, which starts at the
        wall, takes twice it when the local means settled
        (:class:`spheroseg.dataterms.IntensityInterface`).
    adaptive_step : bool
        Halve the step whenever the surface moves back against its last
        motion (it oscillates about the wall instead of settling).
    max_iterations : int
        Cap on iterations at each level of the coarse-to-fine schedule.
    tol : float
        A level stops when the RMS motion of the surface in an iteration
        falls below ``tol`` mm.
    coarse_tol : float, optional
        The same for the coarser levels of ``coarse_to_fine`` (default
        twice ``tol``): a coarse level only brings the surface near the wall
        for the next one, which moves it on from there (on the
        image-formation sweep: 12 % fewer iterations, the same accuracy).
    coarse_to_fine : bool
        Start on a quarter and then half of the patches (exact refinement).
    band, band_out : float
        Widths (mm) of the bands of the local means and of the outer shell
        of the global means.
    interface : float, optional
        Grey level of the interface for ``mode="fast"`` (default: Otsu's
        threshold of the samples around the initial surface).
    nu : float
        Weight of the area term (paper eqs. 16-17, 23-24), 0 as in the paper:
        a normal speed of ``nu`` times the mean curvature times the typical
        radius, in steps (1 moves a sphere inwards by a step).
    smoothness : float
        Weight of a thin-plate regularisation of the surface's departure
        from a reference shape (``smoothness_reference``), applied as an
        implicit step each iteration (0 for the paper's method); 1 halves a
        wave of the patch size at 8 x 8 patches per step.
    smoothness_reference : {"start", "fitted"}
        The shape that departure is measured from on the finest patches:
        ``"start"``, the initial half-ellipsoid, as on the coarse levels;
        ``"fitted"``, that half-ellipsoid widened or narrowed to hold the
        volume the coarse levels ended on (the same apex and base plane;
        :func:`spheroseg.initial.fitted_start`).  The start pulls a small
        cavity out towards the clicked shape (end-systolic phantoms
        segmented from their own clicks 7-13 % large, against 1-7 % from
        the fitted shape); the fitted shape fits every phantom of the
        image-formation sweep closer (Dice and mean surface distance) but
        leaves the volumes 1-2 % lower, and follows the coarse levels' own
        error where a wide blur misleads them (an image whose speckle hides
        its walls' blur: down to -15 %; docs/benchmarks.md).  A frame
        of a sequence is smoothed from the previous frame's surface, a
        given ``init`` from itself.
    landmark_weight : float
        How strongly the landmarks hold the surface (1: a landmark
        outweighs the data over 5 % of the surface, about a patch at 4 x 4).
    apex_weight : float
        The apex point is a landmark of this weight (0: free apex).  The
        default 10 holds the clicked apex against near-field clutter, which
        fills the apical cavity with haze and pulled the surface tens of mm
        towards the base at weight 1.
    order : int
        Sample points per patch and direction (paper: 8).
    radius_ratio : float
        Base radius of the initial half-ellipsoid over the apex-base distance.
    backend : {"auto", "compiled", "numpy"}
        The iteration's array work (:mod:`spheroseg.backends`): ``"auto"``
        runs it in the compiled kernels where the package was built and
        the system is prolate spheroidal, ``"numpy"`` runs the reference.
    threads : int, optional
        Threads of the compiled kernels during the descent (their OpenMP
        loops' count, restored afterwards): each splits its sample points
        among them.  None takes the default (the cores this process may
        run on, or :func:`spheroseg._compiled._runtime.set_default_threads`'s),
        reduced at the start of each segmentation and frame to the cores no
        other process is using (:func:`spheroseg.backends.idle_cores`, read
        at most ten times a second): a thread that shares a core with other
        work slows every parallel step to its pace.  The result is the same to
        the last bit whatever the count.
    """

    system: str = "prolate"
    patches: tuple[int, int] = (8, 8)
    mode: str | DataTerm = "intensity"
    step: float = 1.0
    adaptive_step: bool = True
    max_iterations: int = 60
    tol: float = 0.05
    coarse_tol: float | None = None
    coarse_to_fine: bool = True
    band: float = 8.0
    band_out: float = 15.0
    interface: float | None = None
    nu: float = 0.0
    smoothness: float = 1.0
    smoothness_reference: str = "start"
    landmark_weight: float = 1.0
    apex_weight: float = 10.0
    order: int = 8
    radius_ratio: float = DEFAULT_RADIUS_RATIO
    backend: str = "auto"
    threads: int | None = None

    def __post_init__(self):
        system = getattr(self.system, "name", self.system)  # a CoordinateSystem instance names itself
        if system not in SYSTEMS:
            raise ValueError(f"system must be one of {SYSTEMS}, got {self.system!r}")
        object.__setattr__(self, "system", system)
        terms = _data_terms()
        if isinstance(self.mode, type) and issubclass(self.mode, terms.DataTerm):  # 0.1 took the class
            warnings.warn(f"mode takes a DataTerm object since spheroseg {MOVED_IN}: pass {self.mode.__name__}(), "
                          f"not the class (which it takes until {REMOVED_IN})", DeprecationWarning, stacklevel=4)
            object.__setattr__(self, "mode", self.mode())
        if not (self.mode in MODES if isinstance(self.mode, str) else isinstance(self.mode, terms.DataTerm)):
            raise ValueError(f"mode must be one of {MODES} or a spheroseg.descent.dataterms.DataTerm object, "
                             f"got {self.mode!r}")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")
        try:
            patches = tuple(int(n) for n in self.patches)
        except (TypeError, ValueError):
            patches = ()
        if len(patches) != 2 or min(patches) < 2 or patches != tuple(self.patches):
            raise ValueError(f"patches must be two integers >= 2 (around, along), got {self.patches!r}")
        if max(patches) > LIMITS["patches"]:
            raise ValueError(f"patches must be at most {LIMITS['patches']} in each direction, got {self.patches!r}")
        object.__setattr__(self, "patches", patches)
        for name in ("step", "tol", "band", "band_out"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")
        for name in ("step", "band", "band_out"):
            if getattr(self, name) > LIMITS[name]:
                raise ValueError(f"{name} must be at most {LIMITS[name]:g} mm, got {getattr(self, name):.3g}")
        if self.coarse_tol is not None and not (isinstance(self.coarse_tol, (int, float, np.number))
                                                and np.isfinite(self.coarse_tol) and self.coarse_tol > 0):
            raise ValueError(f"coarse_tol must be a positive number (or None: twice tol), got {self.coarse_tol!r}")
        # a level stops when the RMS motion of an iteration is below its
        # tolerance, and no iteration moves the wall more than the step: a
        # step at or below the tolerance stops every level at its first
        # iteration, returning the start as "converged"
        stops = max(self.tol, (self.coarse_tol or 2 * self.tol) if self.coarse_to_fine else 0.0)
        if not self.step > stops:
            which = "tol" if stops == self.tol else "the coarse levels' tolerance (coarse_tol, default 2 x tol)"
            raise ValueError(f"step must be more than {which}, {stops:g} mm, got {self.step:g}: no iteration could "
                             "move the wall by more than the motion that counts as settled (a smaller step needs a "
                             "smaller tol)")
        if not isinstance(self.adaptive_step, (bool, np.bool_)):
            raise ValueError(f"adaptive_step must be True or False, got {self.adaptive_step!r}")
        for name in ("max_iterations", "order"):
            value = getattr(self, name)
            if not (isinstance(value, (int, np.integer)) and not isinstance(value, bool)):
                raise ValueError(f"{name} must be an integer, got {value!r}")  # its range below
        if self.threads is not None and not (isinstance(self.threads, (int, np.integer))
                                             and not isinstance(self.threads, bool) and self.threads >= 1):
            raise ValueError(f"threads must be a positive integer (or None: the default), got {self.threads!r}")
        if self.threads is not None:
            object.__setattr__(self, "threads", int(self.threads))  # JSON-ready
        if self.max_iterations < 1 or self.max_iterations > LIMITS["max_iterations"]:
            raise ValueError(f"max_iterations must be from 1 to {LIMITS['max_iterations']}, got {self.max_iterations!r}")
        if self.order < 3 or self.order > LIMITS["order"]:  # 1 or 2 points leave the Hermite coefficients undetermined
            raise ValueError(f"order must be from 3 to {LIMITS['order']} sample points per patch and direction, "
                             f"got {self.order!r}")
        points = patches[0] * patches[1] * self.order ** 2
        if points > LIMITS["sample_points"]:
            raise ValueError(f"patches {patches[0]} x {patches[1]} at order {self.order} make {points} sample points; "
                             f"at most {LIMITS['sample_points']} (32 x 32 patches at order 8)")
        for name in ("nu", "smoothness", "landmark_weight", "apex_weight"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float, np.number)) and np.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a number >= 0, got {value!r}")
        if self.smoothness > LIMITS["smoothness"]:  # far past rigid: the implicit step's matrix overflows
            raise ValueError(f"smoothness must be at most {LIMITS['smoothness']:g} (already the start's shape held "
                             f"rigid), got {self.smoothness:g}")
        if self.smoothness_reference not in SMOOTHNESS_REFERENCES:
            raise ValueError(f"smoothness_reference must be one of {SMOOTHNESS_REFERENCES}, "
                             f"got {self.smoothness_reference!r}")
        if not 0 < self.radius_ratio < 1:
            raise ValueError(f"radius_ratio must be in (0, 1), got {self.radius_ratio!r}")
        if self.interface is not None and not np.isfinite(self.interface):
            raise ValueError(f"interface must be a finite grey level, got {self.interface!r}")

    @classmethod
    def names(cls) -> tuple[str, ...]:
        """The option names, in order."""
        return tuple(f.name for f in fields(cls))

    @property
    def data_term(self) -> DataTerm:
        """The data term ``mode`` names (the fast mode's with the
        ``interface`` option), or is."""
        if not isinstance(self.mode, str):
            return self.mode
        terms = _data_terms()
        if self.mode == "fast":
            return terms.FixedInterface(interface=self.interface)
        return terms.DATA_TERMS[self.mode]()

    def as_parameters(self) -> dict:
        """The options as plain JSON-ready values (what results record)."""
        out = {name: getattr(self, name) for name in self.names()}  # all scalars: no deep copy
        out["patches"] = list(self.patches)
        if not isinstance(self.mode, str):  # a term object, by its class's name and its parameters
            term = type(self.mode)
            out["mode"] = f"{term.__module__}.{term.__qualname__}"
            if self.mode.parameters():
                out["mode_parameters"] = {k: (v.tolist() if isinstance(v, np.ndarray) else v)
                                          for k, v in self.mode.parameters().items()}
        return out

    def replace(self, **changes) -> "SegmentOptions":
        """A copy with some options changed (validated again)."""
        return SegmentOptions(**{**asdict(self), **changes})
