"""The descent of one surface on one image: :mod:`.dataterms` (the
protocol of a data term and the built-in ones) with :mod:`.speckle` (the
physics of log-compressed speckle they read), :mod:`.backends` (where the
image is sampled: compiled or numpy), :mod:`.descent` (one level's
iteration), :mod:`.stepper` (the coarse-to-fine schedule, stepped),
:mod:`.options` (the options, validated), :mod:`.results` (what a run
returns) and :mod:`.quality` (how far a result can be trusted).
"""


def __getattr__(name: str):
    # 0.1's module ``spheroseg.descent`` is this folder's ``descent`` now
    from . import descent as iteration
    from .._moved import warn_moved

    if name in iteration.__all__:
        warn_moved(f"spheroseg.descent.{name}", f"spheroseg.descent.descent.{name}")
        value = globals()[name] = getattr(iteration, name)  # warned once
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
