"""The one loader of the optional native libraries: every reason it gives for not using one."""

from __future__ import annotations

import ctypes
from pathlib import Path

import pytest

from visfly_dist.native import load_native
from visfly_dist.training import native_kernels

ENV = "VISFLY_TEST_NATIVE"


def _declare(lib: ctypes.CDLL) -> None:
    lib.vf_phase_max_forward.restype = None


def _load(path: Path, version: int = native_kernels.LIBRARY_VERSION) -> tuple[ctypes.CDLL | None, str]:
    return load_native(path, "vf_kernels_version", version, ENV, "g++", _declare)


built = pytest.mark.skipif(not native_kernels.LIBRARY_PATH.exists(), reason="training kernels not built")


@built
def test_a_built_library_of_the_expected_version_loads() -> None:
    lib, reason = _load(native_kernels.LIBRARY_PATH)
    assert lib is not None and reason == "loaded" and lib.vf_phase_max_forward.restype is None


@built
def test_another_version_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    lib, reason = _load(native_kernels.LIBRARY_PATH, version=native_kernels.LIBRARY_VERSION + 1)
    assert lib is None and "expected" in reason and "rebuild it" in reason
    monkeypatch.setenv(ENV, "0")
    assert _load(native_kernels.LIBRARY_PATH) == (None, f"disabled by {ENV}=0")


def test_missing_and_broken_libraries_say_why(tmp_path: Path) -> None:
    missing = tmp_path / "libmissing.so"
    lib, reason = _load(missing)
    assert lib is None and "not built" in reason and str(missing) in reason and "needs g++" in reason
    missing.write_bytes(b"not a shared object")
    lib, reason = _load(missing)
    assert lib is None and "failed to load" in reason
