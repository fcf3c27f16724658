"""The shape's mathematics: prolate spheroidal (and spherical, cylindrical)
coordinates and their pose, bicubic Hermite interpolation, the sparse
discretisation of the surface's quadrature, and the paper's energy terms.
Pure numpy and scipy: nothing here knows of images, files or kernels.
"""
