"""From an image, or a sequence, to the ventricle: :mod:`.locate` (finding
it without clicks), :mod:`.initial` (the first surface), :mod:`.tracker`
(frame by frame) with :mod:`.frames` (what decides a frame) and
:mod:`.annulus` (the mitral plane), :mod:`.epicardium` (the outer wall) and
:mod:`.segment` (the public ``segment`` and ``track``).
"""
