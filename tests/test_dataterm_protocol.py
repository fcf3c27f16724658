"""A data term written outside the package, through the documented protocol
(:class:`spheroseg.dataterms.DataTerm`: ``offsets`` and a pure
``statistics``), run on both backends."""

import numpy as np
import pytest

import spheroseg
from spheroseg.descent.backends import compiled_available
from spheroseg.descent.dataterms import DataTerm, Force
from spheroseg.surfaces.metrics import dice
from spheroseg.synthetic.phantom import make_phantom


class Rayleigh(DataTerm):
    """Rayleigh likelihoods of the amplitude in each band (Sarti et al. 2005):
    ``p(u) = u / s^2 exp(-u^2 / 2 s^2)``, ``s^2`` the maximum-likelihood
    ``mean(u^2) / 2`` of the samples inside and outside.  The two
    likelihoods cross at ``u^2 = 2 a b ln(b / a) / (b - a)`` (``a``, ``b``
    the two ``s^2``): the force compares ``u^2`` with that level."""

    offsets = np.array([-6.0, -4.0, -2.0, 2.0, 4.0, 6.0])
    calls = 0

    def statistics(self, u, along):
        type(self).calls += 1
        inner, outer = along[:, :3], along[:, 3:]
        a, b = np.nanmean(inner**2) / 2, np.nanmean(outer**2) / 2
        mid = 2 * a * b * np.log(b / a) / (b - a)
        half = b - a
        return Force(u**2, mid - half, mid + half, (2 * half) ** 2)


@pytest.fixture(scope="module")
def phantom():
    return make_phantom(seed=21, spacing=1.5)


def test_the_likelihoods_cross_where_the_statistics_say():
    # independent: the two Rayleigh densities evaluated at the level found
    a, b = 3.0, 11.0
    u = np.array([[np.sqrt(2 * a)] * 3 + [np.sqrt(2 * b)] * 3])  # E[u^2] = 2 s^2 on each side
    force = Rayleigh(np.arange(10.0)).statistics(np.zeros(1), u)
    level = (force.c_in + force.c_out) / 2

    def density(w, s2):  # in u^2 = w
        return np.exp(-w / (2 * s2)) / s2

    assert density(level, a) == pytest.approx(density(level, b), rel=1e-12)
    assert force.c_in < level < force.c_out


@pytest.mark.parametrize("backend", ["numpy", "compiled"])
def test_a_term_of_ones_own_segments_the_phantom(phantom, backend):
    if backend == "compiled" and not compiled_available():
        pytest.skip("the compiled kernels are not built")
    Rayleigh.calls = 0
    result = spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Rayleigh, backend=backend)
    assert Rayleigh.calls == result.iterations > 0  # every iteration asked the term
    assert dice(result.mask(phantom.volume), phantom.truth_mask) > 0.85
    assert result.parameters["mode"] == f"{__name__}.Rayleigh"


def test_both_backends_agree(phantom):
    if not compiled_available():
        pytest.skip("the compiled kernels are not built")
    results = [spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Rayleigh, backend=b)
               for b in ("numpy", "compiled")]
    assert results[0].iterations == results[1].iterations
    np.testing.assert_allclose(results[0].surface.coefficients, results[1].surface.coefficients, atol=1e-6)


def test_a_term_without_statistics_is_refused_clearly(phantom):
    class Nothing(DataTerm):
        pass

    with pytest.raises(NotImplementedError, match="Nothing defines neither"):
        spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Nothing)
    with pytest.raises(ValueError, match="DataTerm subclass"):
        spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=object)
