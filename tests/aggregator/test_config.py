"""Configuration and scene-set checks: every problem is reported before any process starts."""

from __future__ import annotations

import pytest

from visfly_dist.aggregator import Aggregator, PoolConfig, SceneSetConfig
from visfly_dist.aggregator.dataset import SceneDataset, expand_sources
from visfly_dist.errors import ConfigError
from visfly_dist.protocol import CameraSpec


def test_defaults_are_valid():
    assert PoolConfig().validate().problems() == []
    assert SceneSetConfig().validate().num_agents == 1


def test_every_problem_reported_at_once():
    pool = PoolConfig(connect=("tcp/nohostport",), num_local_workers=-1, backend="vulkan", step_timeout_s=0, lease_ms=5)
    with pytest.raises(ConfigError) as info:
        pool.validate()
    text = str(info.value)
    for fragment in ("'tcp/nohostport'", "num_local_workers=-1", "backend='vulkan'", "step_timeout_s=0", "lease_ms=5"):
        assert fragment in text


@pytest.mark.parametrize("endpoint", ["127.0.0.1:7447", "tcp/host", "tcp/host:99999", "carrier-pigeon/a:1", ""])
def test_bad_endpoint_names_it(endpoint):
    with pytest.raises(ConfigError, match="endpoint"):
        PoolConfig(connect=(endpoint,)).validate()


def test_remote_only_pool_needs_an_endpoint():
    with pytest.raises(ConfigError, match=r"num_local_workers=0 \(--workers 0\) needs endpoints where remote workers can join: --connect"):
        PoolConfig(num_local_workers=0).validate()
    PoolConfig(num_local_workers=0, connect=("tcp/10.0.0.5:7447",)).validate()


@pytest.mark.parametrize("kwargs, match", [
    ({"num_scenes": 0}, r"num_scenes=0 must be an int >= 1"),
    ({"agents_per_scene": 0}, r"agents_per_scene=0"),
    ({"swap_every_resets": -1}, r"swap_every_resets=-1"),
    ({"sources": ()}, r"sources is empty"),
])
def test_bad_scene_set(kwargs, match):
    with pytest.raises(ConfigError, match=match):
        SceneSetConfig(**kwargs).validate()


def test_aggregator_rejects_before_starting_anything(tmp_path):
    cams = [CameraSpec()]
    with pytest.raises(ConfigError, match="num_scenes=0"):
        Aggregator(PoolConfig(), SceneSetConfig(num_scenes=0), cams)
    with pytest.raises(ConfigError, match=r"scene path 'missing/scene.glb' not found"):
        Aggregator(PoolConfig(scene_roots=(str(tmp_path),)), SceneSetConfig(sources=("missing/scene.glb",)), cams)
    with pytest.raises(ConfigError, match=r"'tcp/localhost'"):
        Aggregator(PoolConfig(connect=("tcp/localhost",)), SceneSetConfig(), cams)
    with pytest.raises(ConfigError, match="unknown scene kind 'volcano'"):
        Aggregator(PoolConfig(), SceneSetConfig(sources=("gen:volcano",)), cams)
    with pytest.raises(ConfigError, match="cameras"):
        Aggregator(PoolConfig(), SceneSetConfig(), [])


def test_paths_and_globs_resolve_relative_to_roots(tmp_path):
    (tmp_path / "set").mkdir()
    for name in ("b.glb", "a.glb", "c.obj"):
        (tmp_path / "set" / name).write_bytes(b"")
    assert expand_sources(("set/*.glb",), (str(tmp_path),)) == ["set/a.glb", "set/b.glb"]
    assert expand_sources((str(tmp_path / "set" / "c.obj"),), (str(tmp_path),)) == ["set/c.obj"]
    with pytest.raises(ConfigError, match="glob 'set/\\*.ply' matches nothing"):
        expand_sources(("set/*.ply",), (str(tmp_path),))
    with pytest.raises(ConfigError, match="outside the scene roots"):
        expand_sources((str(tmp_path / "set" / "c.obj"),), (str(tmp_path / "set" / "sub"),))


def test_unseeded_specs_get_distinct_reproducible_seeds():
    a = SceneDataset(("gen:pillars?count=4",), (), shuffle=True, seed=3).take(5)
    b = SceneDataset(("gen:pillars?count=4",), (), shuffle=True, seed=3).take(5)
    assert a == b
    assert len(set(a)) == 5 and all(s.startswith("gen:pillars?count=4&seed=") for s in a)
    seeded = SceneDataset(("gen:empty?seed=7",), (), shuffle=True, seed=0).take(2)
    assert seeded == ["gen:empty?seed=7"] * 2


def test_shuffled_passes_cover_every_source():
    sources = tuple(f"gen:empty?seed={i}" for i in range(5))
    ds = SceneDataset(sources, (), shuffle=True, seed=1)
    first, second = ds.take(5), ds.take(5)
    assert sorted(first) == sorted(sources) and sorted(second) == sorted(sources)
    assert SceneDataset(sources, (), shuffle=False, seed=1).take(5) == list(sources)


def test_a_log_dir_that_is_a_file_is_refused(tmp_path):
    taken = tmp_path / "taken"
    taken.write_text("not a folder")
    with pytest.raises(ConfigError, match="log_dir=.*must be a folder"):
        PoolConfig(log_dir=str(taken)).validate()
    PoolConfig(log_dir=str(tmp_path / "new" / "workers")).validate()  # made when the pool opens
