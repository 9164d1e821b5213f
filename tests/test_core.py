"""Package-level contract: version, threads, build info, error hierarchy."""

import pytest

import kinema as km


def test_version_and_build_info():
    assert km.__version__ == "0.1.0"
    info = km.build_info()
    for key in ("compiler", "flags", "openmp", "eigen", "cholmod", "blas"):
        assert info[key], key
    assert info["eigen"].startswith("3.4")


def test_blas_is_optimised():
    # CHOLMOD's supernodal factorisation spends its time in BLAS: it must be OpenBLAS, not
    # Debian's reference BLAS (3x slower on the 2D 1024^2 Laplacian).
    info = km.build_info()
    assert "openblas" in info["blas"].lower() or info["blas_config"].startswith("OpenBLAS"), info


def test_threads_roundtrip():
    n = km.get_num_threads()
    try:
        km.set_num_threads(1)
        assert km.get_num_threads() == 1
    finally:
        km.set_num_threads(n)
    assert km.get_num_threads() == n


@pytest.mark.parametrize("bad", [0, -3, 1.5, "2", True])
def test_threads_reject_bad(bad):
    with pytest.raises(ValueError, match="n:"):
        km.set_num_threads(bad)


def test_error_hierarchy():
    assert issubclass(km.KinemaError, RuntimeError)
    for cls in (km.DivergenceError, km.ConvergenceError, km.StabilityError, km.NotPositiveDefiniteError):
        assert issubclass(cls, km.KinemaError)
    assert issubclass(km.StabilityError, ValueError)
    assert issubclass(km.NotPositiveDefiniteError, ValueError)
    assert not issubclass(km.ConvergenceError, ValueError)
