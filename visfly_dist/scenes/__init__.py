"""Scenes: loading meshes and Habitat datasets, generating scenes, saving them, spawn sampling.

World frame z-up (ENU), metres. See docs/CONTRACTS.md for how the other parts use this API. The
names below are imported on first use, so ``visfly_dist.scene_worker.scenes_cli`` stays light to import.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from visfly_dist.scenes.generators import GENERATORS, generate_scene
    from visfly_dist.scenes.scene import Scene, SceneObject
    from visfly_dist.scenes.sources import resolve_source
    from visfly_dist.scenes.spawn import sample_free_positions
    from visfly_dist.scenes.storage import load_scene, save_scene

_EXPORTS = {
    "GENERATORS": "visfly_dist.scenes.generators",
    "generate_scene": "visfly_dist.scenes.generators",
    "Scene": "visfly_dist.scenes.scene",
    "SceneObject": "visfly_dist.scenes.scene",
    "resolve_source": "visfly_dist.scenes.sources",
    "sample_free_positions": "visfly_dist.scenes.spawn",
    "load_scene": "visfly_dist.scenes.storage",
    "save_scene": "visfly_dist.scenes.storage",
}

__all__ = [  # literal, so that linters see the names of the TYPE_CHECKING imports as exported
    "GENERATORS", "Scene", "SceneObject", "generate_scene", "load_scene", "resolve_source", "sample_free_positions", "save_scene",
]
assert sorted(__all__) == sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    if name not in _EXPORTS:
        raise AttributeError(f"module 'visfly_dist.scenes' has no attribute {name!r}")
    return getattr(importlib.import_module(_EXPORTS[name]), name)
