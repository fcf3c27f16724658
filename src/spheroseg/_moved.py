"""The module paths of 0.1, kept for one release as aliases that warn.

0.2 put the modules into layer folders (``spheroseg.volume`` is now
``spheroseg.volumes.volume``).  Importing an old path imports the new module
under both names, with a :class:`DeprecationWarning` naming the new one; the
aliases go in :data:`REMOVED_IN`.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import types
import warnings

MOVED_IN = "0.2.0"
REMOVED_IN = "0.3.0"

_FOLDERS = {
    "geometry": ("coords", "hermite", "discretisation", "array_cache", "energy"),
    "_compiled": ("_runtime", "_kernels", "_raster", "raster"),
    "volumes": ("volume", "beamspace"),
    "surfaces": ("surface", "fit", "myocardium", "metrics"),
    "synthetic": ("phantom", "echo"),
    "descent": ("dataterms", "backends", "stepper", "options", "results", "quality"),
    "tracking": ("initial", "frames", "annulus", "tracker", "epicardium", "locate", "segment"),
    "io": ("images", "markups", "atomic", "surface_io", "outputs", "report"),
    "apps": ("cli", "warmup", "batch", "manifest", "records", "report_worker", "viewer"),
}
#: ``{old path: new path}`` below ``spheroseg.`` (``descent``, a module
#: before and a folder now, holds its module as ``descent.descent``: its
#: public name, ``Descent``, is importable from the folder)
MOVED = {name: f"{folder}.{name}" for folder, names in _FOLDERS.items() for name in names}


def new_path(name: str) -> str | None:
    """The new dotted path of an old one (``spheroseg.viewer.session`` ->
    ``spheroseg.apps.viewer.session``), or None when ``name`` did not move."""
    package, _, rest = name.partition(".")
    if package != "spheroseg":
        return None
    head, _, tail = rest.partition(".")
    if head not in MOVED:
        return None
    return f"spheroseg.{MOVED[head]}" + (f".{tail}" if tail else "")


def warn_moved(old: str, new: str, stacklevel: int = 2) -> None:
    warnings.warn(f"{old} moved to {new} in spheroseg {MOVED_IN}; the old path goes in {REMOVED_IN}",
                  DeprecationWarning, stacklevel=stacklevel + 1)


class MovedFinder(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old path as its new module (first on ``sys.meta_path``, so
    that ``spheroseg.viewer.session`` is not found a second time, as a new
    module, in the folder its parent now stands for)."""

    def find_spec(self, fullname, path=None, target=None):
        if new_path(fullname) is None:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec):
        return None  # a placeholder: exec_module puts the new module in its place

    def exec_module(self, module):
        new = new_path(module.__name__)
        warn_moved(module.__name__, new, stacklevel=2)
        # the import system takes what sys.modules holds under the old name
        # once this returns (the module is not run a second time)
        sys.modules[module.__name__] = importlib.import_module(new)


class Package(types.ModuleType):
    """The package's module type: an old path imported (``spheroseg.segment``,
    ``spheroseg.locate``) must not replace the public function of its name
    that the package binds, or will bind on first use (the names of its
    ``_PUBLIC``)."""

    def __setattr__(self, name, value):
        if isinstance(value, types.ModuleType) and (name in self.__dict__.get("_PUBLIC", ())
                                                    or callable(self.__dict__.get(name))):
            return
        super().__setattr__(name, value)


def install(package: types.ModuleType) -> None:
    """Serve the old paths below ``package`` (called once by its ``__init__``)."""
    if not any(isinstance(finder, MovedFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedFinder())
    package.__class__ = Package
