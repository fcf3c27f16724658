"""What a user runs: :mod:`.cli` (the ``spheroseg`` command), :mod:`.batch`
with :mod:`.manifest` and :mod:`.records` (cohorts), :mod:`.warmup` (the
kernels loaded ahead), :mod:`.report_worker` (reports drawn beside the
segmentation), :mod:`.viewer` (the local web viewer) and :mod:`.live`
(segmenting a scanner's OpenIGTLink stream).
"""
