# The Hermite coefficients' layout and the prolate spheroidal map, written
# once for the compiled kernels (_kernels, _raster); their Python
# definitions are spheroseg.geometry.hermite (HermiteGrid's node layout)
# and spheroseg.geometry.coords (ProlateSpheroidal.to_cartesian).


cdef inline Py_ssize_t node_offset(Py_ssize_t n1, Py_ssize_t i1, Py_ssize_t i2, int a1, int a2, int e1,
                                   int e2) noexcept nogil:
    """The offset, in coefficients ``(n2 + 1, n1, 4)`` in C order, of node
    ``(i1 + a1, i2 + a2)`` (``theta`` periodic: node ``n1`` is node 0) and
    its value (``e1 = e2 = 0``) or derivative ``e1 + 2 e2``."""
    cdef Py_ssize_t node1 = i1 + a1 if i1 + a1 < n1 else 0
    return ((i2 + a2) * n1 + node1) * 4 + e1 + 2 * e2


cdef inline (double, double, double) prolate_point(double d, double ch, double sh, double ct, double st, double cm,
                                                   double sm) noexcept nogil:
    """The local point of prolate spheroidal coordinates of focal length
    ``d``: ``lambda`` by its ``cosh``, ``sinh`` (``ch``, ``sh``), ``theta``
    and ``mu`` by their cosines and sines: ``(d cosh(l) cos(mu), rho cos(theta),
    rho sin(theta))``, ``rho = d sinh(l) sin(mu)``."""
    cdef double rho = d * sh * sm
    return d * ch * cm, rho * ct, rho * st
