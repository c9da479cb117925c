"""Typed configuration of the aggregator: the worker pool and the scene set.

Each config has one ``validate()`` that reports every problem at once (raising ConfigError), so a
bad run fails before any process starts.
"""

from __future__ import annotations

import json
import os
import re
import secrets
from dataclasses import dataclass

from visfly_dist.errors import ConfigError
from visfly_dist.protocol.keys import check_chunk
from visfly_dist.protocol.session import load_config_file, resolve_config_file

BACKENDS = ("auto", "egl", "raycast")
LINK_PROTOCOLS = ("tcp", "udp", "tls", "quic", "ws", "unixsock-stream")
_ENDPOINT = re.compile(r"^(?P<proto>[a-z\-]+)/(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9_.\-]+):(?P<port>\d{1,5})$")


def endpoint_problem(endpoint: object) -> str | None:
    """Why ``endpoint`` is not a usable Zenoh endpoint (``None`` when it is)."""
    if not isinstance(endpoint, str):
        return f"endpoint {endpoint!r} must be a string like 'tcp/HOST:PORT'"
    if endpoint.startswith("unixsock-stream/"):
        return None
    m = _ENDPOINT.match(endpoint)
    if m is None:
        return f"endpoint {endpoint!r} must look like 'tcp/HOST:PORT' (e.g. 'tcp/127.0.0.1:7447')"
    if m["proto"] not in LINK_PROTOCOLS:
        return f"endpoint {endpoint!r}: protocol {m['proto']!r} must be one of {LINK_PROTOCOLS}"
    if not 0 <= int(m["port"]) <= 65535:
        return f"endpoint {endpoint!r}: port {m['port']} must be in [0, 65535]"
    return None


def new_run_id() -> str:
    """A random short run id (8 hex digits)."""
    return secrets.token_hex(4)


@dataclass
class PoolConfig:
    """Where the scene workers come from and how long to wait for them.

    Attributes:
        run_id: namespace of this run's keys; ``None`` draws a random short id.
        connect: router or peer endpoints to join; remote workers are discovered there, and local
            workers connect there too. Empty: the aggregator listens on loopback and local workers
            connect to it.
        listen: endpoints the aggregator listens on (peer mode) for workers to connect to.
        num_local_workers: workers spawned on this host by the aggregator (0 = only remote ones).
        backend: renderer of local workers: ``auto``, ``egl`` or ``raycast``.
        worker_threads: tracing threads of each local worker; ``None``: this host's usable cores
            (affinity and cgroup quota) divided among the local workers, so that together they
            never ask for more cores than the host has.
        shared_memory: let Zenoh carry large payloads in shared memory (same host only).
        local_channel: send local workers' requests over a private Unix socket pair instead of
            Zenoh queries (same messages; a tenth of the trainer's CPU per request). ``False``
            sends every request through Zenoh, as for remote workers.
        step_timeout_s: deadline of every request during a run (step, spawn sampling, health).
        startup_timeout_s: deadline for workers to come up and for a scene to load.
        scene_roots: folders that scene paths and globs are relative to (local workers get them).
        respawn: replace a local worker that dies.
        min_workers: live workers needed before ``start()`` returns.
        lease_ms: Zenoh link lease of local workers: a hung worker is declared dead after this.
        outage_limit_s: how long a run waits when no worker at all is reachable (the router or the
            network is down) before it fails with NoWorkersError.
        lost_request_limit: a local worker whose request got no answer but which answers a health
            probe is alive and is not killed; after this many such requests in a row, with none of
            their size answered by any worker in between, the run fails with LostRequestsError
            (the learner's side is broken: every replacement would time out the same way). A
            worker that alone reaches it while others answer is replaced.
        zenoh_config: a Zenoh JSON5 config file (TLS, user/password; see ``deploy/zenoh``) for the
            aggregator's session and its local workers; ``None`` uses ``$ZENOH_CONFIG`` when set.
            visfly-dist's own settings (mode, endpoints, shared memory, lease) override the file.
        log_dir: folder of the local workers' logs (``local-0.log``, ...), made if missing and kept
            after the run (``visfly-dist train`` uses the run folder's ``workers/``); ``None``: a
            temporary folder removed when the env closes.
    """

    run_id: str | None = None
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    num_local_workers: int = 2
    backend: str = "auto"
    worker_threads: int | None = None
    shared_memory: bool = True
    local_channel: bool = True
    step_timeout_s: float = 10.0
    startup_timeout_s: float = 60.0
    scene_roots: tuple[str, ...] = ()
    respawn: bool = True
    min_workers: int = 1
    lease_ms: int = 2000
    outage_limit_s: float = 120.0
    lost_request_limit: int = 3
    zenoh_config: str | None = None
    log_dir: str | None = None

    def __post_init__(self) -> None:
        self.connect = tuple(self.connect)
        self.listen = tuple(self.listen)
        self.scene_roots = tuple(str(r) for r in self.scene_roots)

    def problems(self) -> list[str]:
        """Every problem with this config, as messages (empty when valid)."""
        out: list[str] = []
        if self.run_id is not None:
            try:
                check_chunk(self.run_id, "run_id")
            except ConfigError as exc:
                out.append(str(exc))
        for ep in (*self.connect, *self.listen):
            problem = endpoint_problem(ep)
            if problem:
                out.append(problem)
        if self.worker_threads is not None and (not isinstance(self.worker_threads, int) or isinstance(self.worker_threads, bool)
                                                or self.worker_threads < 1):
            out.append(f"worker_threads={self.worker_threads!r} must be an int >= 1 or None (the host's cores shared)")
        if not isinstance(self.num_local_workers, int) or self.num_local_workers < 0:
            out.append(f"num_local_workers={self.num_local_workers!r} must be an int >= 0")
        elif self.num_local_workers == 0 and not self.connect and not self.listen:
            out.append("num_local_workers=0 (--workers 0) needs endpoints where remote workers can join: --connect "
                       "ENDPOINT (a router or a worker that listens), or listen endpoints (PoolConfig.listen)")
        if self.backend not in BACKENDS:
            out.append(f"backend={self.backend!r} must be one of {BACKENDS}")
        for name in ("step_timeout_s", "startup_timeout_s", "outage_limit_s"):
            value = getattr(self, name)
            if not isinstance(value, (int, float)) or not 0 < value <= 3600:
                out.append(f"{name}={value!r} must be a number of seconds in (0, 3600]")
        for root in self.scene_roots:
            if not os.path.isdir(root):
                out.append(f"scene root {root!r} is not a directory")
        if not isinstance(self.min_workers, int) or self.min_workers < 1:
            out.append(f"min_workers={self.min_workers!r} must be an int >= 1")
        if not isinstance(self.lost_request_limit, int) or isinstance(self.lost_request_limit, bool) \
                or self.lost_request_limit < 1:
            out.append(f"lost_request_limit={self.lost_request_limit!r} must be an int >= 1")
        if not isinstance(self.lease_ms, int) or not 200 <= self.lease_ms <= 600_000:
            out.append(f"lease_ms={self.lease_ms!r} must be an int in [200, 600000]")
        if self.log_dir is not None and (not isinstance(self.log_dir, str) or os.path.exists(self.log_dir)
                                         and not os.path.isdir(self.log_dir)):
            out.append(f"log_dir={self.log_dir!r} must be a folder (made if missing) or None")
        out += self._zenoh_config_problems()
        return out

    def _zenoh_config_problems(self) -> list[str]:
        path = resolve_config_file(self.zenoh_config)
        if path is None:
            return []
        try:
            zcfg = load_config_file(path)
        except ConfigError as exc:
            return [str(exc)]
        listens = not self.connect or bool(self.listen)  # peer mode: local workers connect to this process
        usrpwd = [json.loads(zcfg.get_json(f"transport/auth/usrpwd/{k}")) for k in ("user", "dictionary_file")]
        if listens and isinstance(self.num_local_workers, int) and self.num_local_workers > 0 and any(usrpwd):
            return [f"zenoh config {path!r} sets user/password authentication, but this pool's "
                    f"{self.num_local_workers} local worker(s) connect to the pool's own listener, which usrpwd "
                    "cannot admit; give connect endpoints of a router, or a config without transport/auth/usrpwd "
                    "(TLS alone is fine) for a local pool"]
        return []

    def validate(self) -> "PoolConfig":
        """Raise ConfigError listing every problem; return self when valid."""
        problems = self.problems()
        if problems:
            raise ConfigError("invalid PoolConfig: " + "; ".join(problems))
        return self


@dataclass
class SceneSetConfig:
    """Which scenes the agents fly in, and how often they change.

    Attributes:
        sources: scene paths, globs (relative to the pool's scene roots) or generator specs
            ``gen:KIND?k=v``; a spec without ``seed`` gets a fresh seed from ``seed`` each time
            it is used, so scenes differ.
        num_scenes: scenes loaded at once (slots).
        agents_per_scene: agents flying in each scene; agent ``i`` is in slot ``i // agents_per_scene``.
        swap_every_resets: replace a scene after this many episode resets in it (0 = never).
        shuffle: draw sources in a shuffled order (reshuffled each pass).
        seed: seed of the order and of the generator seeds.
    """

    sources: tuple[str, ...] = ("gen:garage-stones",)
    num_scenes: int = 1
    agents_per_scene: int = 1
    swap_every_resets: int = 0
    shuffle: bool = True
    seed: int = 0

    def __post_init__(self) -> None:
        if isinstance(self.sources, str):
            self.sources = (self.sources,)
        self.sources = tuple(self.sources)

    @property
    def num_agents(self) -> int:
        return self.num_scenes * self.agents_per_scene

    def problems(self) -> list[str]:
        """Every problem with this config, as messages (empty when valid)."""
        out: list[str] = []
        if not self.sources:
            out.append("sources is empty; give scene paths, globs or 'gen:KIND' specs")
        for s in self.sources:
            if not isinstance(s, str) or not s.strip():
                out.append(f"source {s!r} must be a non-empty string")
        for name, low in (("num_scenes", 1), ("agents_per_scene", 1), ("swap_every_resets", 0)):
            value = getattr(self, name)
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                out.append(f"{name}={value!r} must be an int >= {low}")
        if not isinstance(self.seed, int) or self.seed < 0:
            out.append(f"seed={self.seed!r} must be an int >= 0")
        return out

    def validate(self) -> "SceneSetConfig":
        """Raise ConfigError listing every problem; return self when valid."""
        problems = self.problems()
        if problems:
            raise ConfigError("invalid SceneSetConfig: " + "; ".join(problems))
        return self
