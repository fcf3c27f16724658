"""The descent of one surface on one image: :mod:`.dataterms` (the
protocol of a data term and the built-in ones) with :mod:`.speckle` (the
physics of log-compressed speckle they read), :mod:`.backends` (where the
image is sampled: compiled or numpy), :mod:`.descent` (one level's
iteration), :mod:`.stepper` (the coarse-to-fine schedule, stepped),
:mod:`.options` (the options, validated), :mod:`.results` (what a run
returns) and :mod:`.quality` (how far a result can be trusted).
"""


def __getattr__(name: str):
    # 0.1's module ``spheroseg.descent`` is this folder's ``descent`` now: its
    # public names (not the submodules, which the import system looks up
    # here before it imports them) are read from it, with a warning
    import importlib

    from .._moved import warn_moved

    if not name.startswith("_") and name in ("Descent", "LevelRun"):
        value = globals()[name] = getattr(importlib.import_module(f"{__name__}.descent"), name)  # warned once
        warn_moved(f"spheroseg.descent.{name}", f"spheroseg.descent.descent.{name}")
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
