"""Backend selection and libLLVM discovery."""

import pytest

from glossrt import backend
from glossrt.errors import BackendError


def test_variant_is_selected():
    v = backend.ensure()
    assert v in (backend.CPU_VARIANT, backend.GPU_VARIANT)
    import mitsuba as mi

    assert mi.variant() == v


def test_unknown_device():
    with pytest.raises(BackendError, match="unknown device"):
        backend.use("tpu")


def test_gpu_without_cuda_is_a_clear_error():
    if backend._cuda_works():
        pytest.skip("a CUDA device is present")
    with pytest.raises(BackendError, match="no working CUDA device"):
        backend.use("gpu")
    assert backend.ensure() == backend.CPU_VARIANT  # still usable afterwards


def test_libllvm_version_parsing():
    assert backend._version_of("/usr/lib/x86_64-linux-gnu/libLLVM-19.so") == 19
    assert backend._version_of("/usr/lib/llvm-17/lib/libLLVM.so.1") == 17
    assert backend._version_of("/opt/lib/libLLVM.so.18.1") == 18


def test_libllvm_found_when_cpu():
    if backend.ensure() != backend.CPU_VARIANT:
        pytest.skip("GPU variant")
    lib = backend.find_libllvm()
    assert lib is not None and lib.version >= backend.MIN_LLVM


def test_info_fields():
    info = backend.info()
    for k in ("variant", "device", "mitsuba", "drjit", "libllvm"):
        assert info[k]
