"""Zenoh session configuration shared by workers, the aggregator and the router command.

Facts that shaped this (measured with Zenoh 1.10, see docs/ARCHITECTURE.md): always set ``listen/endpoints`` (a default peer
listens on every interface); turn multicast scouting off (we connect explicitly); the lease that
bounds hang detection is the one configured on the *monitored* side; shared memory is on by
default and only helps between processes on one host.

A Zenoh JSON5 config file (``--zenoh-config FILE``, ``SessionConfig.config_file``, or the
``ZENOH_CONFIG`` variable when neither is given) is loaded first; the settings visfly-dist makes
itself are applied on top of it and win (:data:`OWN_KEYS`). Everything else in the file (TLS,
user/password, access control, other transport settings) is used as written. Relative file paths
inside it (certificates, keys, the users file) are relative to the config file's own folder.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field
from typing import Sequence

from visfly_dist.errors import ConfigError

VALID_MODES = ("peer", "client", "router")
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"
ZENOH_CONFIG_ENV = "ZENOH_CONFIG"
# Keys visfly-dist always sets, overriding a config file.
OWN_KEYS = ("mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled",
            "transport/shared_memory/enabled", "transport/link/tx/lease")
# Keys of a config file that hold file paths: resolved against the file's folder, checked to exist.
PATH_KEYS = (
    "transport/link/tls/root_ca_certificate",
    "transport/link/tls/listen_certificate",
    "transport/link/tls/listen_private_key",
    "transport/link/tls/connect_certificate",
    "transport/link/tls/connect_private_key",
    "transport/auth/usrpwd/dictionary_file",
)


def resolve_config_file(path: str | os.PathLike | None) -> str | None:
    """The config file to use: ``path``, else ``$ZENOH_CONFIG`` (when set and non-empty), else None.

    Returns an absolute path, so it stays valid for processes started in another folder.
    """
    chosen = os.fspath(path) if path is not None else os.environ.get(ZENOH_CONFIG_ENV) or None
    return os.path.abspath(os.path.expanduser(chosen)) if chosen else None


def load_config_file(path: str):
    """Parse a Zenoh JSON5 config file into a ``zenoh.Config``, with its file paths made absolute.

    Raises:
        ConfigError: naming the file: missing, unparsable, unknown keys, or a path in it that
            does not exist.
    """
    import zenoh

    if not os.path.isfile(path):
        raise ConfigError(f"zenoh config file {path!r} does not exist")
    try:
        cfg = zenoh.Config.from_file(path)
    except Exception as exc:  # zenoh raises ZError with the parser's message and its Rust source location
        detail = " ".join(str(exc).split(" at /")[0].split())
        raise ConfigError(f"zenoh config file {path!r} is not a valid Zenoh config: {detail}") from None
    folder = os.path.dirname(path)
    for key in PATH_KEYS:
        value = json.loads(cfg.get_json(key))
        if value is None:
            continue
        if not isinstance(value, str) or not value:
            raise ConfigError(f"zenoh config file {path!r}: {key} must be a file path, got {value!r}")
        full = os.path.normpath(os.path.join(folder, os.path.expanduser(value)))
        if not os.path.isfile(full):
            raise ConfigError(f"zenoh config file {path!r}: {key} {value!r} does not exist (looked for {full!r}; "
                              "relative paths are relative to the config file's folder)")
        cfg.insert_json5(key, json.dumps(full))
    return cfg


LEASE_MS_RANGE = (200, 600_000)
"""Bounds of a link lease, ms: below, a busy link is taken for dead; above, a dead one is noticed too late."""


def lease_problem(lease_ms: int) -> str | None:
    """What is wrong with a link lease of ``lease_ms``, or ``None``."""
    low, high = LEASE_MS_RANGE
    return None if low <= int(lease_ms) <= high else f"lease_ms={lease_ms} must be in [{low}, {high}]"


@dataclass(frozen=True)
class SessionConfig:
    """How a process joins the Zenoh network.

    Attributes:
        mode: ``peer``, ``client`` or ``router``.
        connect: endpoints to connect to, e.g. ``("tcp/10.0.0.5:7447",)``.
        listen: endpoints to listen on; defaults to loopback on an ephemeral port for peers.
        shared_memory: use Zenoh shared memory for large payloads (same-host only).
        lease_ms: link lease; a hung process is declared dead after about this long.
        extra: further ``key -> JSON value`` settings (TLS, auth), inserted verbatim, last.
        config_file: a Zenoh JSON5 config file (TLS, usrpwd, access control; see ``deploy/``)
            loaded first; the fields above are applied on top of it. ``None`` uses
            ``$ZENOH_CONFIG`` when that is set. Stored as an absolute path.
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = (LOOPBACK_LISTEN,)
    shared_memory: bool = True
    lease_ms: int = 2000
    extra: tuple[tuple[str, object], ...] = field(default_factory=tuple)
    config_file: str | None = None

    def __post_init__(self) -> None:
        if self.mode not in VALID_MODES:
            raise ConfigError(f"mode={self.mode!r} must be one of {VALID_MODES}")
        for ep in (*self.connect, *self.listen):
            if not isinstance(ep, str) or "/" not in ep:
                raise ConfigError(f"endpoint {ep!r} must look like 'tcp/HOST:PORT'")
        problem = lease_problem(self.lease_ms)
        if problem:
            raise ConfigError(problem)
        object.__setattr__(self, "config_file", resolve_config_file(self.config_file))
        if self.config_file is not None:
            load_config_file(self.config_file)  # fail now, naming the file, not at open

    def to_zenoh(self):
        """Build the ``zenoh.Config``: the file (if any), then our own keys, then ``extra``."""
        import zenoh

        cfg = load_config_file(self.config_file) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(bool(self.shared_memory)))
        cfg.insert_json5("transport/link/tx/lease", json.dumps(int(self.lease_ms)))
        for key, value in self.extra:
            cfg.insert_json5(key, json.dumps(value))
        return cfg

    def user(self) -> str | None:
        """The user name this session authenticates with (usrpwd), or ``None``."""
        return json.loads(self.to_zenoh().get_json("transport/auth/usrpwd/user"))


def open_session(config: SessionConfig):
    """Open a Zenoh session.

    Raises:
        SessionConnectError: a subclass that says why a session with ``connect`` endpoints could
            not join: RouterUnreachableError, TlsHandshakeError or AuthenticationError.
        ConfigError: any other failure to open (e.g. a listen endpoint already in use).
    """
    import zenoh

    from visfly_dist.protocol import shm
    from visfly_dist.protocol.diagnosis import diagnose_open_failure

    zcfg = config.to_zenoh()
    try:
        return shm.track(zenoh.open(zcfg))
    except Exception as exc:  # zenoh raises ZError
        where = (f"could not open a Zenoh {config.mode} session (connect={list(config.connect)}, "
                 f"listen={list(config.listen)}"
                 + (f", config {config.config_file!r}" if config.config_file else "") + ")")
        if config.connect:
            raise diagnose_open_failure(where, config.connect, zcfg, exc) from exc
        raise ConfigError(f"{where}: {exc}") from exc


TOKEN_CHECK_S = 1.0
"""How long one liveliness get for a token may take."""


def token_held(session, key: str, lease_ms: int) -> bool:
    """Whether a live session, reachable now, holds the liveliness token ``key``: one seen is looked at
    again for one lease (``lease_ms``) plus a margin, since a holder just killed or hung loses it
    within that time and one that is alive does not. Two holders starting at the same instant can
    both see none; the start-up checks that use this are for the common mistake."""
    deadline = time.monotonic() + lease_ms / 1000.0 + 0.5
    while any(r.ok is not None for r in session.liveliness().get(key, timeout=TOKEN_CHECK_S)):
        if time.monotonic() >= deadline:
            return True
        time.sleep(0.2)
    return False


def add_zenoh_config_argument(parser) -> None:
    """Add ``--zenoh-config FILE`` to an argparse parser (stored as ``args.zenoh_config``)."""
    parser.add_argument("--zenoh-config", default=None, metavar="FILE",
                        help="Zenoh JSON5 config (TLS, user/password, access control; see deploy/zenoh), applied "
                             f"under visfly-dist's own settings; default: ${ZENOH_CONFIG_ENV} if set")


def client_of(endpoints: Sequence[str], shared_memory: bool = True, lease_ms: int = 2000,
              config_file: str | None = None) -> SessionConfig:
    """A session that connects to given endpoints and listens nowhere."""
    return SessionConfig(mode="client", connect=tuple(endpoints), listen=(), shared_memory=shared_memory,
                         lease_ms=lease_ms, config_file=config_file)
