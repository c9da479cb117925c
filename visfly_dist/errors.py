"""The exception hierarchy shared by every part of visfly-dist, and the wire's error codes.

Errors raised on user input name the value, what is accepted and the likely fix. Every error a
worker sends back carries a machine-readable :class:`ErrorCode` (``docs/PROTOCOL.md``): callers
test the code, never the message text.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any, Mapping


class ErrorCode(StrEnum):
    """Machine-readable cause of an error reply (the ``code`` field on the wire)."""

    BAD_REQUEST = "bad_request"        # malformed or invalid request: fix the sender
    TOO_LARGE = "too_large"            # valid but beyond this worker's bounds (pixels, key length): split it
    UNKNOWN_SCENE = "unknown_scene"    # the scene key is not loaded here (e.g. the worker restarted)
    SCENE_LOADING = "scene_loading"    # the scene key is still loading: retry after its load reply
    SCENE_ERROR = "scene_error"        # the scene cannot be loaded/generated/sampled as asked
    SCENE_MISSING = "scene_missing"    # the scene file is not under this worker's scene roots: another may have it
    OVERLOADED = "overloaded"          # the worker is full (scenes per worker): use another worker
    SHUTTING_DOWN = "shutting_down"    # the worker is stopping: use another worker
    INTERNAL = "internal"              # a bug on the worker (logged there with its traceback)


class VisflyError(Exception):
    """Base class of every error visfly-dist raises on purpose.

    Args:
        *args: the message.
        code: the wire code of this error; default the class's ``code``.
    """

    code: ErrorCode = ErrorCode.INTERNAL

    def __init__(self, *args: object, code: ErrorCode | None = None) -> None:
        super().__init__(*args)
        if code is not None:
            self.code = ErrorCode(code)


class ConfigError(VisflyError, ValueError):
    """A configuration value is invalid; raised before any work starts."""

    code = ErrorCode.BAD_REQUEST


class TaskHookError(ConfigError):
    """A task hook (``get_reward``, ``get_success``, ``get_failure``, ``get_observation``) returned
    something its contract does not allow: a wrong shape, dtype or set of keys."""


class SceneError(VisflyError):
    """A scene cannot be found, loaded, generated or is outside the allowed roots."""

    code = ErrorCode.SCENE_ERROR


class ProtocolError(VisflyError):
    """A message on the wire is malformed, of the wrong version, or fails validation."""

    code = ErrorCode.BAD_REQUEST


class TransportTimeoutError(VisflyError):
    """A worker did not answer within its deadline."""


class LostRequestsError(TransportTimeoutError):
    """Workers are alive (they answer health probes) but the run's requests of some size never reach them.

    Replacing workers cannot help then: the fault is on the sender's side, most likely this
    process's Zenoh shared memory. Raised after ``PoolConfig.lost_request_limit`` such requests in
    a row, instead of replacing worker after worker.

    Attributes:
        worker_id: the worker of the last lost request.
        request_bytes: that request's size.
    """

    def __init__(self, run_id: str, worker_id: str, request_bytes: int, count: int, timeout_s: float,
                 cause: str, transport: str = "zenoh") -> None:
        head = (f"run {run_id!r}: local worker {worker_id!r} is alive (it answers health probes), but {count} "
                f"request(s) in a row of {request_bytes} bytes or more got no answer within "
                f"step_timeout_s={timeout_s:g} (last: {cause})")
        if transport == "channel":  # a socket pair delivers in order: the worker got them and did not answer
            why = (": they went over the workers' private channels, which answer the probes, so the workers "
                   "received them and are stuck in such requests or slower than step_timeout_s; raise "
                   "step_timeout_s if they are only slow")
        else:
            why = (": large requests do not arrive. Replacing workers would not help: the fault is on this side, "
                   "most likely this process's Zenoh shared memory (its /dev/shm/*.zenoh files removed while it "
                   "runs, e.g. by a /dev/shm cleanup or systemd-logind's RemoveIPC). Restart the run, or set "
                   "PoolConfig.shared_memory=False; if the workers are only slower than step_timeout_s, raise it")
        super().__init__(head + why)
        self.worker_id = worker_id
        self.request_bytes = request_bytes


class WorkerDiedError(VisflyError):
    """A worker process went away (its liveliness token vanished or it stopped answering)."""

    def __init__(self, worker_id: str, cause: str) -> None:
        super().__init__(f"worker {worker_id!r} died: {cause}")
        self.worker_id = worker_id
        self.cause = cause


class NoWorkersError(VisflyError):
    """No live scene worker is left to serve the run."""


class RemoteError(VisflyError):
    """A worker answered a request with an error reply (its type, code and message are kept).

    Attributes:
        worker_id: the worker that answered.
        error_type: the exception class name on the worker (``SceneError``...).
        code: the :class:`ErrorCode`; test this, not the message.
        message: the worker's message.
    """

    def __init__(self, worker_id: str, error_type: str, message: str,
                 code: ErrorCode | str = ErrorCode.INTERNAL) -> None:
        super().__init__(f"worker {worker_id!r} replied {error_type} ({code}): {message}")
        self.worker_id = worker_id
        self.error_type = error_type
        self.message = message
        self.code = ErrorCode(code) if code in ErrorCode._value2member_map_ else ErrorCode.INTERNAL

    @classmethod
    def from_reply(cls, worker_id: str, reply: Mapping[str, Any]) -> "RemoteError":
        """Build from a decoded error reply ``{"type": "error", "error", "code", "message"}``.

        A missing or unknown code reads as ``internal`` (a worker speaking a newer protocol).
        """
        return cls(worker_id, str(reply.get("error", "Error")), str(reply.get("message", "")),
                   str(reply.get("code", ErrorCode.INTERNAL)))


class SessionConnectError(VisflyError, ConnectionError):
    """A Zenoh session could not join the network; the subclasses say why, as far as Zenoh tells.

    Attributes:
        endpoints: the endpoints that were tried.
    """

    def __init__(self, message: str, endpoints: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.endpoints = tuple(endpoints)


class RouterUnreachableError(SessionConnectError):
    """Nothing accepts TCP connections at any of the endpoints (host down, wrong port, firewall)."""


class TlsHandshakeError(SessionConnectError):
    """The TLS handshake failed: unknown CA, name mismatch, missing client certificate, not TLS."""


class AuthenticationError(SessionConnectError):
    """The router was reached but refused the session: wrong or missing user/password."""


class AccessDeniedError(NoWorkersError):
    """An authenticated session sees no worker of its run: most likely the router's access control.

    Zenoh drops a denied declaration, query or reply without telling either side, so this is a
    diagnosis, not a report: the message names the user and the keys the ACL must allow.
    """
