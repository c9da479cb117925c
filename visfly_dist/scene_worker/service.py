"""The scene worker's Zenoh service: one queryable answering the protocol's requests.

Threading. Zenoh calls the queryable's callback on its own thread; the callback only queues the
query. The *serving thread* (the one that called :meth:`SceneWorker.serve`) takes items off that
inbox and does all the request work (decode, render, FCL, encode, reply) one at a time, so GL
contexts stay on the thread that made them. The one exception is the CPU-heavy half of a
``load_scene`` (mesh loading or generation, BVH builds): it runs on loader threads (and, in a
start-up burst, generator processes), so a load never blocks health checks or other scenes' steps;
how many run at once is :mod:`visfly_dist.scene_worker.loads`'s business. When one ends, the loader
puts the job in the same inbox; the serving thread finishes the load (an EGL renderer is built
there), installs the scene, replies and starts the loads that may start now. Until then a step on
that key gets ``SceneError`` with code ``scene_loading``; a key being re-loaded keeps serving its
old scene. A reply (or error) is sent exactly once per query, and the query is then dropped
explicitly, which tells the querier that the answer is complete.

Every failure of a request becomes an error reply (``codec.error_message``) with the exception's
class name (``ProtocolError``, ``SceneError``) and its :class:`~visfly_dist.errors.ErrorCode`, or
``InternalError`` / ``internal`` for anything unexpected, which is also logged with its
traceback: the worker never dies of a request. Bounds (:class:`WorkerLimits`) turn requests that
would exhaust the worker into error replies.
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
import zenoh

from visfly_dist.errors import ConfigError, ErrorCode, ProtocolError, SceneError, VisflyError
from visfly_dist.protocol import keys
from visfly_dist.protocol.cameras import CameraSpec
from visfly_dist.protocol.codec import decode, encode, error_message
from visfly_dist.protocol.image_segment import SegmentTarget
from visfly_dist.protocol.local_channel import ChannelRequest, ChannelServer
from visfly_dist.protocol.messages import (
    Health,
    LoadScene,
    Request,
    SampleSpawn,
    StepRequest,
    UnloadScene,
    parse_request,
)
from visfly_dist.protocol.session import TOKEN_CHECK_S, SessionConfig, client_of, open_session, token_held
from visfly_dist.scene_worker.image_segments import SegmentMappings
from visfly_dist.scene_worker.limits import LOAD_RESERVE_BYTES, MIB, WorkerLimits, resident_bytes
from visfly_dist.scene_worker.loads import LoadJob, Respond, SceneLoader, parallel_loads
from visfly_dist.scene_worker.queries import query_scenes
from visfly_dist.scene_worker.render_base import BACKEND_CHOICES, gl_device_name, render_scenes_into
from visfly_dist.scene_worker.render_raycast import default_tracer
from visfly_dist.scene_worker.state import LoadedScene, PreparedScene, SceneTable, assemble_scene, same_scene
from visfly_dist.scene_worker.timing import StageTimer
from visfly_dist.scenes import sample_free_positions

log = logging.getLogger(__name__)

VISIBLE_CHECK_S = 5.0
"""How long a worker with a config file waits to see its own token through the router before it refuses to start."""


def default_worker_id() -> str:
    """``<host>-<pid>``, with characters a key expression cannot hold replaced by ``-``."""
    host = "".join(c if c.isalnum() or c in "_.-" else "-" for c in socket.gethostname()) or "host"
    return f"{host}-{os.getpid()}"[-keys.MAX_CHUNK_CHARS:]


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
        limits: what one request and the whole worker may ask for.
        threads: raycast tracing threads; default: the CPUs this process may use, at most 8. Also
            bounds the loads run at once before the first step (:func:`~visfly_dist.scene_worker.loads.parallel_loads`).
        channel: this worker's end of a local channel from the trainer that started it
            (:mod:`visfly_dist.protocol.local_channel`); its requests are served beside Zenoh's.

    Attributes:
        tracer: the raycast backend's tracer, ``native`` or ``embreex`` (the fallback).
        gl_device: ``GL_RENDERER`` of the egl backend's EGL device (None: raycast only).
    """

    def __init__(
        self, run_id: str, session: SessionConfig, scene_roots: Sequence[str | os.PathLike],
        backend: str = "auto", worker_id: str | None = None, limits: WorkerLimits | None = None,
        threads: int | None = None, channel: socket.socket | None = None,
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
        self.gl_device = gl_device_name(backend)   # GL_RENDERER of the egl backend's device, or None
        self.scene_roots = roots
        self.session_config = session
        self.limits = limits or WorkerLimits()
        self._scenes = SceneTable()
        self._segments = SegmentMappings()
        self._timer = StageTimer()
        self._last_encode_s = 0.0
        # The inbox holds Zenoh queries (from Zenoh's thread) and finished loads (from the loader).
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._loader = SceneLoader(roots, backend, threads, parallel_loads(threads), LOAD_RESERVE_BYTES, self._inbox.put)
        self._waiting_for_twin: list[LoadJob] = []  # loads of a scene another key's load is building
        self._stepping = False  # a step request was served
        self._stopping = False
        self._started = time.monotonic()
        self._session: Any = None
        self._queryable: Any = None
        self._token: Any = None
        self._channel_socket = channel
        self._channel: ChannelServer | None = None

    # -- lifecycle -------------------------------------------------------------------------------

    def start(self) -> "SceneWorker":
        """Open the session, refuse a duplicate id, declare the queryable, then the liveliness token
        (in that order: a get sent the moment the token is seen must find the queryable already there).

        Raises:
            ConfigError: the session cannot open, or another live worker of the run holds this id.
        """
        assert self._session is None, "start() called twice"
        self._session = open_session(self.session_config)
        try:
            self._refuse_duplicate_id()
            self._queryable = self._session.declare_queryable(
                self.rpc_key, zenoh.handlers.Callback(self._inbox.put, indirect=False))
            if self._channel_socket is not None:
                self._channel = ChannelServer(self._channel_socket, self._inbox.put)
            self._token = self._session.liveliness().declare_token(self.alive_key)
            self._check_visible()
        except BaseException:
            self.close()
            raise
        self._started = time.monotonic()
        return self

    def _check_visible(self) -> None:
        """ConfigError unless this worker's token is seen through the router: a router's access control
        drops a denied declaration without a word, so a worker it denies would look started.

        Checked with a second, short-lived client session holding the same config (credentials): a
        session sees its own declarations locally, never what the router made of them. Only for a
        worker that connects with a config file, since access control identifies users by the
        credentials such a file holds; the router's ACL must let workers ask for worker tokens
        (rule ``worker-check-token`` in ``deploy/zenoh/router-acl.json5``).
        """
        cfg = self.session_config
        if cfg.config_file is None or not cfg.connect:
            return
        checker = open_session(client_of(cfg.connect, shared_memory=False, lease_ms=cfg.lease_ms,
                                         config_file=cfg.config_file))
        try:
            deadline = time.monotonic() + VISIBLE_CHECK_S
            while time.monotonic() < deadline:
                if any(r.ok is not None for r in checker.liveliness().get(self.alive_key, timeout=TOKEN_CHECK_S)):
                    return
                time.sleep(0.1)
        finally:
            checker.close()
        raise ConfigError(
            f"worker {self.worker_id!r} declared its liveliness token {self.alive_key} but a session with the same "
            f"config ({cfg.config_file}) does not see it through {list(cfg.connect)} within {VISIBLE_CHECK_S:g} s: "
            "the router's access control denies this user the token (or the query of it); no trainer could reach "
            "this worker. Check the user and the run id against the router's ACL (deploy/zenoh/router-acl.json5: "
            "workers need liveliness_token, and liveliness_query for this check, on visfly/<run>/alive/worker/*)")

    def _refuse_duplicate_id(self) -> None:
        """ConfigError if a live worker of this run, reachable now, already holds this worker id.

        See :func:`~visfly_dist.protocol.session.token_held` (a predecessor just killed or hung is
        waited out for one lease).
        """
        if token_held(self._session, self.alive_key, self.session_config.lease_ms):
            raise ConfigError(
                f"worker id {self.worker_id!r} is already alive in run {self.run_id!r} (its liveliness token "
                f"{self.alive_key} exists): give each worker a unique --worker-id, or stop the other one first"
            )

    def serve(self, should_stop: Callable[[], bool] | None = None, poll_s: float = 0.2) -> None:
        """Answer requests until :meth:`stop` is called or ``should_stop()`` returns True.

        Both are checked at least every ``poll_s`` seconds; a request in progress is finished first.
        """
        assert self._session is not None, "call start() before serve()"
        while not self._stopping and not (should_stop is not None and should_stop()):
            self._serve_one(poll_s)

    def _serve_one(self, timeout_s: float) -> None:
        """Take one item off the inbox (waiting up to ``timeout_s``) and deal with it."""
        try:
            item = self._inbox.get(timeout=timeout_s)
        except queue.Empty:
            return
        if isinstance(item, LoadJob):
            self._finish_load(item)
        else:
            self._answer(item)

    def stop(self) -> None:
        """Ask :meth:`serve` to return. Safe from signal handlers and other threads."""
        self._stopping = True

    def close(self) -> None:
        """Withdraw the token and queryable, refuse queued requests and loads in progress, close
        renderers and session.

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
        self._loader.close()
        shutting_down = error_message("WorkerShutdown", ErrorCode.SHUTTING_DOWN,
                                      f"worker {self.worker_id!r} is shutting down")
        for job in self._scenes.pop_loading():
            job.respond(False, shutting_down)
        self._waiting_for_twin.clear()
        while True:
            try:
                item = self._inbox.get_nowait()
            except queue.Empty:
                break
            if isinstance(item, LoadJob):  # already answered above; free what it built (a cancelled one built nothing)
                future = item.future
                if future is not None and future.done() and not future.cancelled() and future.exception() is None:
                    future.result().discard()
            elif isinstance(item, ChannelRequest):
                item.respond(False, shutting_down)
            else:
                self._send(item, False, shutting_down)
        if self._channel is not None:
            self._channel.close()
            self._channel = None
        self._scenes.close()
        self._segments.close()
        if self._session is not None:
            self._session.close()
            self._session = None

    def __enter__(self) -> "SceneWorker":
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- requests --------------------------------------------------------------------------------

    def _answer(self, query: Any) -> None:
        """Answer a Zenoh query or a :class:`ChannelRequest`."""
        if isinstance(query, ChannelRequest):
            self.submit(query.payload, lambda ok, body: self._reply_channel(query, ok, body))
            return
        payload = query.payload.to_bytes() if query.payload is not None else b""
        self.submit(payload, lambda ok, body: self._reply(query, ok, body))

    def _reply_channel(self, request: ChannelRequest, ok: bool, body: bytes) -> None:
        with self._timer.time("reply"):
            request.respond(ok, body)

    def _reply(self, query: Any, ok: bool, body: bytes) -> None:
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

    def submit(self, payload: bytes, respond: Respond) -> None:
        """Answer one encoded request by calling ``respond(ok, body)`` exactly once.

        Transport-independent. Call it on the serving thread. Every request but ``load_scene`` is
        answered before this returns; a load is answered from :meth:`serve` (or :meth:`handle`)
        once its background half has finished. Never raises.
        """
        start = time.perf_counter()
        timings: dict[str, float] = {}
        try:
            with self._timer.time("decode", timings):
                request = parse_request(decode(payload))
            if isinstance(request, LoadScene):
                self._start_load(request, respond, start)
                return
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
        except Exception as exc:
            respond(False, self._error_reply(exc))
            return
        respond(True, body)

    def handle(self, payload: bytes, timeout_s: float = 120.0) -> tuple[bool, bytes]:
        """Answer one encoded request in-process and wait for it (loads included).

        For tests and tools without a transport; use it on one thread, not beside :meth:`serve`.

        Returns:
            ``(True, reply)`` or ``(False, error reply)``.
        """
        answers: list[tuple[bool, bytes]] = []
        self.submit(payload, lambda ok, body: answers.append((ok, body)))
        deadline = time.monotonic() + timeout_s
        while not answers:
            if time.monotonic() >= deadline:
                raise TimeoutError(f"no answer within {timeout_s} s")
            self._serve_one(0.05)
        return answers[0]

    def _error_reply(self, exc: Exception) -> bytes:
        if isinstance(exc, VisflyError):
            return error_message(type(exc).__name__, exc.code, str(exc))
        log.error("unexpected failure while serving a request", exc_info=exc)
        return error_message("InternalError", ErrorCode.INTERNAL, f"{type(exc).__name__}: {exc}")

    def _dispatch(self, request: Request, timings: dict[str, float]) -> dict[str, Any]:
        if isinstance(request, StepRequest):
            return self._step(request, timings)
        if isinstance(request, SampleSpawn):
            return self._sample_spawn(request)
        if isinstance(request, UnloadScene):
            return self._unload(request)
        assert isinstance(request, Health), request
        return self.health()

    # -- loads -----------------------------------------------------------------------------------

    def _start_load(self, request: LoadScene, respond: Respond, start: float) -> None:
        """Check the bounds, mark the key as loading and queue the heavy half for the loader."""
        key = request.scene_key
        if len(key) > self.limits.max_key_chars:
            raise ProtocolError(f"scene_key of {len(key)} chars exceeds this worker's bound of "
                                f"{self.limits.max_key_chars} (--max-key-chars)", code=ErrorCode.TOO_LARGE)
        if self._scenes.is_loading(key):
            raise SceneError(f"scene_key {key!r} is already loading on this worker; wait for its load reply",
                             code=ErrorCode.SCENE_LOADING)
        if key not in self._scenes and len(self._scenes) >= self.limits.max_scenes:
            raise SceneError(f"this worker holds {len(self._scenes)} scenes, its bound (--max-scenes); "
                             "unload one or load on another worker", code=ErrorCode.OVERLOADED)
        twin = self._scenes.serving(request)
        if twin is not None:  # one file over many slots: its meshes, renderer and queries serve every key
            self._share(twin, key, respond, start)
            return
        self._check_memory("before loading")
        job = LoadJob(request, respond, start)
        twin_building = self._building(request)
        self._scenes.begin_load(key, job)
        if twin_building:  # the same scene under another key (a start-up's burst): shared once built
            self._waiting_for_twin.append(job)
            return
        self._loader.add(job)
        self._start_loads()

    def _building(self, request: LoadScene, besides: LoadJob | None = None) -> bool:
        """Whether a load in progress (not one waiting for a twin, nor ``besides``) builds the scene
        ``request`` asks for."""
        return any(same_scene(job.request, request) for job in self._loader_jobs() if job is not besides)

    def _loader_jobs(self) -> list[LoadJob]:
        """The loads in progress that build their scene (those waiting for a twin do not)."""
        return [job for job in self._scenes.loading_jobs() if all(job is not w for w in self._waiting_for_twin)]

    def _share(self, twin: LoadedScene, key: str, respond: Respond, start: float) -> None:
        """Serve ``twin`` under ``key`` too, and answer that load."""
        loaded = twin.shared_as(key)
        self._scenes.put(loaded)
        log.info("scene %r shares the scene of %r (%r)", key, twin.key, twin.built_by.source)
        self._timer.add("load_scene", time.perf_counter() - start)
        respond(True, _loaded_reply(loaded))

    def _take_twins(self) -> None:
        """Serve the loads that waited for a twin being built: shared if it was built, else built now.

        Each is taken off the waiting list in turn, the others staying on it: a job still waiting is
        no builder, so after a failed build the first waiter builds and the rest wait for it."""
        for job in list(self._waiting_for_twin):
            self._waiting_for_twin = [w for w in self._waiting_for_twin if w is not job]
            key = job.request.scene_key
            if not self._scenes.owns_load(key, job):  # unloaded while it waited (already answered)
                continue
            twin = self._scenes.serving(job.request)
            if twin is not None:
                self._scenes.end_load(key, job)
                self._share(twin, key, job.respond, job.start)
            elif self._building(job.request, besides=job):
                self._waiting_for_twin.append(job)
            else:  # its twin failed or was unloaded: built on its own (and answered on its own)
                self._loader.add(job)

    def _start_loads(self) -> None:
        """Start every waiting load the loader lets start now; one the worker's memory no longer
        allows is refused here, one unloaded while it waited is dropped."""
        while (job := self._loader.next_job(resident_bytes(), self.limits.max_memory_bytes)) is not None:
            key = job.request.scene_key
            if not self._scenes.owns_load(key, job):  # unloaded while waiting (already answered)
                continue
            try:
                self._check_memory("before loading")
            except SceneError as exc:
                self._scenes.end_load(key, job)
                job.respond(False, self._error_reply(exc))
                continue
            self._loader.run(job)

    def _finish_load(self, job: LoadJob) -> None:
        """On the serving thread: install the prepared scene, answer the load, start the next ones."""
        self._loader.finished(job)
        try:
            self._install(job)
        finally:
            self._take_twins()
            self._start_loads()

    def _install(self, job: LoadJob) -> None:
        request = job.request
        assert job.future is not None and job.future.done()
        if not self._scenes.end_load(request.scene_key, job):  # unloaded while loading (or the worker closed)
            if not job.future.cancelled() and job.future.exception() is None:
                job.future.result().discard()
            return
        if job.child_s is not None:
            self._timer.add("generate_in_child", job.child_s)
        prepared: PreparedScene | None = None
        try:
            prepared = job.future.result()
            self._check_memory(f"with scene {request.source!r} built")
            loaded = assemble_scene(prepared, self.backend)
            prepared = None
            loaded.cameras = self._shared_cameras(loaded.cameras)
            self._scenes.put(loaded)
            scene = loaded.scene
            log.info("loaded scene %r from %r: %d triangles, backend %s",
                     request.scene_key, request.source, scene.num_triangles, loaded.renderer.name)
            body = _loaded_reply(loaded)
        except Exception as exc:
            if prepared is not None:
                prepared.discard()
            job.respond(False, self._error_reply(exc))
            return
        self._timer.add("load_scene", time.perf_counter() - job.start)
        job.respond(True, body)

    def _check_memory(self, when: str) -> None:
        """SceneError ``overloaded`` when this process's resident memory is at its bound."""
        used, bound = resident_bytes(), self.limits.max_memory_bytes
        if used is not None and used >= bound:
            raise SceneError(f"this worker uses {used / MIB:.0f} MB {when}, at or over its bound of {bound / MIB:.0f} MB "
                             f"(--max-memory-mb); unload scenes or load on another worker", code=ErrorCode.OVERLOADED)

    def _shared_cameras(self, cameras: tuple[CameraSpec, ...]) -> tuple[CameraSpec, ...]:
        """The equal cameras tuple a loaded scene already holds, else ``cameras``: scenes with the
        same cameras then share one tuple, and a step checks them by identity."""
        for key in self._scenes.keys():
            if self._scenes.get(key).cameras == cameras:
                return self._scenes.get(key).cameras
        return cameras

    def _unload(self, request: UnloadScene) -> dict[str, Any]:
        dropped = self._scenes.remove(request.scene_key)
        if dropped is not None:
            dropped.respond(False, error_message(
                "SceneError", ErrorCode.UNKNOWN_SCENE,
                f"load of scene_key {request.scene_key!r} was cancelled by unload_scene"))
        log.info("unloaded scene %r", request.scene_key)
        return {"type": "ok"}

    # -- steps -----------------------------------------------------------------------------------

    def _step(self, request: StepRequest, timings: dict[str, float]) -> dict[str, Any]:
        """Every entry rendered and queried; the reply's arrays hold all entries' rows in order."""
        if not self._stepping:
            self._stepping = True
            self._loader.steps_began()
        # Resolve every key and check the bounds before any work, so a bad request costs nothing.
        loaded, same_cameras = self._scenes.lookup(request.keys)
        if request.render and loaded:
            if not same_cameras:
                raise ProtocolError("the scenes of one step request must carry the same cameras")
            cameras = loaded[0].cameras
            self._check_pixels(len(request.poses) * loaded[0].pixels_per_agent)
        counts = request.counts.astype(np.int32)
        reply: dict[str, Any] = {"type": "step_result", "counts": counts, "images": {}}
        timings.setdefault("render_s", 0.0)
        timings.setdefault("query_s", 0.0)
        bounds = request.bounds()
        times = request.times.tolist()
        poses = request.poses
        if request.render and loaded:
            images, target, starts = self._image_buffers(request, cameras, counts, reply)
            with self._timer.time("render", timings):
                render_scenes_into([(scene.renderer, poses[start:end], scene.multi_agent, t)
                                    for scene, (start, end), t in zip(loaded, bounds, times)], images,
                                   starts.tolist())
            why = target is not None and self._segments.publish(target, images, starts, counts)
            if target is not None and not why:
                reply["images_in_segment"] = True
            else:
                if why:  # the segment changed under us: the images go inline, in request order
                    log.warning("replying inline: %s", why)
                    reply["segment_refused"] = why
                    images = {name: np.concatenate([image[s:s + c] for s, c in zip(starts.tolist(), counts.tolist())])
                              for name, image in images.items()}
                reply["images"] = images
        if request.query:
            with self._timer.time("query", timings):
                positions = poses[:, :3]
                answers = query_scenes([(scene.queries, positions[start:end], t)
                                        for scene, (start, end), t in zip(loaded, bounds, times)],
                                       request.search_radius)
                reply.update(collision=answers.collision, inside=answers.inside, nearest=answers.nearest,
                             distance=answers.distance)
        return reply

    def _image_buffers(self, request: StepRequest, cameras: Sequence[CameraSpec], counts: np.ndarray,
                       reply: dict[str, Any]) -> tuple[dict[str, np.ndarray], SegmentTarget | None, np.ndarray]:
        """Where the step's images go: the request's image segment if this worker can use it (its views,
        the segment target and each entry's first row there), else fresh arrays for the reply (None for
        the target, the entries one after another from row 0, and ``segment_refused`` set when a segment
        was offered)."""
        target = request.image_segment
        if target is not None and not self.session_config.shared_memory:
            reply["segment_refused"] = f"worker {self.worker_id!r} runs without shared memory (--no-shm)"
        elif target is not None:
            starts = target.starts(counts)
            rows = int((starts + counts).max()) if len(counts) else 0
            views, why = self._segments.views(target, cameras, rows)
            if views is not None:
                return views, target, starts
            log.info("replying inline: %s", why)
            reply["segment_refused"] = why
        images = {c.name: np.empty((int(counts.sum()), *c.shape), c.dtype) for c in cameras}
        return images, None, np.cumsum(counts) - counts

    def _check_pixels(self, pixels: int) -> None:
        if pixels > self.limits.max_pixels:
            raise ProtocolError(f"step asks for {pixels} pixels (agents x cameras x pixels), over this worker's "
                                f"bound of {self.limits.max_pixels} (--max-pixels); split it into smaller requests",
                                code=ErrorCode.TOO_LARGE)

    def _sample_spawn(self, request: SampleSpawn) -> dict[str, Any]:
        loaded = self._scenes.get(request.scene_key)
        positions = sample_free_positions(
            request.n, request.clearance, request.distribution, np.asarray(request.a),
            np.asarray(request.b), np.random.default_rng(request.seed), loaded.queries.distance,
            bounds=loaded.scene.bounds,
        )
        return {"type": "spawn", "positions": np.asarray(positions, dtype=np.float32)}

    def health(self) -> dict[str, Any]:
        """The ``health`` reply: identity, loaded and loading scenes, bounds, uptime, mapped image
        segments (name -> bytes) and cumulative stage timings."""
        return {"type": "health", "worker_id": self.worker_id, "pid": os.getpid(), "host": socket.gethostname(),
                "backend": self.backend, "tracer": self.tracer, "gl_device": self.gl_device, "scenes": self._scenes.keys(), "loading": self._scenes.loading_keys(),  # noqa: E501
                "limits": self.limits.to_dict(), "memory_bytes": resident_bytes() or 0, "uptime_s": time.monotonic() - self._started,
                "image_segments": self._segments.names(), "timings": self._timer.summary()}


def _loaded_reply(loaded: LoadedScene) -> bytes:
    """The encoded ``scene_loaded`` reply of a load."""
    scene = loaded.scene
    return encode({"type": "scene_loaded", "scene_key": loaded.key, "bounds": scene.bounds,
                   "num_triangles": scene.num_triangles, "num_objects": len(scene.objects),
                   "backend": loaded.renderer.name, "metadata": scene.metadata})
