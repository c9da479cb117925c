"""The tensor env: a batch of quadrotors in distributed scenes, stepped with torch tensors.

:class:`TensorEnv` owns the batched dynamics state (torch, differentiable) and drives the
aggregator, which renders and queries the scenes on the workers. Its interface is tensors only:
``reset_tensor``, ``step_tensor``, and ``send``/``recv`` for groups of agents. The SB3 ``VecEnv``
(:mod:`visfly_dist.client.sb3`) and the Gymnasium views (:mod:`visfly_dist.client.gym_view`) are
thin adapters on it, and :class:`~visfly_dist.client.env_base.DroneEnvBase` is the task base that
tasks subclass; trainers that want no numpy (``training/tensor_ppo.py``) call the core directly.

One step: actions -> ``Quadrotor.step`` -> poses -> ``Aggregator.observe`` -> images to torch (+
noise) -> ``get_success``, ``get_failure``, then ``get_reward`` (which may read ``self.success`` and
``self.failure``), then ``get_observation``. ``terminated = success | failure`` (``failure`` alone for
a task whose success is judged at its time limit); ``truncated`` = time limit, agents whose scene was
swapped, and lost agents held for longer than ``lost_hold_s``.
An agent whose worker failed (no fresh observation: ``lost``) is *held*: its step is undone (state
back to where it was, no reward, its episode neither advances nor ends, ``info["held"]``), as a
NEXT_STEP autoreset holds an agent, and it resumes with a fresh observation once its scene is served
again (a replacement worker takes it over in seconds). Done agents are
reset by masked selection and their fresh observation replaces the terminal one, which goes into
``info["terminal_observation"]``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, Literal, Sequence

import numpy as np
import torch
from gymnasium import spaces

from visfly_dist.aggregator import Aggregator
from visfly_dist.aggregator.assembler import empty_observation
from visfly_dist.client.buffer_pool import BufferPool
from visfly_dist.client.config import STATE_NOISE_KEY, EnvConfig
from visfly_dist.client.frame import SensorFrame, row_span
from visfly_dist.client.hook_checks import check_flags, check_observation, check_reward
from visfly_dist.client.lost_holds import LostHolds
from visfly_dist.client.noise import SensorNoise
from visfly_dist.dynamics import Quadrotor, QuadState, load_airframe
from visfly_dist.errors import ConfigError
from visfly_dist.protocol.cameras import CameraSpec

PROBE_CAMERA = CameraSpec(name="_probe", kind="depth", width=1, height=1)
"""Handed to the aggregator when a task has no camera (it needs one); its image is dropped."""

STATE_DIM = 13
"""``state_vector``: position (relative to an origin), velocity, quaternion wxyz, body rates."""


@dataclass(frozen=True)
class Spawn:
    """Where agents start: ``uniform`` over the box ``[a, b]`` or ``normal`` (mean ``a``, std ``b``),
    at least ``clearance`` metres from any obstacle."""

    distribution: str = "uniform"
    a: tuple[float, float, float] = (0.0, 0.0, 1.0)
    b: tuple[float, float, float] = (0.0, 0.0, 1.0)
    clearance: float = 0.5

    @classmethod
    def around(cls, center: Sequence[float], half_width: Sequence[float], clearance: float = 0.5) -> "Spawn":
        """Uniform in ``center ± half_width`` (plain floats: tasks ask on every reset)."""
        c, h = [float(x) for x in center], [float(x) for x in half_width]
        if len(c) != 3 or len(h) != 3:
            raise ConfigError(f"center={center!r} and half_width={half_width!r} must be 3 numbers each")
        return cls("uniform", (c[0] - h[0], c[1] - h[1], c[2] - h[2]), (c[0] + h[0], c[1] + h[1], c[2] + h[2]),
                   clearance)


@dataclass
class _InFlight:
    """A step that was sent and not yet taken in."""

    ticket: Any
    group: torch.Tensor
    members: np.ndarray
    held: torch.Tensor
    before: QuadState  # the state before this step: where an agent whose worker fails is held
    pending: QuadState | None  # the state after this step, whose group rows _finish takes in (None: already in place)
    full: bool
    spawn_agents: np.ndarray
    started: float
    physics_s: float
    sim_time: float


@dataclass
class StepResult:
    """What ``step_tensor`` returns (unpacks like a Gymnasium step).

    Attributes:
        observation: key -> ``(N, ...)`` tensors after auto-reset.
        reward: ``(N,)``, carries gradients when ``requires_grad``.
        terminated: ``(N,)`` bool, success or failure.
        truncated: ``(N,)`` bool, time limit, lost agent held too long, or scene swap (never also
            terminated).
        info: ``terminal_observation`` (observation before the reset, all rows), ``success``,
            ``collision``, ``out_of_bounds``, ``lost`` (truncated because its worker stayed away
            longer than ``lost_hold_s``), ``held`` (paused this step: its worker failed; no reward,
            its state and episode unchanged: not a transition to learn from), ``swapped``
            (``(N,)`` bool each), and ``episode_return`` / ``episode_length`` (``(N,)``,
            meaningful where done).
    """

    observation: dict[str, torch.Tensor]
    reward: torch.Tensor
    terminated: torch.Tensor
    truncated: torch.Tensor
    info: dict[str, Any]

    def __iter__(self):
        return iter((self.observation, self.reward, self.terminated, self.truncated, self.info))



class TensorEnv:
    """A batch of quadrotors in distributed scenes, stepped with tensors (the module docstring).

    Args:
        config: the settings (a task's own ``config_class``); validated before anything starts.

    Attributes available to the hooks:
        state: :class:`QuadState` of all agents.
        frame: :class:`SensorFrame` of the last observation (images, collision, nearest, ...); with
            ``send``/``recv`` its images are written in place: copy what a hook keeps across steps.
        bounds: ``(N, 2, 3)`` flight box of each agent's scene.
        actions: ``(N, 4)`` last actions in ``[-1, 1]``.
        episode_step: ``(N,)`` steps taken in the current episode.
        success, failure: ``(N,)`` bool of the current step (valid inside ``get_reward``).
        generator: the env's ``torch.Generator`` (noise, task randomness).
    """

    config_class: type[EnvConfig] = EnvConfig
    render_mode = None
    success_ends_episode = True
    """``False`` for a task whose success is judged when its time runs out (hover, tracking): such an
    episode is cut by the time limit (truncated), success or not, as the task could go on. Were a
    success to end it instead, a trainer would bootstrap a failed episode from the value of going on
    and not a successful one, and the agent would learn to fail the hold at the very end."""

    def __init__(self, config: EnvConfig | None = None) -> None:
        config = self.config_class() if config is None else config
        config.validate()
        self.config = config
        self.device = torch.device(config.device)
        self.cameras: tuple[CameraSpec, ...] = tuple(config.cameras)
        n = config.num_envs
        self.quad = Quadrotor(config.dynamics_config(), load_airframe(config.airframe), num_agents=n, device=self.device)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(config.seed)
        self._camera_names = [c.name for c in self.cameras]
        self._image_noise = {c.name: SensorNoise(config.noise.get(c.name, ()), c.kind, c.far) for c in self.cameras}
        self._state_noise = SensorNoise(config.noise.get(STATE_NOISE_KEY, ()), STATE_NOISE_KEY)
        self._closed = True
        self._in_flight: list[_InFlight] = []  # before start: close() reads it should the start fail
        self._init_views(n, spaces.Dict(self.observation_space_dict()), spaces.Box(-1.0, 1.0, (4,), np.float32))
        self.aggregator = Aggregator(pool=config.pool, scenes=config.scene_set(), cameras=list(self.cameras or (PROBE_CAMERA,)),
                                     drone_radius=config.drone_radius, multi_agent=config.multi_agent,
                                     search_radius=config.search_radius, seed=config.seed)
        self._closed = False
        try:
            self.aggregator.start()
        except BaseException:
            self.close()
            raise
        self.agent_scene = torch.as_tensor(np.asarray(self.aggregator.agent_scene), device=self.device)
        self.bounds = self._agent_bounds()
        zeros = torch.zeros(n, device=self.device)
        self.episode_step = zeros.long()
        self.episode_return = zeros.clone()
        self.success = zeros.bool()
        self.failure = zeros.bool()
        self.actions = torch.zeros(n, 4, device=self.device)
        self.state: QuadState = self.quad.initial_state(torch.zeros(n, 3, device=self.device))
        self.frame: SensorFrame | None = None
        self._image_buffers = BufferPool()  # merged images of reset steps, reused once nobody holds them
        self._own_frame: SensorFrame | None = None  # a frame whose images only the env refers to (see _merge)
        self.frame_timings: dict[str, float] = {}
        self.step_timings: dict[str, float] = {}
        # Each agent's next start, drawn ahead so its first view travels with an earlier step.
        self._next_pos = torch.zeros(n, 3, device=self.device)
        self._prepared = np.zeros(n, dtype=bool)
        self._prepared_obs = empty_observation(self.aggregator.cameras, n)
        self._switched = np.zeros(n, dtype=bool)  # scene changed mid-episode, not yet taken in
        self._next_scene = np.zeros(n, dtype=bool)  # next episode in a new scene, start not yet redrawn
        self.step_mask = torch.ones(n, dtype=torch.bool, device=self.device)
        self.agents_per_scene = config.agents_per_scene
        self.sim_time = 0.0   # s: where the moving obstacles are for the group being stepped or taken in
        self._steps_sent = np.zeros(n, dtype=np.int64)  # per agent, since the last reseed
        self._everyone = torch.ones(n, dtype=torch.bool, device=self.device)  # read only: the group of a plain step
        self._everyone_np = _read_only(np.ones(n, dtype=bool))  # its members and agents, as _send needs them
        self._all_agents = _read_only(np.arange(n))
        self._no_one = torch.zeros(n, dtype=torch.bool, device=self.device)  # read only: nobody held
        self._oob: tuple[QuadState, torch.Tensor, torch.Tensor] | None = None  # out_of_bounds of one state
        self._box: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # bounds, its lower and upper corners
        self._lost_holds = LostHolds(n, config.lost_hold_s)  # agents whose worker failed wait, up to a bound
        self._hooks_checked = False  # set once the first step's hook outputs passed client.hook_checks

    # ----- task hooks ---------------------------------------------------------------------------

    def get_observation(self) -> dict[str, torch.Tensor]:
        """Observation entries, ``(N, ...)`` each, keys as in ``observation_space_dict``."""
        raise NotImplementedError

    def get_reward(self) -> torch.Tensor:
        """Reward of this step, ``(N,)`` float."""
        raise NotImplementedError

    def get_success(self) -> torch.Tensor:
        """``(N,)`` bool: the agent reached its goal this step (terminates the episode unless
        :attr:`success_ends_episode` is ``False``)."""
        raise NotImplementedError

    def get_failure(self) -> torch.Tensor:
        """``(N,)`` bool: the episode failed (default: collision, inside an obstacle, out of bounds)."""
        frame = self.frame
        assert frame is not None, "the task hooks run once the env has observed"
        return frame.collision | frame.inside | self.out_of_bounds()

    def observation_space_dict(self) -> dict[str, spaces.Space]:
        """Observation spaces: ``state`` (13,) and one image entry per camera; tasks extend it."""
        out: dict[str, spaces.Space] = {"state": spaces.Box(-np.inf, np.inf, (STATE_DIM,), np.float32)}
        for cam in self.cameras:
            out[cam.name] = camera_space(cam)
        return out

    def spawn_distribution(self) -> Spawn:
        """Where agents start (the default: 1 m above the origin)."""
        return Spawn()

    def spawn_positions(self, idx: torch.Tensor) -> torch.Tensor:
        """Start positions ``(k, 3)`` of agents ``idx``, sampled clear of obstacles by the workers."""
        spawn = self.spawn_distribution()
        pos = self.aggregator.sample_spawn(idx.cpu().numpy(), spawn.distribution, spawn.a, spawn.b, spawn.clearance)
        return torch.as_tensor(np.asarray(pos, dtype=np.float32), device=self.device)

    def spawn_around(self, idx: torch.Tensor, centres: np.ndarray, half_width: Sequence[float],
                     clearance: float) -> torch.Tensor:
        """Start positions ``(k, 3)`` of agents ``idx``, uniform in ``centres[i] ± half_width``.

        For tasks whose start box follows a per-scene point (a target, a pad, a lane): one pooled
        draw per distinct centre.
        """
        centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        out = torch.zeros(len(idx), 3, device=self.device)
        for centre in np.unique(centres, axis=0):
            rows = np.flatnonzero((centres == centre).all(axis=1))
            spawn = Spawn.around(centre, half_width, clearance)
            pos = self.aggregator.sample_spawn(idx[rows].cpu().numpy(), spawn.distribution, spawn.a, spawn.b,
                                               spawn.clearance)
            out[torch.as_tensor(rows)] = torch.as_tensor(np.asarray(pos), dtype=torch.float32, device=self.device)
        return out

    def reset_agents_hook(self, idx: torch.Tensor) -> None:
        """Called after agents ``idx`` got their new state, before their first observation."""

    def update_task_state(self) -> None:
        """Advance the task's own per-step state (previous distances, gate counters, ...).

        Called exactly once per step, after ``get_success``, ``get_failure``, ``get_reward`` and
        ``get_observation``: those hooks must be pure (calling one twice gives the same result and
        changes nothing), so that state advances in this one place. With :meth:`send`/:meth:`recv`
        only the agents of ``self.step_mask`` moved: the others' ``state`` is the one of their last
        finished step (a group still in flight takes its new state when :meth:`recv` returns it), so
        state derived from it is unchanged for them, and event counters must advance only where
        ``step_mask`` is set.
        """

    def precompute(self) -> None:
        """Hook: compute, while the workers render, what this step's task hooks need from the state
        alone, into caches keyed on the state object (so the hooks stay pure and give the same
        result without it). Called once the step's request is on the wire."""
        TensorEnv.out_of_bounds(self)  # the scene-box part, which tasks extend

    # ----- helpers for tasks --------------------------------------------------------------------

    def state_vector(self, origin: torch.Tensor | None = None) -> torch.Tensor:
        """``(N, 13)``: position minus ``origin`` (m), velocity (m/s), quaternion wxyz, body rates (rad/s)."""
        s = self.state
        pos = s.pos if origin is None else s.pos - origin
        return torch.cat((pos, s.vel, s.quat, s.omega), dim=1)

    def out_of_bounds(self) -> torch.Tensor:
        """``(N,)`` bool: the agent left its scene's flight box."""
        state, bounds = self.state, self.bounds
        if self._oob is None or self._oob[0] is not state or self._oob[1] is not bounds:
            if self._box is None or self._box[0] is not bounds:  # contiguous corners: compares at half the cost
                self._box = (bounds, bounds[:, 0].contiguous(), bounds[:, 1].contiguous())
            pos = state.pos.detach()
            self._oob = (state, bounds, ((pos < self._box[1]) | (pos > self._box[2])).any(dim=1))
        return self._oob[2]

    def hold_observations(self, count: int) -> None:
        """Say that the caller keeps up to ``count`` of the observations it was handed at once (a
        trainer keeping a rollout's images without copying them): the workers' image segments those
        are views of are then offered again once let go, instead of new ones being made every step."""
        self.aggregator.hold_observations(count)

    def scene_metadata(self, agent: int) -> dict[str, Any]:
        """Metadata of the scene agent ``agent`` flies in (goal regions and the like)."""
        return self.aggregator.agent_metadata(int(agent))

    # ----- core step ----------------------------------------------------------------------------

    def step_tensor(self, actions: torch.Tensor | np.ndarray, hold: torch.Tensor | None = None,
                    terminal: Literal["all", "ended"] = "all") -> StepResult:
        """Advance every agent one control step, keeping torch tensors (and gradients).

        Args:
            actions: ``(N, 4)`` in ``[-1, 1]``; values outside are clipped.
            hold: ``(N,)`` bool: agents that stay where they are this step (their action is ignored,
                their reward is 0 and their episode neither advances nor ends). Gymnasium's
                NEXT_STEP autoreset uses it for the step that returns a reset agent's first view.
            terminal: what ``info["terminal_observation"]`` holds: every agent's row (``"all"``, as
                SB3 reads it), or only the rows of the agents whose episode ended this step, in
                index order (``"ended"``): the reset then writes their new first views into the
                step's images in place instead of copying every image (a trainer's fast path).
        """
        self._check_open()
        self._check_no_flight("step()")
        if terminal not in ("all", "ended"):
            raise ConfigError(f"terminal={terminal!r} must be 'all' or 'ended'")
        if self.frame is None:
            self._first_reset()
        with torch.set_grad_enabled(self.config.requires_grad):
            return self._step(actions, hold, terminal)

    def _step(self, actions: torch.Tensor | np.ndarray, hold: torch.Tensor | None = None,
              terminal: Literal["all", "ended"] = "all") -> StepResult:
        return self._finish(self._send(self._actions(actions, self.num_envs), self._everyone, hold), terminal=terminal)

    def _actions(self, actions: torch.Tensor | np.ndarray, k: int) -> torch.Tensor:
        actions = torch.as_tensor(actions, dtype=torch.float32, device=self.device)
        if actions.shape != (k, 4):
            raise ConfigError(f"actions of shape {tuple(actions.shape)} must be ({k}, 4)")
        return actions.clamp(-1.0, 1.0)

    def _send(self, actions: torch.Tensor, group: torch.Tensor, hold: torch.Tensor | None) -> _InFlight:
        """Advance the agents of ``group`` (``(N,)`` bool) and put their observation on the wire."""
        t0 = time.perf_counter()
        everyone = group is self._everyone
        members = self._everyone_np if everyone else group.cpu().numpy()
        agents = self._all_agents if everyone else np.flatnonzero(members)
        held = self._no_one if hold is None else torch.as_tensor(hold, dtype=torch.bool, device=self.device)
        full = len(agents) == self.num_envs and hold is None  # every agent moves: no masking needed
        before = self.state
        stepped = self.quad.step(self.state, actions)
        alone = len(agents) == self.num_envs  # no other group can be in flight: in place now
        # A group's new state joins self.state when its step is taken in (_finish): until then the task
        # hooks of other groups' steps see its agents as they were at their last finished step. With
        # no one held, _finish takes the group's rows of ``stepped`` (its other rows are never read).
        if full or (not alone and hold is None) or bool((group & ~held).all()):
            after = stepped
        else:
            after = QuadState.where(group & ~held, stepped, self.state)
        pending = None if alone else after
        if alone:
            self.state = after
        self.actions = actions if alone else torch.where(group[:, None], actions, self.actions)
        t1 = time.perf_counter()
        spawn_agents = np.flatnonzero(~self._prepared if everyone else ~self._prepared & members)
        poses = after.pose().detach().cpu().numpy()
        # groups stepped in turn share one clock: a group's k-th step happens at k * ctrl_dt
        self._steps_sent[agents] += 1
        sim_time = int(self._steps_sent[agents].max()) * self.config.ctrl_dt if len(agents) else self.sim_time
        self.sim_time = sim_time
        ticket = self.aggregator.submit(poses if len(agents) == self.num_envs else poses[agents], agents=agents,
                                        spawn_poses=self._start_poses(spawn_agents), spawn_agents=spawn_agents,
                                        sim_time=sim_time)
        if alone:
            self.precompute()  # the workers render meanwhile
        return _InFlight(ticket, group, members, held, before, pending, full, spawn_agents, t0, t1 - t0, sim_time)

    def _finish(self, flight: _InFlight, ids: torch.Tensor | None = None,
                terminal: Literal["all", "ended"] = "all") -> StepResult:
        """Take in a sent step: task hooks, terminations, resets. Tensors over all N agents; only the
        rows of ``flight.group`` are this step's (the others are zero / False).

        ``ids``: the group's agents (``recv``): only their rows are returned, never the frame's own
        images (which are merged into in place, :meth:`_merge`): an image the task passes through
        is handed out as the group's fresh rows (its reset agents' first views written into them),
        the other entries as their rows (views for a consecutive group, :meth:`_group_rows`).
        ``terminal``: see :meth:`step_tensor` and :meth:`recv`."""
        t0 = time.perf_counter()
        self.sim_time = flight.sim_time  # the task hooks see this group's time
        obs, spawn_obs = self.aggregator.collect(flight.ticket)
        if len(flight.spawn_agents):
            ok = ~spawn_obs.lost
            self._store_prepared(spawn_obs, np.flatnonzero(ok), flight.spawn_agents[ok])
        self.frame_timings = dict(obs.timings)
        rows = self._frame(obs)
        everyone = len(flight.ticket.agents) == self.num_envs
        if everyone or self.frame is None:
            self.frame = rows
        else:
            self.frame = self._merge(flight.group.nonzero().squeeze(1) if ids is None else ids, rows, own=ids is not None)
        t1 = time.perf_counter()
        group, full, held = flight.group, flight.full, flight.held
        if flight.pending is not None:
            self.state = QuadState.where(group, flight.pending, self.state)
        paused = self._hold_lost(obs.lost, flight)
        if paused is not None:  # their step is undone: they wait where they were for their worker
            self.state = QuadState.where(paused, flight.before, self.state)
            full, held = False, held | paused
        # with every agent moving (a plain step) the group and hold masks select everything: skip them
        live = group if full else group & ~held
        self.step_mask = live
        self.episode_step = self.episode_step + 1 if full else self.episode_step + live.long()
        lost = self.frame.lost if full else self.frame.lost & live  # lost and not held: cut now
        any_lost = bool(obs.lost.any())  # else ``lost`` is all False (the group's rows are obs's): no masking
        success = self.get_success()
        checking = not self._hooks_checked
        if checking:
            check_flags("get_success", success, self.num_envs)
        if any_lost:
            success = success & ~lost
        self.success = success if full else success & live
        failure = self.get_failure()
        if checking:
            check_flags("get_failure", failure, self.num_envs)
        failure = failure & ~self.success
        if any_lost:
            failure = failure & ~lost
        self.failure = failure if full else failure & live
        reward = self.get_reward()
        if checking:
            check_reward(reward, self.num_envs)
        if not full and not bool(live.all()):
            reward = torch.where(live, reward, torch.zeros_like(reward))
        self.episode_return = self.episode_return + reward.detach()
        observation = self._observation()
        self.update_task_state()
        self._hooks_checked = True  # every hook's output had its shape checked once

        terminated = self.success | self.failure if self.success_ends_episode else self.failure
        timed_out = self.episode_step >= self.config.max_episode_steps
        truncated = ((timed_out | lost) if any_lost else timed_out) & ~terminated
        terminated, truncated = self.expand_resets(terminated, truncated if full else truncated & live)
        swapped = self._take_swapped(flight.members)
        if swapped is None:
            swapped = self._no_one
        else:
            swapped = swapped & ~terminated
            truncated = truncated | swapped
        collision, out_of_bounds = self.frame.collision, self.out_of_bounds()
        info: dict[str, Any] = {"terminal_observation": observation, "success": self.success, "lost": lost,
                                "held": self._no_one if paused is None else paused,
                                "collision": collision if full else collision & group,
                                "out_of_bounds": out_of_bounds if full else out_of_bounds & group,
                                "swapped": swapped, "episode_return": self.episode_return,
                                "episode_length": self.episode_step}
        done = terminated | truncated
        reset = bool(done.any())
        ended = done.nonzero().squeeze(1) if reset else None
        # the terminal rows handed out are taken before a reset writes the new rows into the frame's images
        ended_rows = None
        if ids is not None and ended is not None:
            ended_rows = _rows(observation, ids if terminal == "all" else ended)
        elif terminal == "ended":  # no episode ended: no rows (views, no copy)
            ended_rows = {k: v[:0] for k, v in observation.items()} if ended is None else _rows(observation, ended)
            info["terminal_observation"] = ended_rows
        if ended is not None:  # the frame of this step is the env's alone until it is returned: written into in place
            observation = self._reset_agents(done, observation, ended=True, own=ids is not None,
                                             fresh=ids is None and terminal == "ended", idx=ended)
        self.step_timings = {**self.frame_timings, "physics_s": flight.physics_s,
                             "observe_s": self.frame_timings.get("total_s", t1 - t0),
                             "total_s": time.perf_counter() - flight.started}
        if ids is None:
            return StepResult(observation, reward, terminated, truncated, info)
        span = row_span(ids) or ids
        picked = self._group_rows(observation, rows, ids, span, ended)
        # this step's tensors: the env replaces them next step, never writes into them, so a view is safe
        picked_info: dict[str, Any] = {k: _pick(v, span) for k, v in info.items() if k != "terminal_observation"}
        # no reset with terminal "all": the same rows ("ended" always set ended_rows above)
        picked_info["terminal_observation"] = dict(picked) if ended_rows is None else ended_rows
        return StepResult(picked, _pick(reward, span), _pick(terminated, span), _pick(truncated, span), picked_info)

    def _group_rows(self, observation: dict[str, torch.Tensor], fresh: SensorFrame, ids: torch.Tensor,
                    span: slice | torch.Tensor, ended: torch.Tensor | None) -> dict[str, torch.Tensor]:
        """Rows ``ids`` (``span``: the same, a slice where they are consecutive) of ``observation``.
        An image the task passes through (the frame's own, written into by later steps) is not
        copied out of the frame: ``fresh``, the group's rows this step brought (not handed out yet,
        nothing else refers to them), holds the same, but for the reset agents' first views, which
        are written into it. Every other entry is this step's own: its rows (a view where they are
        consecutive)."""
        frame = self.frame
        assert frame is not None, "a group's step follows the first observation"
        picked = {}
        for k, v in observation.items():
            image = fresh.images.get(k)
            if image is None or v is not frame.images.get(k):
                picked[k] = v.index_select(0, ids) if any(v is i for i in frame.images.values()) else _pick(v, span)
                continue
            if ended is not None:
                image.index_copy_(0, torch.searchsorted(ids, ended), v.index_select(0, ended))
            picked[k] = image
        return picked

    def _hold_lost(self, lost_rows: np.ndarray, flight: _InFlight) -> torch.Tensor | None:
        """``(N,)`` bool: the agents of this step with no fresh observation that are held (``None``
        when there are none). An agent is held from the first step its worker fails to answer for
        up to ``lost_hold_s``; after that its episode is cut (truncated, ``lost``) once, and the
        next one is held again if the worker is still away."""
        agents = flight.ticket.agents
        if not lost_rows.any():
            self._lost_holds.served(agents)
            return None
        lost = np.zeros(self.num_envs, dtype=bool)
        lost[agents] = lost_rows
        lost &= ~flight.held.cpu().numpy()  # an agent held by the caller stays as it is asked
        paused = self._lost_holds.update(flight.members, lost, time.monotonic())
        return torch.as_tensor(paused, device=self.device) if paused.any() else None

    # ----- asynchronous stepping (EnvPool-style) --------------------------------------------------

    def send(self, actions: torch.Tensor | np.ndarray, env_ids: torch.Tensor | np.ndarray) -> None:
        """Step the agents ``env_ids`` with ``actions`` (``(k, 4)``) and return at once.

        Several groups may be in flight (disjoint ``env_ids``); :meth:`recv` returns whichever is
        ready first. Meanwhile the caller can compute the next actions of another group, so the
        learner and the scene workers work at the same time (and a network round trip is hidden).
        In multi-agent scenes a group must hold whole teams (drones see those of their request).
        """
        self._check_open()
        if self.frame is None:
            self._first_reset()
        given = np.asarray(env_ids.cpu() if isinstance(env_ids, torch.Tensor) else env_ids).reshape(-1)
        members = np.zeros(self.num_envs, dtype=bool)  # on the host: these checks are a few NumPy calls
        in_range = given.size and np.issubdtype(given.dtype, np.integer) and 0 <= given.min() and given.max() < self.num_envs
        if in_range:
            members[given] = True
        if not in_range or int(members.sum()) != len(given):  # out of range, not indices, none or repeated
            raise ConfigError(f"env_ids must be distinct indices in [0, {self.num_envs}), got {given.tolist()[:10]}")
        if any(f.members[given].any() for f in self._in_flight):
            raise ConfigError("send(): some env_ids are still in flight; recv() them first")
        if self.agents_per_scene > 1 and self.config.multi_agent:
            teams = members.reshape(-1, self.agents_per_scene)
            if (teams.any(axis=1) & ~teams.all(axis=1)).any():
                raise ConfigError(f"send(): env_ids must hold whole teams of {self.agents_per_scene} agents")
        group = torch.from_numpy(members).to(self.device)
        ids = torch.as_tensor(given, dtype=torch.long, device=self.device)
        full = self.actions.detach().clone()
        full[ids] = self._actions(actions, len(ids))
        with torch.set_grad_enabled(self.config.requires_grad):
            self._in_flight.append(self._send(full, group, None))

    def recv(self, timeout_s: float | None = None,
             terminal: Literal["all", "ended"] = "all") -> tuple[StepResult, torch.Tensor]:
        """The step of the first group whose observations are in: its rows only, and its env ids.

        ``terminal``: what ``info["terminal_observation"]`` holds when an episode of the group ended:
        every row of the group (``"all"``), or only the rows of the agents whose episode ended, in
        index order (``"ended"``: a trainer's fast path, no copy of the group's other images).

        Raises:
            ConfigError: nothing was sent, or ``terminal`` is neither.
        """
        self._check_open()
        if not self._in_flight:
            raise ConfigError("recv() without a send() in flight")
        if terminal not in ("all", "ended"):
            raise ConfigError(f"terminal={terminal!r} must be 'all' or 'ended'")
        i = self.aggregator.wait_any([f.ticket for f in self._in_flight], timeout_s)
        flight = self._in_flight.pop(0 if i is None else i)  # on timeout, the oldest (its collect is bounded)
        ids = flight.group.nonzero().squeeze(1)
        with torch.set_grad_enabled(self.config.requires_grad):
            return self._finish(flight, ids, terminal), ids

    def _take_swapped(self, members: np.ndarray) -> torch.Tensor | None:
        """``(N,)`` bool: agents of ``members`` whose scene changed under their episode (None if
        none; a swap takes over at episode ends, so only a worker lost mid-swap does that); they
        start their next episode in the new scene. Agents of ``members`` whose next episode will
        be in a swapped-in scene get their next start drawn there."""
        self._redraw_for_new_scene(members)
        self._switched |= self.aggregator.take_switched()
        if not self._switched.any():
            return None
        swapped = self._switched & members
        if not swapped.any():
            return None
        self._switched &= ~members
        self.bounds = self._agent_bounds()
        self._prepared &= ~swapped  # their next start lies in the new scene
        swapped = torch.as_tensor(swapped, device=self.device)
        self._draw_next_starts(swapped.nonzero().squeeze(1))
        return swapped

    def _redraw_for_new_scene(self, agents: np.ndarray) -> None:
        """Draw again the next start of those of ``agents`` (``(N,)`` bool, or indices) whose next
        episode will be in a swap armed since it was drawn: it lies in the new scene."""
        self._next_scene |= self.aggregator.take_next_scene()
        if not self._next_scene.any():  # most steps: no swap armed
            return
        redraw = np.zeros_like(self._next_scene)
        redraw[agents] = self._next_scene[agents]
        if redraw.any():
            self._next_scene &= ~redraw
            self._draw_next_starts(torch.as_tensor(np.flatnonzero(redraw), device=self.device))

    def expand_resets(self, terminated: torch.Tensor, truncated: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Hook: end further episodes because of these (teams end together in multi-agent tasks)."""
        return terminated, truncated

    def _frame(self, obs: Any) -> SensorFrame:
        return SensorFrame.from_observation(obs, self.device, self._image_noise, self.generator, cameras=self._camera_names)

    def _store_prepared(self, obs: Any, rows: np.ndarray, agents: np.ndarray) -> None:
        store = self._prepared_obs
        for name, image in store.images.items():
            image[agents] = obs.images[name][rows]
        for key in ("collision", "inside", "nearest", "distance", "lost"):
            getattr(store, key)[agents] = getattr(obs, key)[rows]
        self._prepared[agents] = True

    def _draw_next_starts(self, idx: torch.Tensor, idx_np: np.ndarray | None = None) -> None:
        """Draw the start of the next episode of agents ``idx`` (its view is rendered with the next
        step); ``idx_np``: the same indices in numpy, if the caller has them."""
        if len(idx) == 0:
            return
        self._next_pos.index_copy_(0, idx, self.spawn_positions(idx).detach().to(self._next_pos.dtype))
        self._prepared[idx.cpu().numpy() if idx_np is None else idx_np] = False

    def _start_poses(self, agents: np.ndarray) -> np.ndarray:
        """``(k, 7)`` poses of the agents' next starts: at ``_next_pos``, level and at rest, as
        ``Quadrotor.initial_state`` puts them."""
        poses = np.zeros((len(agents), 7), dtype=np.float32)
        if len(agents) == 0:
            return poses
        poses[:, :3] = self._next_pos[torch.as_tensor(agents, dtype=torch.long)].cpu().numpy()
        poses[:, 3] = 1.0
        return poses

    def _observation(self) -> dict[str, torch.Tensor]:
        obs = self.get_observation()
        if not self._hooks_checked:
            check_observation(obs, self.observation_space, self.num_envs)
        if self._state_noise and "state" in obs:
            obs = {**obs, "state": self._state_noise(obs["state"], self.generator)}
        return obs

    def _reset_agents(self, mask: torch.Tensor, observation: dict[str, torch.Tensor] | None, ended: bool = False,
                      own: bool = False, fresh: bool = False, idx: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        """Reset the agents in ``mask`` to their drawn next start; return ``observation`` with their
        rows replaced by the first view of their new episode (rendered ahead, or now if it is not).
        ``ended``: their episodes ended (they count towards scene swaps; a reset asked for does not).
        ``own``: neither ``observation`` nor the result is handed out whole (:meth:`_merge`).
        ``fresh``: ``observation``'s images are this step's, not handed out yet (:meth:`_merge`).
        ``idx``: ``mask``'s agents (``mask.nonzero()``), if the caller has them."""
        idx = mask.nonzero().squeeze(1) if idx is None else idx
        idx_np = idx.cpu().numpy()
        self._redraw_for_new_scene(idx_np)  # a swap armed since their next start was drawn
        if len(self.aggregator.note_resets(idx_np, count=ended)):  # some start this episode in a swapped-in scene
            self.bounds = self._agent_bounds()
        self.state = self.quad.restart(self.state, idx, self._next_pos.index_select(0, idx))
        self.episode_step = self.episode_step.index_fill(0, idx, 0)
        self.episode_return = self.episode_return.index_fill(0, idx, 0.0)
        self.reset_agents_hook(idx)
        missing = idx_np[~self._prepared[idx_np]]
        if len(missing):  # first reset, a swapped scene, or a failed worker: render now (a second round trip)
            obs = self.aggregator.observe(self._start_poses(missing), agents=missing, sim_time=self.sim_time)
            self._store_prepared(obs, np.arange(len(missing)), missing)
        rows = self._frame(self._prepared_obs.take(idx_np))
        before = self.frame
        if observation is None or before is None:
            self.frame = rows
        else:
            self.frame = self._merge(idx, rows, own, fresh)
        after = self.frame
        self._draw_next_starts(idx, idx_np)
        fresh_obs = self._observation()
        if observation is None or before is None:
            return fresh_obs
        # An entry that is the frame's image before and after the reset already holds the old rows
        # outside ``mask`` (scatter wrote the new rows into a copy, or in place): no second select of
        # every image.
        passed = {k for k, v in fresh_obs.items()
                  if v is after.images.get(k) and observation[k] is before.images.get(k)}
        return {k: v if k in passed else torch.where(mask.reshape((-1,) + (1,) * (v.dim() - 1)), v, observation[k])
                for k, v in fresh_obs.items()}

    def _merge(self, index: torch.Tensor, rows: SensorFrame, own: bool, fresh: bool = False) -> SensorFrame:
        """``self.frame`` with its rows ``index`` from ``rows``.

        ``own``: the send/recv path, which hands out copies of the group's rows only, never the
        frame's images: the merged frame's images are then the env's alone, and the next merge on
        that path writes into them in place (no copy of every agent's images per group step). Any
        other merge copies, so a frame handed out (a plain step's or a reset's observation) is never
        written over. Task hooks must not keep the frame's images across steps (copy what they keep).

        ``fresh``: the frame's images were collected this step and nothing outside the env refers to
        them yet (a step whose terminal observation holds only the ended rows, copies): they are
        written into in place too; the result is handed out, so it is not the env's own afterwards.
        """
        frame = self.frame
        assert frame is not None, "a merge follows the first observation"
        in_place = fresh or (own and frame is self._own_frame)
        merged = frame.scatter(index, rows, self._image_buffers, in_place=in_place)
        self._own_frame = merged if own else None
        return merged

    def _agent_bounds(self) -> torch.Tensor:
        return torch.as_tensor(np.asarray(self.aggregator.agent_bounds(), dtype=np.float32), device=self.device)


    # ----- resets and life cycle ----------------------------------------------------------------

    def reset_tensor(self, seeds: Sequence[int] | None = None) -> dict[str, torch.Tensor]:
        """Reset every agent (from ``seeds``, one per agent, when given); the observation as tensors.

        Groups still in flight (:meth:`send`) are taken in and dropped: their step never happened."""
        self._check_open()
        self._drop_in_flight()
        if seeds is not None:
            self._reseed(seeds)
        with torch.set_grad_enabled(self.config.requires_grad):
            self.state = self.state.detach()
            everyone = torch.arange(self.num_envs, device=self.device)
            self._draw_next_starts(everyone)
            return self._reset_agents(torch.ones(self.num_envs, dtype=torch.bool, device=self.device), None)

    def reset_some_tensor(self, mask: torch.Tensor | np.ndarray, seeds: Sequence[int] | None = None) -> dict[str, torch.Tensor]:
        """Reset only the agents in ``mask`` (``(N,)`` bool); the observation of every agent as tensors.

        ``seeds``: one per agent of ``mask`` (in index order): each restarts from its own seed, so
        the same seeds give the same starts whatever happened before.
        """
        self._check_open()
        self._check_no_flight("reset_some()")
        mask = torch.as_tensor(np.asarray(mask, dtype=bool), device=self.device)
        if mask.shape != (self.num_envs,):
            raise ConfigError(f"reset mask of shape {tuple(mask.shape)} must be ({self.num_envs},)")
        if self.frame is None:
            return self.reset_tensor()
        if seeds is not None:
            idx = mask.nonzero().squeeze(1)
            self._reseed(seeds, idx.cpu().numpy())
            self._draw_next_starts(idx)  # from the new streams, not the starts drawn before
        with torch.set_grad_enabled(self.config.requires_grad):
            return self._reset_agents(mask, self._observation())

    def _first_reset(self) -> None:
        """A step before any reset resets every agent first (an adapter applies its own seeding)."""
        self.reset_tensor()

    def _init_views(self, num_envs: int, observation_space: spaces.Dict, action_space: spaces.Box) -> None:
        """Set the batch size and spaces (an adapter, such as the SB3 ``VecEnv``, adds its own state)."""
        self.num_envs, self.observation_space, self.action_space = num_envs, observation_space, action_space

    def _reseed(self, seeds: Sequence[int], agents: np.ndarray | None = None) -> None:
        """Restart the random streams: the spawn draws of agent ``agents[i]`` (default: every agent)
        from ``seeds[i]``, the noise generator from all of ``seeds``. The moving obstacles' clock,
        which every agent shares, restarts when every agent is reseeded."""
        seeds = [int(s) for s in seeds]
        self.generator.manual_seed(combined_seed(seeds))
        self.aggregator.reseed(seeds, agents)
        if agents is None or len(agents) == self.num_envs:
            self.sim_time = 0.0   # the same seed starts the moving obstacles from the same places
            self._steps_sent[:] = 0

    def _check_no_flight(self, what: str) -> None:
        if self._in_flight:
            raise ConfigError(f"{what} while {len(self._in_flight)} group(s) sent with send() are in flight; recv() them first")

    def _drop_in_flight(self) -> None:
        """Take in the groups in flight and forget them (their image segments are released)."""
        while self._in_flight:
            self.aggregator.collect(self._in_flight.pop(0).ticket)

    def detach(self) -> None:
        """Cut the autograd graph (truncated BPTT): the state keeps its values, loses its history."""
        self.state = self.state.detach()
        self.actions = self.actions.detach()

    def close(self) -> None:
        """Stop the aggregator and its workers; safe to call more than once."""
        if self._closed:
            return
        self._closed = True
        self._in_flight.clear()  # groups sent and not received are gone with the workers
        self.aggregator.close()

    def __enter__(self) -> "TensorEnv":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _check_open(self) -> None:
        if self._closed:
            raise ConfigError("this env is closed; build a new one (make_env) to keep going")


def _read_only(array: np.ndarray) -> np.ndarray:
    """``array``, marked read only (shared by every plain step: nothing may write into it)."""
    array.setflags(write=False)
    return array


def _pick(tensor: torch.Tensor, span: slice | torch.Tensor) -> torch.Tensor:
    """Rows ``span`` of ``tensor``: a view for a slice, else a copy."""
    return tensor[span] if isinstance(span, slice) else tensor.index_select(0, span)


def _rows(tensors: dict[str, torch.Tensor], ids: torch.Tensor) -> dict[str, torch.Tensor]:
    """Rows ``ids`` of each entry, copies (``index_select``: images several times faster than ``v[ids]``)."""
    return {k: v.index_select(0, ids) for k, v in tensors.items()}


def camera_space(cam: CameraSpec) -> spaces.Box:
    """The observation space of one camera: depth float32 [0, far], RGB uint8, segmentation uint16."""
    if cam.kind == "depth":
        return spaces.Box(0.0, float(cam.far), cam.shape, np.float32)
    if cam.kind == "rgb":
        return spaces.Box(0, 255, cam.shape, np.uint8)
    return spaces.Box(0, np.iinfo(np.uint16).max, cam.shape, np.uint16)


def combined_seed(seeds: Sequence[int]) -> int:
    """One non-negative 63-bit seed from several (each entry changes it; the same list gives the same)."""
    return int(np.random.SeedSequence([s & (2**64 - 1) for s in seeds]).generate_state(1, np.uint64)[0] >> np.uint64(1))
