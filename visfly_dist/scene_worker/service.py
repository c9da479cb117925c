"""The scene worker's Zenoh service: one queryable answering the protocol's requests.

Threading: Zenoh calls the queryable's callback on its own thread (one per entity). The callback
only queues the query; the thread that called :meth:`SceneWorker.serve` takes queries off the queue
and does all the work (decode, render, FCL, encode, reply) one request at a time. Rendering and
geometry hold the GIL and the GL context anyway, so serial work on one known thread costs nothing
and keeps the GL context on the thread that created it. A queued query is replied to (or its error
sent) and then dropped explicitly, which is what tells the querier that the answer is complete.

Every failure of a request becomes an error reply (``codec.error_message``) whose type is the
exception's class name (``ProtocolError``, ``SceneError``, ``ConfigError``), or ``InternalError`` for
anything unexpected, which is also logged with its traceback: the worker never dies of a request.
"""

from __future__ import annotations

import logging
import os
import queue
import socket
import time
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from visfly_dist.errors import ConfigError, VisflyError
from visfly_dist.protocol import keys
from visfly_dist.protocol.codec import decode, encode, error_message
from visfly_dist.protocol.messages import (
    Health, LoadScene, Request, SampleSpawn, StepRequest, UnloadScene, parse_request,
)
from visfly_dist.protocol.session import SessionConfig, open_session
from visfly_dist.scene_worker.render_base import BACKEND_CHOICES
from visfly_dist.scene_worker.render_raycast import default_tracer
from visfly_dist.scene_worker.state import LoadedScene, SceneTable, build_scene
from visfly_dist.scene_worker.timing import StageTimer
from visfly_dist.scenes import sample_free_positions

log = logging.getLogger(__name__)


def default_worker_id() -> str:
    """``<host>-<pid>``, with characters a key expression cannot hold replaced by ``-``."""
    host = "".join(c if c.isalnum() or c in "_.-" else "-" for c in socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"


class SceneWorker:
    """Serves scenes (rendering and obstacle queries) to one run over Zenoh.

    Usage::

        with SceneWorker("run1", SessionConfig(listen=("tcp/127.0.0.1:7447",)), ["scenes"]) as w:
            w.serve()          # until stop() is called (e.g. from a signal handler)

    Args:
        run_id: the run namespace of the key expressions.
        session: how to join the Zenoh network.
        scene_roots: directories scene files may be loaded from (at least one).
        backend: ``auto``, ``egl`` or ``raycast``; ``auto`` chooses per scene from its cameras.
        worker_id: this worker's id in the run; default ``<host>-<pid>``.
        threads: raycast tracing threads; default: the CPUs this process may use, at most 8.

    Attributes:
        tracer: the raycast backend's tracer, ``native`` or ``embreex`` (the fallback).
    """

    def __init__(
        self, run_id: str, session: SessionConfig, scene_roots: Sequence[str | os.PathLike],
        backend: str = "auto", worker_id: str | None = None, threads: int | None = None,
    ) -> None:
        if backend not in BACKEND_CHOICES:
            raise ConfigError(f"backend={backend!r} must be one of {BACKEND_CHOICES}")
        roots = [Path(r).expanduser().resolve() for r in scene_roots]
        if not roots:
            raise ConfigError("a worker needs at least one scene root (--scene-root DIR)")
        missing = [str(r) for r in roots if not r.is_dir()]
        if missing:
            raise ConfigError(f"scene roots {missing} are not directories; pass existing folders to --scene-root")
        self.run_id = run_id
        self.worker_id = worker_id or default_worker_id()
        self.rpc_key = keys.worker_rpc(run_id, self.worker_id)
        self.alive_key = keys.worker_alive(run_id, self.worker_id)
        self.backend = backend
        self.threads = threads
        self.tracer, reason = default_tracer()
        log.info("raycast tracer %s (%s)", self.tracer, reason)
        self.scene_roots = roots
        self.session_config = session
        self._scenes = SceneTable()
        self._timer = StageTimer()
        self._last_encode_s = 0.0
        self._queries: queue.SimpleQueue = queue.SimpleQueue()
        self._stopping = False
        self._started = time.monotonic()
        self._session: Any = None
        self._queryable: Any = None
        self._token: Any = None

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> "SceneWorker":
        """Open the session, declare the queryable, then the liveliness token (in that order:
        a get sent the moment the token is seen must find the queryable already there)."""
        assert self._session is None, "start() called twice"
        self._session = open_session(self.session_config)
        try:
            self._queryable = self._session.declare_queryable(self.rpc_key, self._queries.put)
            self._token = self._session.liveliness().declare_token(self.alive_key)
        except BaseException:
            self.close()
            raise
        self._started = time.monotonic()
        return self

    def serve(self, should_stop: Callable[[], bool] | None = None, poll_s: float = 0.2) -> None:
        """Answer requests until :meth:`stop` is called or ``should_stop()`` returns True.

        Both are checked at least every ``poll_s`` seconds; a request in progress is finished first.
        """
        assert self._session is not None, "call start() before serve()"
        while not self._stopping and not (should_stop is not None and should_stop()):
            try:
                query = self._queries.get(timeout=poll_s)
            except queue.Empty:
                continue
            self._answer(query)

    def stop(self) -> None:
        """Ask :meth:`serve` to return. Safe from signal handlers and other threads."""
        self._stopping = True

    def close(self) -> None:
        """Withdraw the token and queryable, refuse queued requests, close renderers and session.

        Idempotent. The token goes first so observers stop routing work here at once.
        """
        self._stopping = True
        for entity in (self._token, self._queryable):
            if entity is not None:
                try:
                    entity.undeclare()
                except Exception:  # the session may already be gone
                    log.debug("undeclare failed", exc_info=True)
        self._token = self._queryable = None
        while True:
            try:
                query = self._queries.get_nowait()
            except queue.Empty:
                break
            self._send(query, False, error_message("WorkerShutdown", f"worker {self.worker_id!r} is shutting down"))
        self._scenes.close()
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "SceneWorker":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- requests --------------------------------------------------------------------------------

    def _answer(self, query: Any) -> None:
        payload = query.payload.to_bytes() if query.payload is not None else b""
        ok, body = self.handle(payload)
        with self._timer.time("reply"):
            self._send(query, ok, body)

    def _send(self, query: Any, ok: bool, body: bytes) -> None:
        try:
            if ok:
                query.reply(self.rpc_key, body)
            else:
                query.reply_err(body)
        except Exception:  # the querier may have timed out or the session closed
            log.warning("could not send a reply", exc_info=True)
        finally:
            query.drop()

    def handle(self, payload: bytes) -> tuple[bool, bytes]:
        """Answer one encoded request: ``(True, reply)`` or ``(False, error reply)``.

        Transport-independent, so it can be exercised in-process. Never raises.
        """
        start = time.perf_counter()
        timings: dict[str, float] = {}
        try:
            with self._timer.time("decode", timings):
                request = parse_request(decode(payload))
            reply = self._dispatch(request, timings)
            if request.type == "step":
                timings["encode_s"] = self._last_encode_s
                timings["total_s"] = time.perf_counter() - start
                reply["timings"] = timings
            t0 = time.perf_counter()
            body = encode(reply)
            self._last_encode_s = time.perf_counter() - t0
            self._timer.add("encode", self._last_encode_s)
            self._timer.add(request.type, time.perf_counter() - start)
            return True, body
        except VisflyError as exc:
            return False, error_message(type(exc).__name__, str(exc))
        except Exception as exc:
            log.exception("unexpected failure while serving a request")
            return False, error_message("InternalError", f"{type(exc).__name__}: {exc}")

    def _dispatch(self, request: Request, timings: dict[str, float]) -> dict[str, Any]:
        if isinstance(request, StepRequest):
            return self._step(request, timings)
        if isinstance(request, LoadScene):
            return self._load(request)
        if isinstance(request, SampleSpawn):
            return self._sample_spawn(request)
        if isinstance(request, UnloadScene):
            self._scenes.remove(request.scene_key)
            log.info("unloaded scene %r", request.scene_key)
            return {"type": "ok"}
        assert isinstance(request, Health), request
        return self.health()

    def _load(self, request: LoadScene) -> dict[str, Any]:
        loaded = build_scene(request, self.scene_roots, self.backend, self.threads)
        self._scenes.put(loaded)
        scene = loaded.scene
        log.info("loaded scene %r from %r: %d triangles, backend %s",
                 request.scene_key, request.source, scene.num_triangles, loaded.renderer.name)
        return {"type": "scene_loaded", "scene_key": request.scene_key, "bounds": scene.bounds,
                "num_triangles": scene.num_triangles, "num_objects": len(scene.objects),
                "backend": loaded.renderer.name, "metadata": scene.metadata}

    def _step(self, request: StepRequest, timings: dict[str, float]) -> dict[str, Any]:
        # Resolve every key before any work, so a bad key costs nothing.
        loaded = [self._scenes.get(s.scene_key) for s in request.scenes]
        timings.setdefault("render_s", 0.0)
        timings.setdefault("query_s", 0.0)
        results = []
        for item, scene in zip(request.scenes, loaded):
            result: dict[str, Any] = {"scene_key": item.scene_key, "images": {}}
            if request.render:
                with self._timer.time("render", timings):
                    result["images"] = _render(scene, item.poses)
            if request.query:
                with self._timer.time("query", timings):
                    result.update(_query(scene, item.poses, request.search_radius))
            results.append(result)
        return {"type": "step_result", "scenes": results}

    def _sample_spawn(self, request: SampleSpawn) -> dict[str, Any]:
        loaded = self._scenes.get(request.scene_key)
        positions = sample_free_positions(
            request.n, request.clearance, request.distribution, np.asarray(request.a),
            np.asarray(request.b), np.random.default_rng(request.seed), loaded.queries.distance,
            bounds=loaded.scene.bounds,
        )
        return {"type": "spawn", "positions": np.asarray(positions, dtype=np.float32)}

    def health(self) -> dict[str, Any]:
        """The ``health`` reply: identity, loaded scenes, uptime and cumulative stage timings."""
        return {"type": "health", "worker_id": self.worker_id, "pid": os.getpid(), "host": socket.gethostname(),
                "backend": self.backend, "tracer": self.tracer, "scenes": self._scenes.keys(),
                "uptime_s": time.monotonic() - self._started, "timings": self._timer.summary()}


def _render(scene: LoadedScene, poses: np.ndarray) -> dict[str, np.ndarray]:
    if len(poses) == 0:
        return {c.name: np.zeros((0, *c.shape), dtype=c.dtype) for c in scene.cameras}
    return scene.renderer.render(poses, show_drones=scene.multi_agent)


def _query(scene: LoadedScene, poses: np.ndarray, search_radius: float) -> dict[str, np.ndarray]:
    if len(poses) == 0:
        return {"collision": np.zeros(0, bool), "inside": np.zeros(0, bool),
                "nearest": np.zeros((0, 3), np.float32), "distance": np.zeros(0, np.float32)}
    q = scene.queries.query(poses[:, :3], search_radius)
    return {"collision": np.asarray(q.collision, dtype=bool), "inside": np.asarray(q.inside, dtype=bool),
            "nearest": np.asarray(q.nearest, dtype=np.float32), "distance": np.asarray(q.distance, dtype=np.float32)}
