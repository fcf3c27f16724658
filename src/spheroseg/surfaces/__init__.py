"""The left ventricle's surface on an image: :mod:`.surface` (the Hermite
surface posed in the world, its mesh, volume and mask), :mod:`.fit` (a
surface fitted to points, the annulus of a mesh), :mod:`.myocardium` (the
wall between two surfaces: volume, mass, the 17 segments) and
:mod:`.metrics` (Dice and surface distances against a truth).
"""
