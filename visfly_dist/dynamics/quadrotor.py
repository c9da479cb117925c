"""``Quadrotor``: a batch of N quadrotors advanced by a pure ``step(state, action) -> state``."""

from __future__ import annotations

import math
from typing import Any, Callable

import torch

from visfly_dist.dynamics.adjoint import CtbrStep, CtbrStepFunction, ctbr_step
from visfly_dist.dynamics.airframe import Airframe, load_airframe
from visfly_dist.dynamics.config import DynamicsConfig
from visfly_dist.dynamics.controllers import CollectiveThrustBodyRate, PositionYaw, make_controller
from visfly_dist.dynamics.model import GRAVITY, ROTOR_ROW, ROWS, RigidBodyModel, euler_step, rk4_step, unpack
from visfly_dist.dynamics.native_step import NativeCtbrStep, load_dynamics
from visfly_dist.dynamics.state import QuadState
from visfly_dist.errors import ConfigError

Tensors = tuple[torch.Tensor, ...]
RECOMPILE_LIMIT = 64
ADJOINT_MAX_AGENTS = 3072
NUMPY_STEP_MAX_AGENTS = 2048
"""Up to this many agents, steps without gradients run the adjoint's NumPy forward too when the native
step is not built: per-op dispatch, not arithmetic, is their cost (no grad, one thread: 0.65 against
2.4 ms a step at 16 agents, 1.2 against 3.0 at 100, 2.7 against 3.6 at 1,000; slower than torch at
3,000)."""


class Quadrotor:
    """N quadrotors of one airframe under one controller, on one device and dtype.

    One ``step`` is one control step of ``config.ctrl_dt``: the (possibly delayed) action becomes a
    set point, then ``config.substeps`` physics substeps each run the controller's inner loop and
    integrate (RK4 or Euler) with the rotor command held over the substep.

    Ground: contact with the plane ``z = 0`` is reported in ``QuadState.ground_contact``. With
    ``config.ground`` a simple inelastic reaction acts after each substep: an agent below the
    plane is put back on it and its downward velocity is removed (no friction, no bounce, no
    torque), so a drone resting on the floor does not sink.

    Gradients flow from the output state to actions, the input state and any airframe tensors
    that require grad; nothing is modified in place.

    Speed: on CPU run torch single-threaded (``torch.set_num_threads(1)``) in the process that
    steps the batch. Each op here lasts microseconds; with a second thread MKL's pool makes small
    matmuls take milliseconds whenever the other core is busy. ``config.compile`` fuses the step
    (about 5x faster at 1,000 agents after a compile of a minute or so). With gradients, CTBR
    steps on the CPU are one autograd node with a hand-written reverse pass (``dynamics.adjoint``,
    on by default: ``config.adjoint``), unless airframe parameters require grad; without gradients,
    the same CTBR steps (any number of agents) run the native forward ``dynamics/native`` built by
    ``setup.sh`` (``dynamics.native_step``: plain loops over blocks of agents, in the state's dtype;
    off with ``VISFLY_NATIVE_DYNAMICS=0``), or, when it is not built, the adjoint's NumPy forward up
    to ``NUMPY_STEP_MAX_AGENTS`` agents. A step without grad (float32, one thread, busy 2-core
    machine) took 0.2 ms native against 2.1-2.4 ms NumPy at 256 agents, 0.6-1.1 against 4-9 ms at
    1,024: NumPy's ~500 small ops a control step are its cost.

    Args:
        config: simulation and controller settings.
        airframe: an ``Airframe`` or the name/path for ``load_airframe`` (default ``"visfly"``).
        num_agents: N.
        device: torch device.
        dtype: ``torch.float32`` (default) or ``torch.float64``.

    Raises:
        ConfigError: an invalid ``num_agents``, ``dtype``, airframe or a wind of the wrong shape.
    """

    def __init__(self, config: DynamicsConfig, airframe: Airframe | str = "visfly", num_agents: int = 1,
                 device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32) -> None:
        if not isinstance(config, DynamicsConfig):
            raise ConfigError(f"config must be a DynamicsConfig, got {type(config).__name__}")
        if not isinstance(num_agents, int) or num_agents < 1:
            raise ConfigError(f"num_agents={num_agents!r} must be an int >= 1")
        if dtype not in (torch.float32, torch.float64):
            raise ConfigError(f"dtype={dtype} must be torch.float32 or torch.float64")
        self.airframe = load_airframe(airframe) if isinstance(airframe, str) else airframe
        if not isinstance(self.airframe, Airframe):
            raise ConfigError(f"airframe must be an Airframe or a name/path, got {type(airframe).__name__}")
        wind = None
        if config.wind is not None:
            wind = torch.as_tensor(config.wind)
            if wind.dim() == 2 and wind.shape[0] != num_agents:
                raise ConfigError(f"wind of shape {tuple(wind.shape)} must be (3,) or ({num_agents}, 3) "
                                  f"for num_agents={num_agents}")
        self.config = config
        self.num_agents = num_agents
        self.device = torch.device(device)
        self.dtype = dtype
        self.model = RigidBodyModel(self.airframe, config.motor_lag, wind, self.device, dtype)
        self.controller = make_controller(config.controller, self.model, self.airframe,
                                          config.position_origin)
        self._integrate = rk4_step if config.integrator == "rk4" else euler_step
        self._adjoint: CtbrStep | None = None
        self._native: NativeCtbrStep | None = None
        self._rest_rows: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # see _rest
        # The adjoint runs on NumPy views of CPU tensors. Past about 3,000 agents its dense matmuls
        # cost more than autograd's bookkeeping saves (measured with grad: 0.75x autograd at 4,096,
        # 1.1x at 3,000, 2-3x at 1,000, 5x at 100); compiled, autograd's own graph is used. The
        # native forward (steps without grad) takes the adjoint's constants, at any number of agents.
        if config.adjoint and isinstance(self.controller, CollectiveThrustBodyRate) and not config.compile and self.device.type == "cpu" \
                and not _any_requires_grad(self.model, self.controller):
            ctbr = CtbrStep(self.model, self.controller, config.substeps, config.sim_dt,
                            config.integrator == "rk4", config.ground)
            self._adjoint = ctbr if num_agents <= ADJOINT_MAX_AGENTS else None
            lib, _ = load_dynamics()
            self._native = None if lib is None else NativeCtbrStep(ctbr, lib)
        self._advance: Callable[..., Tensors] = self._advance_eager
        if config.compile:
            # All instances share one code object, and each batch size, grad mode and
            # requires-grad pattern of the inputs is its own specialisation of it: allow many more
            # than dynamo's default of 8 (fullgraph makes running out a hard error, not a
            # silent fall-back to eager).
            torch._dynamo.config.recompile_limit = max(torch._dynamo.config.recompile_limit, RECOMPILE_LIMIT)
            self._advance = torch.compile(self._advance_eager, fullgraph=True, dynamic=False)

    # --- states and actions -------------------------------------------------------------------

    def hover_action(self) -> torch.Tensor:
        """(4,) the action that holds a drone hovering in place (PS: at ``position_origin``)."""
        return torch.tensor(self.controller.hover_action(), dtype=self.dtype, device=self.device)

    def hover_rotor_speed(self) -> torch.Tensor:
        """() rotor speed, rad/s, at which four rotors carry the weight (in the airframe's graph)."""
        return self.model.rotor_speed_for(self.model.mass * GRAVITY / 4)

    def initial_state(self, pos: torch.Tensor | None = None, vel: torch.Tensor | None = None,
                      quat: torch.Tensor | None = None, omega: torch.Tensor | None = None,
                      rotor: torch.Tensor | None = None, agents: int | None = None) -> QuadState:
        """A state of N agents (``agents`` if given: the new rows of a few, see
        :meth:`QuadState.put_rows`); components left None are: at the origin, at rest, level, with
        rotors at hover speed. The action queue holds the hover action (PS: the action that holds
        each agent's position)."""
        n = self.num_agents if agents is None else agents
        kw: dict[str, Any] = {"dtype": self.dtype, "device": self.device}
        level, hover_speed, hover_action = self._rest()
        pos = self._component("pos", pos, torch.zeros(n, 3, **kw))
        vel = self._component("vel", vel, torch.zeros(n, 3, **kw))
        given_quat = quat is not None
        quat = self._component("quat", quat, level.expand(n, 4).contiguous())
        omega = self._component("omega", omega, torch.zeros(n, 3, **kw))
        rotor = self._component("rotor", rotor, hover_speed.expand(n, 4))
        hold = hover_action.expand(n, 4)
        if isinstance(self.controller, PositionYaw):
            offset = (pos.detach() - self.controller.origin.T) / 10.0
            hold = torch.cat((offset.clamp(-1, 1), hold[:, 3:]), dim=1)
        queue = hold[:, None].expand(n, self.config.delay_steps, 4).contiguous()
        return QuadState(pos=pos, vel=vel, quat=quat / quat.norm(dim=1, keepdim=True) if given_quat else quat,
                         omega=omega, rotor=rotor, ground_contact=pos[:, 2] <= 0, action_queue=queue)

    def restart(self, state: QuadState, index: torch.Tensor, pos: torch.Tensor) -> QuadState:
        """``state`` with agents ``index`` (``(k,)`` long) back at rest at ``pos`` (``(k, 3)``): what
        ``state.put_rows(index, self.initial_state(pos, agents=k))`` gives, in one operation per
        component instead of building the ``k`` rows first (an env resets a few agents most steps)."""
        level, hover_speed, hover_action = self._rest()
        if isinstance(self.controller, PositionYaw) or self._rest_rows is None:  # hold depends on pos; rest in a graph
            return state.put_rows(index, self.initial_state(pos, agents=len(index)))
        k, pos = len(index), pos.to(self.dtype)
        queue = state.action_queue
        if queue.shape[1]:
            queue = queue.index_copy(0, index, hover_action.expand(k, queue.shape[1], 4))
        return QuadState(pos=state.pos.index_copy(0, index, pos), vel=state.vel.index_fill(0, index, 0.0),
                         quat=state.quat.index_copy(0, index, level.expand(k, 4)),
                         omega=state.omega.index_fill(0, index, 0.0),
                         rotor=state.rotor.index_fill(0, index, hover_speed),
                         ground_contact=state.ground_contact.index_copy(0, index, pos[:, 2] <= 0), action_queue=queue)

    def _rest(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``(1, 4)`` the level quaternion, ``()`` the hover rotor speed and ``(4,)`` the hover action:
        made once, unless an airframe parameter requires grad (then each start is in its graph)."""
        if self._rest_rows is not None:
            return self._rest_rows
        rest = (torch.tensor([[1.0, 0.0, 0.0, 0.0]], dtype=self.dtype, device=self.device),
                self.hover_rotor_speed(), self.hover_action())
        if not _any_requires_grad(self.model, self.controller):
            self._rest_rows = rest
        return rest

    def _component(self, name: str, value: torch.Tensor | None, default: torch.Tensor) -> torch.Tensor:
        if value is None:
            return default
        value = torch.as_tensor(value, dtype=self.dtype, device=self.device)
        if value.shape != default.shape:
            raise ConfigError(f"{name} has shape {tuple(value.shape)}; expected {tuple(default.shape)}")
        return value

    # --- the step -----------------------------------------------------------------------------

    def step(self, state: QuadState, action: torch.Tensor) -> QuadState:
        """Advance every agent by one control step; pure (the input state is untouched).

        Args:
            state: current state of the N agents.
            action: (N, 4) in [-1, 1] (values outside are clamped); see ``controllers``.

        Raises:
            ConfigError: wrong action shape or non-finite actions (with ``config.check_actions``).
        """
        if self.config.check_actions:
            self._check_action(action)
        queue = state.action_queue
        if queue.shape[1] > 0:
            action, queue = queue[:, 0], torch.cat((queue[:, 1:], action[:, None]), dim=1)
        inputs = (state.pos, state.vel, state.quat, state.omega, state.rotor, action)
        grad = torch.is_grad_enabled() and any(x.requires_grad for x in inputs)
        # the native forward declines inputs it does not take (None): they go the other ways
        outputs = None if self._native is None or grad else self._native(*inputs[:5], action.to(self.dtype))
        if outputs is None:
            advance = self._advance
            if self._adjoint is not None and (self.num_agents <= NUMPY_STEP_MAX_AGENTS or grad):
                advance = self._advance_adjoint
            outputs = advance(*inputs)
        pos, vel, quat, omega, rotor, contact = outputs
        return QuadState(pos=pos, vel=vel, quat=quat, omega=omega, rotor=rotor,
                         ground_contact=contact, action_queue=queue)

    def _check_action(self, action: torch.Tensor) -> None:
        expected = (self.num_agents, 4)
        if not isinstance(action, torch.Tensor) or tuple(action.shape) != expected:
            shape = tuple(action.shape) if hasattr(action, "shape") else type(action).__name__
            raise ConfigError(f"action of shape {shape} must be a tensor of shape {expected} "
                              f"(num_agents, 4) in [-1, 1]")
        if not math.isfinite(float(action.detach().abs().max())):  # max propagates NaN: 2 operations, isfinite().all() 6
            bad = (~torch.isfinite(action)).any(dim=1).nonzero().flatten()[:8].tolist()
            raise ConfigError(f"action has NaN or infinite entries (agents {bad}...); actions must be "
                              "finite values in [-1, 1]")

    def _advance_eager(self, pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
                       rotor: torch.Tensor, action: torch.Tensor) -> Tensors:
        """The control step on plain tensors, recorded op by op by autograd (compiled as a whole
        with ``config.compile``)."""
        s, action = self._pack(pos, vel, quat, omega, rotor, action)
        return self._unpack(*self._substeps(s, action))

    def _advance_adjoint(self, pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
                         rotor: torch.Tensor, action: torch.Tensor) -> Tensors:
        """The control step with gradients, as one autograd node (``dynamics.adjoint``); without
        them, the same NumPy forward called directly."""
        adjoint = self._adjoint
        assert adjoint is not None, "step() takes this path only with an adjoint"
        inputs = (pos, vel, quat, omega, rotor, action.to(self.dtype))
        if torch.is_grad_enabled() and any(x.requires_grad for x in inputs):
            return CtbrStepFunction.apply(*inputs, adjoint)
        return ctbr_step(*inputs, adjoint)[0]

    def _pack(self, pos: torch.Tensor, vel: torch.Tensor, quat: torch.Tensor, omega: torch.Tensor,
              rotor: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The flat component-major state (17, N) and clamped actions (4, N)."""
        s = torch.cat((pos, vel, quat, omega, rotor), dim=1).T.contiguous()
        return s, action.to(self.dtype).clamp(-1.0, 1.0).T

    @staticmethod
    def _unpack(s: torch.Tensor, contact: torch.Tensor) -> Tensors:
        """Batch-first components of a flat state, the quaternion renormalised, and the contacts."""
        pos, vel, quat, omega, rotor = unpack(s)
        s = torch.cat((pos, vel, quat / quat.norm(dim=0, keepdim=True), omega, rotor)).T.contiguous()
        return (*s.split(ROWS, dim=1), contact)

    def _substeps(self, s: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The physics substeps of one control step on the flat state (recorded by autograd)."""
        setpoint = self.controller.prepare(action)
        contact = torch.zeros(s.shape[1], dtype=torch.bool, device=s.device)
        for _ in range(self.config.substeps):
            rotor_cmd = self.controller.rotor_command(s, setpoint)
            if not self.config.motor_lag:
                s = torch.cat((s[:ROTOR_ROW], rotor_cmd))
            s = self._integrate(self.model, s, rotor_cmd, self.config.sim_dt)
            contact = contact | (s[2] <= 0)
            if self.config.ground:
                s = _ground_reaction(s)
        return s, contact


def _any_requires_grad(*objects: object) -> bool:
    """Whether a tensor attribute of any of ``objects`` requires grad (airframe parameters, wind)."""
    return any(isinstance(v, torch.Tensor) and v.requires_grad for o in objects for v in vars(o).values())


def _ground_reaction(s: torch.Tensor) -> torch.Tensor:
    """Put agents below ``z = 0`` back on the plane and remove their downward velocity."""
    xy, z, vxy, vz, rest = s.split((2, 1, 2, 1, s.shape[0] - 6))
    below = z < 0
    return torch.cat((xy, z.clamp_min(0.0), vxy, torch.where(below, vz.clamp_min(0.0), vz), rest))
