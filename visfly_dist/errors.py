"""The exception hierarchy shared by every part of visfly-dist.

Errors raised on user input name the value, what is accepted and the likely fix.
"""


class VisflyError(Exception):
    """Base class of every error visfly-dist raises on purpose."""


class ConfigError(VisflyError, ValueError):
    """A configuration value is invalid; raised before any work starts."""


class SceneError(VisflyError):
    """A scene cannot be found, loaded, generated or is outside the allowed roots."""


class ProtocolError(VisflyError):
    """A message on the wire is malformed, of the wrong version, or fails validation."""


class TransportTimeoutError(VisflyError):
    """A worker did not answer within its deadline."""


class WorkerDiedError(VisflyError):
    """A worker process went away (its liveliness token vanished or it stopped answering)."""

    def __init__(self, worker_id: str, cause: str) -> None:
        super().__init__(f"worker {worker_id!r} died: {cause}")
        self.worker_id = worker_id
        self.cause = cause


class NoWorkersError(VisflyError):
    """No live scene worker is left to serve the run."""


class RemoteError(VisflyError):
    """A worker answered a request with an error reply (its type and message are kept)."""

    def __init__(self, worker_id: str, error_type: str, message: str) -> None:
        super().__init__(f"worker {worker_id!r} replied {error_type}: {message}")
        self.worker_id = worker_id
        self.error_type = error_type
        self.message = message
