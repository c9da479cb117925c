"""Zenoh session configuration shared by workers, the aggregator and the router command.

Facts that shaped this (reference/zenoh-facts.md): always set ``listen/endpoints`` (a default peer
listens on every interface); turn multicast scouting off (we connect explicitly); the lease that
bounds hang detection is the one configured on the *monitored* side; shared memory is on by
default and only helps between processes on one host.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Sequence

from visfly_dist.errors import ConfigError

VALID_MODES = ("peer", "client", "router")
LOOPBACK_LISTEN = "tcp/127.0.0.1:0"


@dataclass(frozen=True)
class SessionConfig:
    """How a process joins the Zenoh network.

    Attributes:
        mode: ``peer``, ``client`` or ``router``.
        connect: endpoints to connect to, e.g. ``("tcp/10.0.0.5:7447",)``.
        listen: endpoints to listen on; defaults to loopback on an ephemeral port for peers.
        shared_memory: use Zenoh shared memory for large payloads (same-host only).
        lease_ms: link lease; a hung process is declared dead after about this long.
        extra: further ``key -> JSON value`` settings (TLS, auth), inserted verbatim.
        config_file: a Zenoh JSON5 config file (TLS, usrpwd, access control; see ``deploy/``)
            loaded first; the fields above are applied on top of it.
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
        if self.config_file is not None and not os.path.isfile(self.config_file):
            raise ConfigError(f"zenoh config file {self.config_file!r} does not exist")
        if not 200 <= int(self.lease_ms) <= 600_000:
            raise ConfigError(f"lease_ms={self.lease_ms} must be in [200, 600000]")

    def to_zenoh(self):
        """Build the ``zenoh.Config``."""
        import zenoh

        cfg = zenoh.Config.from_file(self.config_file) if self.config_file else zenoh.Config()
        cfg.insert_json5("mode", json.dumps(self.mode))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        cfg.insert_json5("connect/endpoints", json.dumps(list(self.connect)))
        cfg.insert_json5("listen/endpoints", json.dumps(list(self.listen)))
        cfg.insert_json5("transport/shared_memory/enabled", json.dumps(bool(self.shared_memory)))
        cfg.insert_json5("transport/link/tx/lease", json.dumps(int(self.lease_ms)))
        for key, value in self.extra:
            cfg.insert_json5(key, json.dumps(value))
        return cfg


def open_session(config: SessionConfig):
    """Open a Zenoh session; wraps connection failures in a ConfigError that names the endpoints."""
    import zenoh

    from visfly_dist.protocol import shm

    try:
        return shm.track(zenoh.open(config.to_zenoh()))
    except Exception as exc:  # zenoh raises ZError
        raise ConfigError(
            f"could not open a Zenoh {config.mode} session (connect={list(config.connect)}, "
            f"listen={list(config.listen)}): {exc}"
        ) from exc


def client_of(endpoints: Sequence[str], shared_memory: bool = True, lease_ms: int = 2000) -> SessionConfig:
    """A session that connects to given endpoints and listens nowhere."""
    return SessionConfig(mode="client", connect=tuple(endpoints), listen=(), shared_memory=shared_memory, lease_ms=lease_ms)
