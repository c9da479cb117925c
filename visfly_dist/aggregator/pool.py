"""The worker pool: the Zenoh session, who is alive, local worker processes, and fan-out requests.

Invariants (Zenoh 1.x behaviour, see docs/ARCHITECTURE.md):
- Liveliness is the source of truth for "alive": a worker is usable while its token exists and we
  have not banned it. A DELETE (process gone, or its lease expired when hung) removes it. A
  worker that misses a deadline is banned even if its token lingers; a later DELETE lifts the
  ban, so a worker restarted under the same id can come back. Each PUT bumps the worker's
  generation: a scene loaded at an older generation is gone from the worker and must be reloaded.
  Events queue on a channel that the calling thread drains: no callback thread, so no locks, and
  no hang at interpreter exit if a user forgets ``close()``.
- A local worker's requests go over its private channel (:mod:`visfly_dist.protocol.local_channel`,
  unless ``PoolConfig.local_channel`` is off): the same messages, the same :class:`Pending`, the same
  failures (its end closing is zero replies, an expired request a ``Timeout`` reply), at a tenth of
  a Zenoh query's CPU. Liveliness stays on Zenoh for every worker.
- Every other request is a session ``get`` with a timeout and ``ConsolidationMode.NONE`` (not a declared
  querier: a router's access control that allows the ``query`` message denies a querier's requests),
  answered through a callback that keeps the first reply's bytes and flags the request done (:class:`Pending`). A
  request never blocks the caller: :meth:`WorkerPool.send` returns at once, :meth:`WorkerPool.gather`
  waits for a batch (which costs the slowest worker, not the sum), and :meth:`WorkerPool.wait_any`
  waits for whichever of several batches is ready. Zero replies (worker gone, or it dropped the
  query) and a ``Timeout`` reply both mean the worker is failing; an error reply in our codec is
  the worker reporting a problem with the request.
- Local workers are spawned with subprocess (fork + exec, safe after the session opened) and are
  stopped on close, SIGTERM first, then SIGKILL after a grace period; the session is closed too.
- A ban is not for ever: a banned worker whose token stays is sent a health probe now and then
  (:meth:`WorkerPool.recheck_banned`, every :data:`RECHECK_S`, backing off), and one that answers
  is taken back, with a new generation. A request lost in a transient (the router restarting, a
  route not yet rebuilt) must not cost a healthy remote worker for the rest of the run: nothing
  else would lift its ban, since its token never goes.
- A local worker whose request got no answer is probed with a health request (small, so never in
  shared memory; :data:`PROBE_TIMEOUT_S`) before it is killed. One that answers is alive and kept;
  :mod:`.lost_requests` decides when such cases mean the learner's side is broken (the run fails
  with :class:`LostRequestsError` instead of replacing worker after worker) or that worker is.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
import subprocess
import tempfile
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Sequence

import zenoh

from visfly_dist.aggregator.config import PoolConfig
from visfly_dist.aggregator.launcher import LocalWorker, WorkerLaunchSpec, stop_workers
from visfly_dist.aggregator.lost_requests import LostRequests, Verdict
from visfly_dist.errors import ConfigError, LostRequestsError, NoWorkersError, ProtocolError, RemoteError
from visfly_dist.host import usable_cores
from visfly_dist.protocol import keys
from visfly_dist.protocol.codec import decode, encode
from visfly_dist.protocol.local_channel import ChannelClient, socket_pair
from visfly_dist.protocol.messages import Health
from visfly_dist.protocol.session import SessionConfig, open_session, token_held

log = logging.getLogger(__name__)

STOP_GRACE_S = 5.0
POLL_S = 0.02
LIVELINESS_QUEUE = 4096
EXIT_WAIT_S = 0.5
"""How long a dropped local worker's process is waited for, to tell how it ended (once per drop)."""
PROBE_TIMEOUT_S = 1.0  # a health reply takes milliseconds; a hung worker costs this much more before it is replaced
RECHECK_S = (1.0, 16.0)
"""First and longest wait between health probes of a banned worker whose token stays (doubling in between)."""


def free_port(host: str = "127.0.0.1") -> int:
    """A TCP port that was free a moment ago."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def _loopback(endpoint: str) -> str:
    for any_host in ("0.0.0.0", "[::]"):
        endpoint = endpoint.replace(f"/{any_host}:", "/127.0.0.1:")
    return endpoint


@dataclass
class Reply:
    """The outcome of one request to one worker: exactly one of message, error, failure is set.

    ``unanswered_bytes``: the size of the request when it got no answer at all (zero replies or
    ``Timeout``), else 0.
    """

    worker_id: str
    message: dict[str, Any] | None = None
    error: RemoteError | None = None
    failure: str | None = None
    unanswered_bytes: int = 0


class Pending:
    """One request in flight to one worker; Zenoh's callback thread fills it in.

    Only the first reply is kept (a worker answers once). ``done()`` turns true at that reply, or
    when the query finishes without one (dropped by the worker, or timed out); the pool's
    condition is notified then. The waiter wakes on the reply itself, not on the query's final
    message, which only follows it.
    """

    def __init__(self, worker_id: str, timeout_s: float, condition: threading.Condition,
                 request_bytes: int = 0) -> None:
        self.worker_id = worker_id
        self.timeout_s = timeout_s
        self.request_bytes = request_bytes
        self.sent_at = time.perf_counter()
        self.raw: tuple[bool, bytes] | None = None
        self._done = False  # set once, under the condition (a plain flag: an Event costs a lock per request)
        self._condition = condition

    def on_reply(self, reply: Any) -> None:
        """Zenoh's reply callback."""
        if self.raw is None:
            self.finish((True, reply.ok.payload.to_bytes()) if reply.ok is not None else (False, reply.err.payload.to_bytes()))

    def finish(self, raw: tuple[bool, bytes] | None) -> None:
        """Keep ``raw`` (``(ok, body)``, or ``None``: no reply) unless a reply came first, and flag the request done."""
        if self.raw is None:
            self.raw = raw
        self.on_done()

    def on_done(self) -> None:
        with self._condition:
            if self._done:  # the reply already finished it
                return
            self._done = True
            self._condition.notify_all()

    def done(self) -> bool:
        return self._done


@dataclass
class BatchTimings:
    """Where the time of one fan-out batch went, in seconds."""

    fanout_s: float = 0.0
    wait_s: float = 0.0
    decode_s: float = 0.0
    bytes_in: int = 0
    extra: dict[str, float] = field(default_factory=dict)

    def step_report(self, workers: list[dict], assemble_s: float, total_s: float) -> dict[str, float]:
        """A step's ``obs.timings``: ours, the slowest worker's own stages (``workers``: each reply's
        ``timings``), and the transport in between."""
        out = {"fanout_s": self.fanout_s, "wait_s": self.wait_s, "decode_s": self.decode_s,
               "assemble_s": assemble_s, **self.extra}
        own = set(out)
        worker_total = 0.0
        for wt in workers:  # one pass over each worker's map: its stages, and its total or their sum
            total, summed = None, 0.0
            for stage, value in wt.items():
                if not isinstance(value, (int, float)):
                    continue
                seconds = float(value)
                if stage == "total_s":
                    total = seconds
                    continue
                summed += seconds
                name = f"worker_{stage}" if stage in own else stage  # the worker's decode_s is not ours
                before = out.get(name, 0.0)
                out[name] = seconds if seconds > before else before
            worker_total = max(worker_total, summed if total is None else total)
        out["worker_total_s"] = worker_total
        out["transport_s"] = max(0.0, self.fanout_s + self.wait_s - worker_total)
        out["total_s"] = total_s
        return out


class WorkerPool:
    """Live workers of one run, and the one place that talks to them."""

    def __init__(self, config: PoolConfig, run_id: str) -> None:
        self.config = config
        self.run_id = run_id
        self._alive: set[str] = set()
        self._banned: set[str] = set()
        self._generation: dict[str, int] = {}
        self._local: dict[str, LocalWorker] = {}
        self._channels: dict[str, ChannelClient] = {}  # local worker -> its private request channel
        self._spawned = 0
        self._session: zenoh.Session | None = None
        self._subscriber: zenoh.Subscriber | None = None
        self._token: zenoh.LivelinessToken | None = None  # this run's trainer token (one trainer per run id)
        self._log_dir: str | None = None
        self._launch: WorkerLaunchSpec | None = None
        self._replies = threading.Condition()
        self._user: str | None = None
        self._lost = LostRequests(config.lost_request_limit)
        self._recheck: dict[str, tuple[float, float, Pending | None]] = {}  # banned -> (next probe, wait, probe in flight)
        self._rpc_keys: dict[str, str] = {}  # worker -> its checked rpc key expression

    # ----- lifecycle -------------------------------------------------------------------------

    def _session_config(self) -> tuple[SessionConfig, tuple[str, ...]]:
        """This process's session, and the endpoints local workers connect to."""
        cfg = self.config
        listen: tuple[str, ...]
        if cfg.connect and not cfg.listen:
            mode, listen, workers_connect = "client", (), cfg.connect
        else:
            mode = "peer"
            listen = cfg.listen or (f"tcp/127.0.0.1:{free_port()}",)
            workers_connect = cfg.connect or tuple(_loopback(ep) for ep in listen)
        session = SessionConfig(mode=mode, connect=cfg.connect, listen=listen, shared_memory=cfg.shared_memory,
                                lease_ms=cfg.lease_ms, config_file=cfg.zenoh_config)
        return session, workers_connect

    def open(self) -> None:
        """Open the session, watch liveliness, and spawn the local workers (not waiting for them)."""
        session_cfg, workers_connect = self._session_config()
        self._user = session_cfg.user()
        self._session = session = open_session(session_cfg)
        try:
            self._refuse_second_trainer(session)
            self._token = session.liveliness().declare_token(keys.trainer_alive(self.run_id))
            self._subscriber = session.liveliness().declare_subscriber(
                keys.workers_alive_pattern(self.run_id), zenoh.handlers.FifoChannel(LIVELINESS_QUEUE), history=True)
            if self.config.num_local_workers:
                self._log_dir = self._open_log_dir()
                self._launch = WorkerLaunchSpec(
                    run_id=self.run_id, connect=workers_connect, scene_roots=self.config.scene_roots,
                    backend=self.config.backend, shared_memory=self.config.shared_memory,
                    lease_ms=self.config.lease_ms, parent_pid=os.getpid(), zenoh_config=session_cfg.config_file,
                    threads=self.config.worker_threads or max(1, usable_cores() // self.config.num_local_workers))
                for _ in range(self.config.num_local_workers):
                    self.spawn_local()
        except BaseException:
            self.close()
            raise

    def _refuse_second_trainer(self, session: zenoh.Session) -> None:
        """ConfigError if another trainer holds this run's token, reachable now: two trainers on one
        run id would load their scenes under the same keys on the same workers, each rendering in
        the other's scenes without a word.

        See :func:`~visfly_dist.protocol.session.token_held`. Under a router's access control that
        does not grant the trainer token (``deploy/zenoh/router-acl.json5``: rule ``trainer-token``),
        nothing is seen: no check.
        """
        key = keys.trainer_alive(self.run_id)
        if token_held(session, key, self.config.lease_ms):
            raise ConfigError(
                f"run id {self.run_id!r} is in use by another trainer (its liveliness token {key} exists): two "
                "trainers on one run id would render in each other's scenes. Give this run its own --run-id "
                "(and start its workers with it), or stop the other run first")

    def close(self) -> None:
        """Stop local workers, undeclare, close the session. Idempotent.

        This process's Zenoh shared-memory files stay until it exits (:mod:`visfly_dist.protocol.shm`
        releases them then): Zenoh keeps some of them per process and reuses them in the next
        session, e.g. the next env of a sweep, whose workers could not map them once unlinked.
        """
        local, self._local = list(self._local.values()), {}
        stop_workers(local, STOP_GRACE_S)
        for wid in list(self._channels):
            self._close_channel(wid)
        if self._subscriber is not None:
            self._subscriber.undeclare()
            self._subscriber = None
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        if self._session is not None:
            self._session.close()
            self._session = None
        if self._log_dir is not None and self.config.log_dir is None:  # a folder of the user's stays
            shutil.rmtree(self._log_dir, ignore_errors=True)
        self._log_dir = None

    def _open_log_dir(self) -> str:
        """The local workers' log folder: the configured one (made if missing), else a temporary one."""
        if self.config.log_dir is None:
            return tempfile.mkdtemp(prefix=f"visfly-{self.run_id}-")
        try:
            os.makedirs(self.config.log_dir, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"pool log_dir={self.config.log_dir!r}: cannot make the workers' log folder ({exc})") from exc
        return self.config.log_dir

    # ----- liveliness ------------------------------------------------------------------------

    def _poll_liveliness(self) -> None:
        """Apply the liveliness events queued since the last poll (main thread only)."""
        if self._subscriber is None:
            return
        while (sample := self._subscriber.try_recv()) is not None:
            wid = keys.worker_id_from_alive_key(str(sample.key_expr))
            if sample.kind == zenoh.SampleKind.PUT:
                self._alive.add(wid)
                self._generation[wid] = self._generation.get(wid, 0) + 1
            else:
                self._alive.discard(wid)
                self._banned.discard(wid)
                self._recheck.pop(wid, None)

    def live_workers(self) -> list[str]:
        """Ids of the workers that are alive and not banned, sorted."""
        self._poll_liveliness()
        return sorted(self._alive - self._banned)

    def remote_live_workers(self) -> list[str]:
        """:meth:`live_workers` that this pool did not start (they outlive it), sorted."""
        return [w for w in self.live_workers() if w not in self._local]

    def recheck_banned(self) -> list[str]:
        """Probe banned workers whose token stays (never blocks); take back those that answered.

        Call it often (every step does): a probe is sent at most every :data:`RECHECK_S` per worker,
        the wait doubling after each unanswered one. A worker taken back gets a new generation, as
        if it had restarted: the caller treats what it held as gone. Returns the workers taken back.
        """
        if not self._banned:
            return []
        self._poll_liveliness()
        now, back = time.monotonic(), []
        for wid in sorted(self._banned & self._alive):
            due, wait, probe = self._recheck.get(wid, (now + RECHECK_S[0], RECHECK_S[0], None))
            if probe is not None and probe.done():
                if self.result(probe).message is not None:
                    log.warning("run %s: worker %s answers again; taking it back", self.run_id, wid)
                    self._banned.discard(wid)
                    self._recheck.pop(wid, None)
                    self._generation[wid] = self._generation.get(wid, 0) + 1
                    back.append(wid)
                    continue
                probe, wait = None, min(2 * wait, RECHECK_S[1])
                due = now + wait
            if probe is None and now >= due:
                (probe,) = self.send([(wid, Health().to_message())], PROBE_TIMEOUT_S)
            self._recheck[wid] = (due, wait, probe)
        return back

    def generation(self, worker_id: str) -> int:
        """How many times this worker's token appeared (a new value means it restarted)."""
        self._poll_liveliness()
        return self._generation.get(worker_id, 0)

    def generations(self, workers: Sequence[str]) -> dict[str, int]:
        """:meth:`generation` of each of ``workers`` (the liveliness events polled once)."""
        self._poll_liveliness()
        return {w: self._generation.get(w, 0) for w in workers}

    def wait_for(self, count: int, timeout_s: float, required: Sequence[str] = (),
                 remote_may_join: bool = False) -> list[str]:
        """Wait until ``count`` workers (and every running one of ``required``) are live.

        Returns the live workers when the condition holds, or when the timeout expires, or when no
        local worker is still starting and no remote one may join.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            if remote_may_join:
                self.respawn_exited()
            self.recheck_banned()  # after an outage, a worker may be banned for a request the outage lost
            live = set(self.live_workers())
            starting = [w for w in self._local.values() if w.worker_id not in live and w.running()]
            missing = [w for w in required if w not in live and w in self._local and self._local[w].running()]
            if len(live) >= count and not missing:
                break
            if time.monotonic() >= deadline or (not starting and not remote_may_join):
                break
            time.sleep(POLL_S)
        return sorted(live)

    # ----- local processes -------------------------------------------------------------------

    def spawn_local(self) -> str:
        """Start one more local worker; returns its id (it is live once its token appears)."""
        assert self._launch is not None and self._log_dir is not None, "no local workers configured"
        while f"local-{self._spawned}" in self._alive | self._banned:  # a remote worker may have taken it
            self._spawned += 1
        wid = f"local-{self._spawned}"
        self._spawned += 1
        log_path = f"{self._log_dir}/{wid}.log"
        if self.config.local_channel:
            ours, theirs = socket_pair()
            try:
                worker = LocalWorker(wid, self._launch.argv(wid, channel_fd=theirs.fileno()), log_path,
                                     pass_fds=(theirs.fileno(),))
            except BaseException:
                ours.close()
                raise
            finally:
                theirs.close()
            self._channels[wid] = ChannelClient(ours, wid)
        else:
            worker = LocalWorker(wid, self._launch.argv(wid), log_path)
        self._local[wid] = worker
        log.info("run %s: started local worker %s (pid %d)", self.run_id, wid, worker.pid)
        return wid

    @property
    def user(self) -> str | None:
        """The user name the session authenticated with (usrpwd), or ``None``."""
        return self._user

    def respawn_exited(self, min_age_s: float = 2.0) -> list[str]:
        """Replace local workers whose process exited (e.g. it could not reach the router).

        Each replacement is started at most once per ``min_age_s`` per worker slot, so an outage
        gives a bounded retry rate, and workers come back by themselves once the router does.
        """
        if not self.config.respawn or self._launch is None:
            return []
        out = []
        now = time.monotonic()
        for wid, worker in list(self._local.items()):
            if not worker.running() and now - worker.started_at >= min_age_s:
                log.warning("run %s: local worker %s left; starting a replacement%s", self.run_id, wid,
                            self._exit_note(wid))
                del self._local[wid]
                self._close_channel(wid)
                out.append(self.spawn_local())
        return out

    def _exit_note(self, worker_id: str) -> str:
        """``; it exited (CODE); the end of its log PATH: ...`` for a local worker whose process
        ended, else nothing: where to read why it died (the log is kept with a ``log_dir``)."""
        worker = self._local.get(worker_id)
        if worker is None:
            return ""
        try:  # a killed process can be reaped only once all its threads are gone, a moment after its channel closed
            worker.process.wait(timeout=EXIT_WAIT_S)
        except subprocess.TimeoutExpired:  # alive (hung): nothing to tell
            return ""
        return f"; it exited ({worker.process.returncode}); the end of its log {worker.log_path}: {worker.log_tail(400)!r}"

    def _close_channel(self, worker_id: str) -> None:
        channel = self._channels.pop(worker_id, None)
        if channel is not None:
            channel.close()

    def transport(self, worker_id: str) -> str:
        """How requests reach ``worker_id``: ``channel`` (a local worker's private channel) or ``zenoh``."""
        return "channel" if worker_id in self._channels else "zenoh"

    def is_local(self, worker_id: str) -> bool:
        return worker_id in self._local

    def local_pids(self) -> dict[str, int]:
        """Pid of each local worker process still tracked."""
        return {wid: w.pid for wid, w in self._local.items()}

    def startup_report(self) -> str:
        """Why local workers did not come up: each dead one's exit code and output tail."""
        lines = []
        for wid, w in self._local.items():
            if not w.running():
                lines.append(f"{wid} exited with {w.process.returncode}: {w.log_tail(800)!r}")
        return "; ".join(lines)

    def probe(self, worker_id: str, timeout_s: float = PROBE_TIMEOUT_S) -> bool:
        """Whether the worker answers a health request (a few bytes) within ``timeout_s``."""
        (reply,) = self.call([(worker_id, Health().to_message())], timeout_s)
        return reply.message is not None

    def dropped(self, worker_id: str) -> bool:
        """Whether ``worker_id`` is out of use already: banned, or neither alive nor one of our local workers."""
        self._poll_liveliness()
        return worker_id in self._banned or (worker_id not in self._alive and worker_id not in self._local)

    def drop(self, worker_id: str, reason: str, replace: bool = True, unanswered_bytes: int = 0) -> str | None:
        """Stop using a failing worker until its token reappears.

        A local one is killed and replaced (when ``respawn`` is on) only with ``replace``: the
        caller passes ``False`` when no other worker is reachable either, since then the network
        or the router is down and the worker itself is probably fine. Returns the replacement's id
        (not yet live), or ``None``.

        ``unanswered_bytes`` (:attr:`Reply.unanswered_bytes`): the failure was a request of that
        size without an answer. A local worker is then probed first (even without ``replace``: a
        worker that answers shows that the network is up), and kept (not banned, not killed;
        ``None`` is returned) if it answers, unless :class:`.LostRequests` says it is at fault. Raises LostRequestsError when lost-but-alive requests reach
        ``PoolConfig.lost_request_limit`` in a row with none of their size answered in between.
        """  # noqa: E501
        if unanswered_bytes and worker_id in self._local and self.probe(worker_id):  # reachable: no outage
            verdict = self._lost.lost_but_alive(worker_id, unanswered_bytes)
            if verdict is Verdict.FAIL:
                raise LostRequestsError(self.run_id, worker_id, unanswered_bytes, self._lost.count,
                                        self.config.step_timeout_s, reason, self.transport(worker_id))
            if verdict is Verdict.KEEP:
                log.warning("run %s: worker %s answers a health probe but not a request of %d bytes (%s); "
                            "not killing it (%d such case(s) in a row)", self.run_id, worker_id, unanswered_bytes,
                            reason, self._lost.count)
                return None
            reason += f"; it answers health probes but not requests of {unanswered_bytes} bytes, which others answer"
        self._lost.forget(worker_id)
        log.warning("run %s: dropping worker %s: %s%s", self.run_id, worker_id, reason, self._exit_note(worker_id))
        self._poll_liveliness()
        if worker_id in self._alive:  # a DELETE already seen needs no ban (and must not outlive a restart)
            self._banned.add(worker_id)
            self._recheck.pop(worker_id, None)  # the first probe of this ban comes RECHECK_S[0] from now
        if not replace or worker_id not in self._local:
            return None
        worker = self._local.pop(worker_id)
        worker.kill()
        self._close_channel(worker_id)
        if self.config.respawn:
            return self.spawn_local()
        return None

    def require_live(self) -> list[str]:
        """The live workers; NoWorkersError when there is none and none comes up.

        With none live, waits up to ``startup_timeout_s`` for a local worker that is starting or,
        when remote workers may join (connect or listen endpoints), for any worker.
        """
        live = self.live_workers()
        if live:
            return live
        remote = bool(self.config.connect or self.config.listen)
        if remote or any(w.running() for w in self._local.values()):
            live = self.wait_for(1, self.config.startup_timeout_s, remote_may_join=remote)
        if not live:
            where = f"connect={list(self.config.connect)}" if self.config.connect else "local workers only"
            detail = self.startup_report()
            raise NoWorkersError(
                f"run {self.run_id!r} has no live scene worker left ({where}, respawn={self.config.respawn})"
                + (f"; {detail}" if detail else "")
                + "; start workers with `visfly-dist worker --run-id "
                + f"{self.run_id} --connect ...` or enable respawn")
        return live

    # ----- requests --------------------------------------------------------------------------

    def send(self, requests: Sequence[tuple[str, dict[str, Any]]], timeout_s: float) -> list[Pending]:
        """Put every request on the wire and return at once, one :class:`Pending` each.

        Every request is encoded before the first is sent, so the requests leave back to back.
        """
        assert self._session is not None, "pool is not open"
        out = []
        for wid, payload in [(wid, encode(message)) for wid, message in requests]:
            pending = Pending(wid, timeout_s, self._replies, len(payload))
            channel = self._channels.get(wid)
            if channel is not None:
                channel.send(payload, pending, timeout_s)
                out.append(pending)
                continue
            key = self._rpc_keys.get(wid)
            if key is None:
                key = self._rpc_keys[wid] = keys.worker_rpc(self.run_id, wid)
            self._session.get(key, payload=payload, timeout=timeout_s,
                              consolidation=zenoh.ConsolidationMode.NONE,
                              handler=zenoh.handlers.Callback(pending.on_reply, pending.on_done, indirect=False))
            out.append(pending)
        return out

    def wait_any(self, batches: Sequence[Sequence[Pending]], timeout_s: float) -> int | None:
        """Index of the first batch whose requests are all done, waiting up to ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        with self._replies:
            while True:
                for i, batch in enumerate(batches):
                    if all(p.done() for p in batch):
                        return i
                left = deadline - time.monotonic()
                if left <= 0:
                    return None
                self._replies.wait(min(left, 0.5))

    def gather(self, pending: Sequence[Pending], timings: BatchTimings | None = None) -> list[Reply]:
        """Wait until every request of ``pending`` is done; one :class:`Reply` each, in order.

        Never raises for a failing worker (see :class:`Reply`); raises ProtocolError for a reply
        that is not a valid message (a bug on one side). A request's own timeout bounds the wait
        (plus a margin for the callback that reports it).
        """
        t1 = time.perf_counter()
        longest = max((p.timeout_s for p in pending), default=0.0)
        self.wait_any([pending], longest + 5.0)
        t2 = time.perf_counter()
        out = [self.result(p) for p in pending]
        if timings is not None:
            timings.wait_s += t2 - t1
            timings.decode_s += time.perf_counter() - t2
            timings.bytes_in += sum(len(p.raw[1]) for p in pending if p.raw is not None)
        return out

    def result(self, pending: Pending) -> Reply:
        """The outcome of a finished request (a request not done yet counts as timed out)."""
        reply = self._interpret(pending.worker_id, pending.raw if pending.done() else None, pending.timeout_s)
        if reply.failure is None:
            self._lost.answered(pending.worker_id, pending.request_bytes)
        else:
            reply.unanswered_bytes = pending.request_bytes
        return reply

    def call(self, requests: Sequence[tuple[str, dict[str, Any]]], timeout_s: float,
             timings: BatchTimings | None = None) -> list[Reply]:
        """Send every request at once, then gather one reply each (same order as ``requests``)."""
        t0 = time.perf_counter()
        pending = self.send(requests, timeout_s)
        if timings is not None:
            timings.fanout_s += time.perf_counter() - t0
        return self.gather(pending, timings)

    def _interpret(self, wid: str, raw: tuple[bool, bytes] | None, timeout_s: float) -> Reply:
        if raw is None:
            return Reply(wid, failure="no reply (worker gone or query dropped; under a router's access control, "
                                      "a denied query or reply looks the same)")
        ok, payload = raw
        if not ok and payload == b"Timeout":
            return Reply(wid, failure=f"no reply within {timeout_s:g} s (Timeout)")
        try:
            message = decode(payload)
        except ProtocolError as exc:
            raise ProtocolError(f"worker {wid!r} sent an invalid {'reply' if ok else 'error reply'}: {exc}") from None
        if not ok or message.get("type") == "error":
            return Reply(wid, error=RemoteError.from_reply(wid, message))
        return Reply(wid, message=message)
