"""Images with their geometry: :mod:`.volume` (an ITK-style grid, trilinear
sampling at world points, the scanner's sector) and :mod:`.beamspace` (a
volume in beam space: depth and steering angles, and scan conversion).
"""
