"""The scene set as data: sources expanded and checked up front, then drawn as an endless stream.

A source is one of:
- a generator spec ``gen:KIND?k=v&...``; without ``seed`` each use draws a fresh seed from the
  dataset's generator, so every slot and every swap gets a different scene ("scenes as data");
- a path relative to one of the scene roots (a scene folder, a mesh file, a Habitat
  ``*.scene_instance.json``), or an absolute path inside a root;
- a glob relative to the roots (``garages/*.glb``), expanded here in sorted order.

Workers resolve paths against their own roots, so paths travel relative to the root they were
found in; local workers are given the same roots.
"""

from __future__ import annotations

import glob
import os
from urllib.parse import parse_qsl

import numpy as np

from visfly_dist.errors import ConfigError, SceneError
from visfly_dist.scenes.source_syntax import GEN_PREFIX, split_path_source

_GLOB_CHARS = set("*?[")


def has_seed(spec: str) -> bool:
    """Whether a ``gen:`` spec sets its seed."""
    query = spec.partition("?")[2]
    return any(key == "seed" for key, _ in parse_qsl(query, keep_blank_values=True))


def with_seed(spec: str, seed: int) -> str:
    """``spec`` with ``seed=S`` appended (the spec must not set one)."""
    return f"{spec}{'&' if '?' in spec else '?'}seed={int(seed)}"


def _check_gen_spec(spec: str) -> str | None:
    from visfly_dist.scenes import GENERATORS
    from visfly_dist.scenes.sources import parse_gen_spec

    try:
        kind, _, _ = parse_gen_spec(spec)
    except SceneError as exc:
        return f"source {spec!r}: {exc}"
    if kind not in GENERATORS:
        return f"source {spec!r}: unknown scene kind {kind!r}; valid kinds: {sorted(GENERATORS)}"
    return None


def _relative_to_roots(path: str, roots: tuple[str, ...]) -> str | None:
    real = os.path.realpath(path)
    for root in roots:
        root_real = os.path.realpath(root)
        if os.path.commonpath([real, root_real]) == root_real and real != root_real:
            return os.path.relpath(real, root_real)
    return None


def expand_sources(sources: tuple[str, ...], roots: tuple[str, ...]) -> list[str]:
    """Expand globs and check every source; raise ConfigError listing every problem.

    Returns concrete sources: generator specs unchanged, paths relative to their root (mesh load
    options such as ``?up=z`` kept on every match).
    """
    out: list[str] = []
    problems: list[str] = []
    roots_hint = f"scene_roots={list(roots)}" if roots else "no scene_roots were given"
    for source in sources:
        options = ""
        if not source.startswith(GEN_PREFIX):   # mesh load options (``room.glb?up=z``) travel along
            try:
                path, parsed = split_path_source(source)
            except SceneError as exc:
                problems.append(str(exc))
                continue
            if parsed:
                source, options = path, source[len(path):]
        if source.startswith(GEN_PREFIX):
            problem = _check_gen_spec(source)
            if problem:
                problems.append(problem)
            else:
                out.append(source)
        elif _GLOB_CHARS & set(source):
            matches = sorted({os.path.relpath(m, root) for root in roots
                              for m in glob.glob(os.path.join(root, source), recursive=True)})
            if not matches:
                problems.append(f"glob {source!r} matches nothing under {roots_hint}")
            out.extend(m + options for m in matches)
        elif os.path.isabs(source):
            rel = _relative_to_roots(source, roots)
            if not os.path.exists(source):
                problems.append(f"scene path {source!r} does not exist")
            elif rel is None:
                problems.append(f"scene path {source!r} is outside the scene roots ({roots_hint}); add its folder to scene_roots")
            else:
                out.append(rel + options)
        elif any(os.path.exists(os.path.join(root, source)) for root in roots):
            out.append(os.path.normpath(source) + options)
        else:
            where = f"under {roots_hint}" if roots else f"({roots_hint})"
            problems.append(f"scene path {source!r} not found {where}; give a path relative to a root, or a 'gen:KIND' spec")
    if problems:
        raise ConfigError("invalid scene sources: " + "; ".join(problems))
    return out


class SceneDataset:
    """An endless, seeded stream of concrete scene sources.

    Sources are taken in passes; with ``shuffle`` each pass is a fresh permutation. Generator specs
    without a seed get one drawn here, so the stream is the same for the same seed.
    """

    def __init__(self, sources: tuple[str, ...], roots: tuple[str, ...], shuffle: bool, seed: int) -> None:
        self.entries = expand_sources(tuple(sources), tuple(roots))
        self.shuffle = shuffle
        self._rng = np.random.default_rng(seed)
        self._order: list[int] = []
        self._origin: dict[str, str] = {}  # concrete source handed out -> its entry
        self.dropped: dict[str, str] = {}  # entry -> why it was dropped

    def drop(self, source: str, why: str) -> bool:
        """Stop handing out the entry ``source`` (a concrete source from :meth:`next_source`) came
        from. Returns whether any entry remains; a source dropped already changes nothing."""
        entry = self._origin.get(source, source)
        if entry in self.entries:
            keep = [e for e in self.entries if e != entry]
            order = [self.entries[i] for i in self._order if self.entries[i] != entry]
            self.entries = keep
            self._order = [keep.index(e) for e in order]
            self.dropped[entry] = why
        return bool(self.entries)

    def next_source(self) -> str:
        """The next concrete source (a seeded gen spec or a root-relative path)."""
        if not self._order:
            idx = np.arange(len(self.entries))
            if self.shuffle:
                idx = self._rng.permutation(idx)
            self._order = [int(i) for i in idx]
        entry = self.entries[self._order.pop(0)]
        source = entry
        if entry.startswith(GEN_PREFIX) and not has_seed(entry):
            source = with_seed(entry, int(self._rng.integers(0, 2**31 - 1)))
        self._origin[source] = entry
        return source

    def take(self, n: int) -> list[str]:
        """The next ``n`` sources."""
        return [self.next_source() for _ in range(n)]
