"""The memory budget: what one run may hold for the arrays its input
decides (the image's voxels, a scan conversion's grid), checked before they
are made.  ``SPHEROSEG_MAX_IMAGE_GB`` sets it (default 4 GB)."""

from __future__ import annotations

import math
import os

__all__ = ["BUDGET_VARIABLE", "DEFAULT_BUDGET_GB", "budget_bytes", "check_allocation"]

#: the environment variable that sets the budget, GB, and its default: a
#: 3D+t file of 60 frames of 250^3 float32 voxels is within it, a 1000^3
#: volume is not
BUDGET_VARIABLE = "SPHEROSEG_MAX_IMAGE_GB"
DEFAULT_BUDGET_GB = 4.0


def budget_bytes() -> float:
    """The budget in bytes (a bad setting is a one-line error)."""
    text = os.environ.get(BUDGET_VARIABLE, "")
    try:
        gb = float(text) if text.strip() else DEFAULT_BUDGET_GB
    except ValueError:
        gb = math.nan
    if not gb > 0 or not math.isfinite(gb):
        raise ValueError(f"{BUDGET_VARIABLE} must be a positive number of GB, got {text!r}")
    return gb * 1e9


def check_allocation(need: float, what: str) -> None:
    """Raise ``MemoryError`` with one line when ``need`` bytes (the peak of
    what ``what`` would make) exceed the budget, before anything is made."""
    budget = budget_bytes()
    if need > budget:
        raise MemoryError(f"{what} would hold {need / 1e9:.3g} GB at its peak, over the memory budget of "
                          f"{budget / 1e9:.3g} GB (set {BUDGET_VARIABLE} to raise it)")
