"""The navigation task's per-step terms in one native call each (``tasks/native/libvisfly_tasks.so``).

Built by ``setup.sh`` (``make -C visfly_dist/tasks/native``; needs g++). It computes the goal
geometry and the ``ours`` reward of :mod:`visfly_dist.tasks.navigation` for steps without gradients,
in plain float32 loops instead of dozens of small torch operations a step (whose dispatch is the
cost at hundreds of agents). Without the library, or with ``VISFLY_NATIVE_TASKS=0``, or for inputs
it does not take (another dtype or device, gradients), the task runs its torch code: the same
geometry bit for bit, the same reward up to the float32 rounding of its weighted sum.
"""

from __future__ import annotations

import ctypes
import functools
from pathlib import Path

import torch

from visfly_dist.native import declare, load_native

LIBRARY_PATH = Path(__file__).parent / "native" / "libvisfly_tasks.so"
LIBRARY_VERSION = 1
DISABLE_ENV = "VISFLY_NATIVE_TASKS"
_GEOMETRY_WIDTHS = (3, 3, 4, 3, 3)       # pos, vel, quat, omega, goal
_REWARD_WIDTHS = (3, 3, 3) + (0,) * 8    # pos, vel, nearest; then (N,) columns (0: one dimension)


class _RewardParams(ctypes.Structure):
    """``RewardParams`` of ``nav_terms.cpp``."""

    _fields_ = [("seen_below", ctypes.c_float), ("near", ctypes.c_float), ("dt", ctypes.c_float),
                ("weights", ctypes.c_float * 8), ("fused", ctypes.c_int64)]


@functools.lru_cache(maxsize=1)
def load_tasks() -> tuple[ctypes.CDLL | None, str]:
    """The loaded library, or ``None`` and the reason it is not used."""
    return load_native(LIBRARY_PATH, "vf_tasks_version", LIBRARY_VERSION, DISABLE_ENV, "g++", _declare)


def _declare(lib: ctypes.CDLL) -> None:
    declare(lib, ("vf_nav_geometry_f32",), None,
            [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64])
    declare(lib, ("vf_nav_reward_f32",), None,
            [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64])


@functools.lru_cache(maxsize=1)
def _fused() -> bool:
    """torch's CPU norms fuse their multiply-adds: every vectorised capability does, DEFAULT does not."""
    return torch.backends.cpu.get_cpu_capability() != "DEFAULT"


def _pointers(tensors: tuple[torch.Tensor, ...], widths: tuple[int, ...],
              dtypes: tuple[torch.dtype, ...]) -> tuple[ctypes.Array, ctypes.Array, list[torch.Tensor]] | None:
    """Data pointers and row strides of ``tensors`` (``(N, width)`` with unit column stride, or
    ``(N,)`` for width 0, on the CPU, of ``dtypes``), the copies made to get there (to keep alive
    until the call returns), or ``None`` when one does not fit."""
    n = tensors[0].shape[0]
    ptrs, strides = (ctypes.c_void_p * len(tensors))(), (ctypes.c_int64 * len(tensors))()
    held = []
    for i, (x, width, dtype) in enumerate(zip(tensors, widths, dtypes)):
        if x.dtype != dtype or not x.is_cpu or x.shape != ((n, width) if width else (n,)):
            return None
        if width and x.stride(1) != 1:
            x = x.contiguous()
            held.append(x)
        ptrs[i], strides[i] = x.data_ptr(), x.stride(0)
    return ptrs, strides, held


def goal_geometry(pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
                  goal: torch.Tensor) -> tuple[torch.Tensor, ...] | None:
    """``(distance, target, heading, speed, spin)`` of ``navigation._GoalGeometry`` (new tensors,
    ``target`` ``(N, 4)``, the others ``(N,)``), or ``None`` where the library is not loaded or does
    not take the inputs (not float32 ``(N, width)`` CPU tensors): the caller runs torch.

    Gradients are not tracked: call it only where none are needed.
    """
    lib = load_tasks()[0]
    if lib is None:
        return None
    found = _pointers((pos, vel, quat, omega, goal), _GEOMETRY_WIDTHS, (torch.float32,) * 5)
    if found is None:
        return None
    ptrs, strides, _held = found
    n = pos.shape[0]
    terms, target = torch.empty(4, n, dtype=torch.float32), torch.empty(n, 4, dtype=torch.float32)
    lib.vf_nav_geometry_f32(ptrs, strides, terms.data_ptr(), target.data_ptr(), n, _fused())
    distance, heading, speed, spin = terms.unbind(0)
    return distance, target, heading, speed, spin


@functools.lru_cache(maxsize=16)
def _reward_params(search_radius: float, near: float, dt: float, weights: tuple[float, ...]) -> _RewardParams:
    """The constants as torch compares and combines them: Python numbers rounded to float32."""
    return _RewardParams(search_radius * 0.999, near, dt, (ctypes.c_float * 8)(*weights), _fused())


def ours_reward(pos: torch.Tensor, vel: torch.Tensor, nearest: torch.Tensor, obstacle_distance: torch.Tensor,
                prev_distance: torch.Tensor, distance: torch.Tensor, heading: torch.Tensor, speed: torch.Tensor,
                spin: torch.Tensor, success: torch.Tensor, failure: torch.Tensor, search_radius: float, near: float,
                dt: float, weights: tuple[float, ...]) -> torch.Tensor | None:
    """``(N,)`` navigation's ``ours`` reward: ``weights`` (8) times ``(speed, spin, proximity, progress,
    heading, approach, success, failure)`` summed, with proximity and approach those of
    :func:`~visfly_dist.tasks.common.obstacle_terms` and progress :func:`~visfly_dist.tasks.common.progress_speed`
    over ``dt``; or ``None`` as for :func:`goal_geometry`. ``success``/``failure`` are bool.
    """
    lib = load_tasks()[0]
    if lib is None:
        return None
    found = _pointers((pos, vel, nearest, obstacle_distance, prev_distance, distance, heading, speed, spin,
                       success, failure), _REWARD_WIDTHS, (torch.float32,) * 9 + (torch.bool,) * 2)
    if found is None:
        return None
    ptrs, strides, _held = found
    out = torch.empty(pos.shape[0], dtype=torch.float32)
    lib.vf_nav_reward_f32(ptrs, strides, ctypes.byref(_reward_params(search_radius, near, dt, weights)),
                          out.data_ptr(), pos.shape[0])
    return out
