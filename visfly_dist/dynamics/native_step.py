"""The native forward of a CTBR control step (``dynamics/native/libvisfly_dynamics.so``).

Built by ``setup.sh`` (``make -C visfly_dist/dynamics/native``; needs g++). It computes what
:meth:`~visfly_dist.dynamics.adjoint.CtbrStep.forward` does, for steps without gradients, in plain
loops over blocks of agents instead of ~500 NumPy ops a control step (whose dispatch is the cost at
hundreds of agents). It covers every configuration ``CtbrStep`` does: RK4 or Euler, motor lag on
or off, ground on or off, no wind, one wind or a wind per agent; float32 and float64, computed in
that dtype. Without the library, or with ``VISFLY_NATIVE_DYNAMICS=0``, ``Quadrotor`` runs the NumPy
forward: same results up to rounding, slower.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import numpy as np
import torch

from visfly_dist.dynamics.adjoint import CtbrStep
from visfly_dist.dynamics.model import ROWS
from visfly_dist.native import declare, load_native

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_dynamics.so"
LIBRARY_VERSION = 1
DISABLE_ENV = "VISFLY_NATIVE_DYNAMICS"
_WIDTHS = (*ROWS, 4)                 # pos, vel, quat, omega, rotor, action
_TERM = np.dtype([("row", np.int32), ("a", np.int32), ("b", np.int32)])


class _Params(ctypes.Structure):
    """``Params`` of ``ctbr_step.cpp``."""

    _fields_ = [(name, ctypes.c_int64) for name in
                ("substeps", "rk4", "ground", "motor_lag", "n_terms", "n_loop_terms", "wind_stride")] + \
               [(name, ctypes.c_void_p) for name in
                ("terms", "term_values", "loop_terms", "loop_values", "constants", "wind")]


@functools.lru_cache(maxsize=1)
def load_dynamics() -> tuple[ctypes.CDLL | None, str]:
    """The loaded library, or ``None`` and the reason it is not used."""
    return load_native(LIBRARY_PATH, "vf_dynamics_version", LIBRARY_VERSION, DISABLE_ENV, "g++", _declare)


def _declare(lib: ctypes.CDLL) -> None:
    declare(lib, ("vf_ctbr_step_f32", "vf_ctbr_step_f64"), None,
            [ctypes.POINTER(_Params), ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64])


def _terms(entries: list[tuple[int, int, int, float]], dtype: np.dtype) -> tuple[np.ndarray, np.ndarray]:
    """Nonzero terms ``value * u[a] * u[b]`` (a <= b, equal ones merged) as index and value arrays."""
    merged: dict[tuple[int, int, int], float] = {}
    for row, a, b, value in entries:
        if value != 0.0:
            key = (row, min(a, b), max(a, b))
            merged[key] = merged.get(key, 0.0) + value
    keys = sorted(k for k, v in merged.items() if v != 0.0)
    return np.array(keys, dtype=np.int32).reshape(-1, 3).view(_TERM).ravel(), \
        np.array([merged[k] for k in keys], dtype=dtype)


def _feature_entries(matrix: np.ndarray, linear: int, square_at: int, squares: int, pair_at: int,
                     pair_size: int) -> list[tuple[int, int, int, float]]:
    """``(row, a, b, value)`` of ``matrix @ features`` with features ``[u[1:1+linear]; u[square_at:]**2
    (squares of them); u[pair_at:] outer u[pair_at:] (pair_size^2)]``, as terms ``value * u[a] * u[b]``."""
    entries = []
    for row, col in zip(*np.nonzero(matrix)):
        if col < linear:
            a, b = 0, 1 + col
        elif col < linear + squares:
            a = b = square_at + col - linear
        else:
            i, j = divmod(col - linear - squares, pair_size)
            a, b = pair_at + i, pair_at + j
        entries.append((int(row), int(a), int(b), float(matrix[row, col])))
    return entries


def _model_terms(step: CtbrStep) -> tuple[np.ndarray, np.ndarray]:
    """The model ``matrix @ [r; r^2; x outer x] + bias`` over ``u = [1, rotor (4), quat (4), omega (3)]``."""
    entries = _feature_entries(step.matrix, linear=4, square_at=1, squares=4, pair_at=5, pair_size=7)
    entries += [(row, 0, 0, float(v)) for row, v in enumerate(step.bias[:, 0])]
    return _terms(entries, step.matrix.dtype)


def _loop_terms(step: CtbrStep) -> tuple[np.ndarray, np.ndarray]:
    """The inner loop ``loop @ [omega; r; r^2; omega outer omega]`` over ``u = [1, omega (3), rotor (4)]``."""
    entries = _feature_entries(step.loop, linear=7, square_at=4, squares=4, pair_at=1, pair_size=3)
    return _terms(entries, step.loop.dtype)


class NativeCtbrStep:
    """:meth:`CtbrStep.forward` of ``step`` in the native library, on batch-first CPU tensors.

    Args:
        step: the NumPy step whose constants it takes (copied once).
        lib: the library from :func:`load_dynamics`.
    """

    def __init__(self, step: CtbrStep, lib: ctypes.CDLL) -> None:
        dtype = step.matrix.dtype
        self.dtype = torch.float64 if dtype == np.float64 else torch.float32
        self._fn = lib.vf_ctbr_step_f64 if dtype == np.float64 else lib.vf_ctbr_step_f32
        h = step.h
        self._terms, self._values = _model_terms(step)
        self._loop_terms, self._loop_values = _loop_terms(step)
        self._constants = np.concatenate([
            step.loop_bias.ravel(), step.setpoint_matrix.ravel(), step.action_scale.ravel(),
            step.drag_linear.ravel(), step.drag_quadratic.ravel(), step.gravity.ravel(),
            np.array([h, h / 2, h / 6, step.inv_motor_tau, step.half_b, step.half_b * step.half_b,
                      step.low, step.high]),
        ]).astype(dtype)
        # None: any number of agents; else the one number a per-agent wind was given for.
        self.agents: int | None = None
        self._wind = None
        if step.wind is not None:
            self._wind = np.ascontiguousarray(step.wind.T, dtype=dtype)
            if self._wind.shape[0] > 1:
                self.agents = self._wind.shape[0]
        wind_stride = 3 if self.agents is not None else 0
        self._params = _Params(
            step.substeps, step.rk4, step.ground, step.motor_lag, len(self._terms), len(self._loop_terms),
            wind_stride, self._terms.ctypes.data, self._values.ctypes.data, self._loop_terms.ctypes.data,
            self._loop_values.ctypes.data, self._constants.ctypes.data,
            None if self._wind is None else self._wind.ctypes.data)
        self._params_ref = ctypes.byref(self._params)

    def __call__(self, pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
                 rotor: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, ...] | None:
        """The next ``(pos, vel, quat, omega, rotor, contact)`` (new contiguous tensors, contact
        bool), or ``None`` for inputs it does not take (another dtype or device, shapes that are not
        ``(N, width)``, or an N other than a per-agent wind's): the caller runs NumPy."""
        n = pos.shape[0]
        if self.agents is not None and n != self.agents:
            return None
        ptrs, strides, outputs = (ctypes.c_void_p * 6)(), (ctypes.c_int64 * 6)(), (ctypes.c_void_p * 5)()
        held = []                                   # contiguous copies, alive until the call returns
        for i, (x, width) in enumerate(zip((pos, vel, quat, omega, rotor, action), _WIDTHS)):
            if x.dtype != self.dtype or not x.is_cpu or x.shape != (n, width):
                return None
            if x.stride(1) != 1:
                x = x.contiguous()
                held.append(x)
            ptrs[i], strides[i] = x.data_ptr(), x.stride(0)
        out = tuple(torch.empty((n, width), dtype=self.dtype) for width in ROWS)
        for i, x in enumerate(out):
            outputs[i] = x.data_ptr()
        contact = torch.empty(n, dtype=torch.bool)
        self._fn(self._params_ref, ptrs, strides, outputs, contact.data_ptr(), n)
        return (*out, contact)
