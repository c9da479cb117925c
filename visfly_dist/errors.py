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
