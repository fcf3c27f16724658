"""The on-disk cache of the grid matrices: what is read equals what is
computed, and a bad file or directory costs only the computation."""

import numpy as np
import pytest
import scipy.sparse as sp

from spheroseg.geometry.array_cache import cache_directory, cached_arrays
from spheroseg.geometry.discretisation import discretise
from spheroseg.geometry.hermite import HermiteGrid

GRID = HermiteGrid(4, 3, (0.0, np.pi / 2))


@pytest.fixture
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("SPHEROSEG_CACHE_DIR", str(tmp_path))
    return cache_directory()


def fields(d):
    """Every array of a Discretisation (sparse ones dense), by name."""
    out = {}
    for name, value in vars(d).items():
        for k, v in enumerate(value if isinstance(value, tuple) else (value,)):
            if sp.issparse(v):
                v = v.toarray()
            if isinstance(v, np.ndarray):
                out[f"{name}{k}"] = v
    return out


def assert_same(a, b):
    fa, fb = fields(a), fields(b)
    assert fa.keys() == fb.keys() and len(fa) > 15
    for name in fa:
        assert fa[name].dtype == fb[name].dtype and np.array_equal(fa[name], fb[name]), name
        # the same memory layout too: the kernels take C-contiguous arrays
        assert fa[name].flags.c_contiguous and fb[name].flags.c_contiguous, name
    assert np.array_equal(a.system_inverse(0.5), b.system_inverse(0.5))


def test_matrices_read_back_equal_the_computed_ones(cache):
    computed = discretise.__wrapped__(GRID, 5)  # the lru_cache bypassed: a new process
    computed.system_inverse(0.5)
    assert len(list(cache.glob("*.npz"))) == 2  # the discretisation and one smoothing's inverse
    read = discretise.__wrapped__(GRID, 5)
    assert_same(computed, read)
    assert not read.mass.flags.writeable and not read.system_inverse(0.5).flags.writeable


def test_a_corrupted_file_is_computed_again(cache):
    computed = discretise.__wrapped__(GRID, 5)
    computed.system_inverse(0.5)
    for path in cache.glob("*.npz"):
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF  # one flipped byte: the zip's checksum fails
        path.write_bytes(bytes(data[: len(data) // 2 + 100]) if "inverse" in path.name else bytes(data))
    assert_same(computed, discretise.__wrapped__(GRID, 5))


def test_an_unwritable_directory_only_computes(tmp_path, monkeypatch):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    monkeypatch.setenv("SPHEROSEG_CACHE_DIR", str(blocker))
    assert_same(discretise(GRID, 5), discretise.__wrapped__(GRID, 5))
    assert blocker.read_text() == "not a directory"


def test_computed_once_per_key_and_source(cache, tmp_path):
    calls = []

    def compute():
        calls.append(1)
        return {"x": np.arange(3.0)}

    source = tmp_path / "source.py"
    source.write_text("a = 1\n")
    for _ in range(2):
        assert cached_arrays("t", (1,), compute, sources=[source])["x"].tolist() == [0.0, 1.0, 2.0]
    assert len(calls) == 1
    cached_arrays("t", (2,), compute, sources=[source])  # another key
    source.write_text("a = 22\n")  # an edited source
    cached_arrays("t", (1,), compute, sources=[source])
    assert len(calls) == 3
    assert not list(cache.glob("*.tmp"))  # no temporary file left behind
