"""A data term written outside the package, through the documented protocol
(:class:`spheroseg.descent.dataterms.DataTerm`: its parameters, its
``offsets`` and a pure ``statistics``), run on both backends."""

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

    calls = 0  # a spy of the tests, not the term's: how often the iteration asked

    def __init__(self, *, width: float = 6.0, samples: int = 3):
        self.width, self.samples = float(width), int(samples)

    @property
    def offsets(self):  # its own samples: ``samples`` a side, over ``width`` mm inside and outside the surface
        side = np.linspace(self.width / self.samples, self.width, self.samples)
        return np.concatenate([-side[::-1], side])

    def statistics(self, u, along):
        Rayleigh.calls += 1
        inner, outer = along[:, :self.samples], along[:, self.samples:]
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
    force = Rayleigh().statistics(np.zeros(1), u)
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
    term = Rayleigh(width=6.0, samples=3)
    result = spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=term, backend=backend)
    assert Rayleigh.calls == result.iterations > 0  # every iteration asked the term
    assert dice(result.mask(phantom.volume), phantom.truth_mask) > 0.85
    assert result.parameters["mode"] == f"{__name__}.Rayleigh"
    assert result.parameters["mode_parameters"] == {"width": 6.0, "samples": 3}
    assert vars(term) == {"width": 6.0, "samples": 3}  # rule 1: the run changed none of it


def test_its_parameters_are_its_own_samples(phantom):
    """Rule 2: the iteration samples the term's own offsets, whatever its
    parameters make them (here 2 a side over 4 mm)."""
    seen = []

    class Recording(Rayleigh):
        def statistics(self, u, along):
            seen.append(along.shape[1])
            return super().statistics(u, along)

    spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Recording(width=4.0, samples=2),
                      max_iterations=3)
    assert seen and set(seen) == {4}
    np.testing.assert_array_equal(Recording(width=4.0, samples=2).offsets, [-4.0, -2.0, 2.0, 4.0])


def test_a_term_class_still_runs_with_a_warning(phantom):
    with pytest.warns(DeprecationWarning, match=r"pass Rayleigh\(\), not the class"):
        result = spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Rayleigh, max_iterations=3)
    assert result.parameters["mode"] == f"{__name__}.Rayleigh"


def test_both_backends_agree(phantom):
    if not compiled_available():
        pytest.skip("the compiled kernels are not built")
    results = [spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Rayleigh(), backend=b)
               for b in ("numpy", "compiled")]
    assert results[0].iterations == results[1].iterations
    np.testing.assert_allclose(results[0].surface.coefficients, results[1].surface.coefficients, atol=1e-6)


def test_a_term_without_statistics_is_refused_clearly(phantom):
    class Nothing(DataTerm):
        pass

    with pytest.raises(NotImplementedError, match="Nothing defines neither"):
        spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=Nothing())
    with pytest.raises(ValueError, match="DataTerm object"):
        spheroseg.segment(phantom.volume, phantom.apex, phantom.base, mode=object)
