"""A trained PPO policy's actor as one ONNX graph, for a drone's companion computer.

The graph takes the observation entries exactly as the env gives them (raw: depth in metres,
state in SI units, no normalisation) and returns the command the policy would send:

    raw observation --(VecNormalize statistics, clipped)--> extractor --> actor MLP --> mean action
                    --> clipped to [-1, 1]  = ``action``

so ``action`` equals ``model.predict(normalised_obs, deterministic=True)`` of the training stack.
The observation normalisation (the checkpoint's ``*.norm.npz``, :mod:`~visfly_dist.training.checkpoints`)
and the action clipping are baked in; the critic and the action noise are left out.

Inputs are named after the observation keys (``depth``, ``state``, ``target``, ...), each with a
leading batch axis of any size; the output is ``action`` ``(B, 4)``. A policy with a recurrent
core (see :class:`RecurrentCore`) gets one more input ``hidden_in`` and output ``hidden_out``, both
``(B, *core.hidden_shape)``: feed ``hidden_out`` back as the next step's ``hidden_in`` and zeros at
the start of an episode. A ``visfly-dist train --recurrent`` checkpoint (sb3-contrib ``RecurrentPPO``)
is exported with its actor LSTM as that core (:class:`LstmCore`): ``hidden`` is ``(B, 2, layers, units)``,
``[:, 0]`` the LSTM's h and ``[:, 1]`` its c. What each input holds, its units and frame, and how ``action`` maps onto
the controller's physical command are written into the file's metadata (``visfly`` key, JSON) and
documented in docs/DEPLOY.md; ``deploy/onnx_runner.py`` runs the file with numpy and onnxruntime only.
"""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol, Sequence

import numpy as np
import torch
from gymnasium import spaces
from torch import nn

from visfly_dist.errors import ConfigError

ACTION_OUTPUT = "action"
HIDDEN_INPUT = "hidden_in"
HIDDEN_OUTPUT = "hidden_out"
METADATA_KEY = "visfly"
OPSET = 17
MIN_OPSET = 12
"""The lowest opset whose files onnxruntime was seen to run (11 and below: no float Clip kernel for some graphs)."""

OBSERVATION_DOCS: dict[str, str] = {
    "state": ("position minus the task's reference point (navigation: the goal; hover, gap_crossing: the own "
              "target; tracking: the moving target now; landing: the pad centre), world frame (z up), m [0:3]; "
              "velocity, world frame, m/s [3:6]; attitude quaternion w, x, y, z rotating body (FLU: x forward, "
              "y left, z up) to world [6:10]; body rates, rad/s [10:13]"),
    "target": "unit direction to the goal (gap_crossing: the own target) in the body frame (FLU) [0:3], then its distance, m [3]",
    "gap": "unit direction to the own gap point (centre of the gap, at the target's height) in the body frame (FLU) [0:3], then its distance, m [3]",  # noqa: E501
    "path": ("the moving target's next K positions (now, then every future_dt s) minus the drone's position, "
             "in the body frame (FLU), m; one row per point"),
    "pad": ("the pad centre in the downward camera: u, v in [-1, 1] (u right, v down in the image) [0:2], then "
            "1 when in view (depth camera: projected from the state; RGB camera: the pad pixels' share) [2]; u, v = 0 out of view"),
    "teammates": "each teammate's position [0:3] and velocity [3:6] minus the own, world frame, m and m/s; one row per teammate",
    "moving": "the nearest moving obstacles' relative positions and velocities, world frame (see tasks/navigation_moving.py)",
    "gates": "the next two gates' centres minus the drone's position, world frame, m (see tasks/racing.py)",
    "progress": "share of the course flown, [0, 1]",
}
"""What each observation entry holds (keys of the tasks' ``observation_space_dict``)."""


def camera_doc(kind: str, far: float | None) -> str:
    """The description of a camera image input of ``kind``."""
    if kind == "depth":
        return (f"depth image, float32 metres along the optical axis, (1, H, W), row 0 at the top; rays that hit "
                f"nothing read far ({far:g} m); values are clipped to [0, far] inside the graph")
    if kind == "rgb":
        return "colour image, uint8 RGB, (3, H, W), row 0 at the top"
    return "segmentation ids, uint16, (1, H, W), 0 = nothing"


def action_mapping(controller: str, airframe: Any = None, position_origin: Sequence[float] = (0.0, 0.0, 0.0)) -> dict[str, Any]:
    """How ``action`` (in ``[-1, 1]^4``) maps onto ``controller``'s physical command.

    Returns ``{"controller", "command", "scale", "offset", "units", "text"}``: the command is
    ``offset + scale * action`` per entry (for ``srt`` a rotor thrust, not a speed).
    """
    if controller == "ctbr":
        a_max, rate = float(airframe.max_collective_accel), float(airframe.max_body_rate)
        return dict(controller="ctbr", command=["collective_accel", "rate_x", "rate_y", "rate_z"],
                    scale=[a_max / 2, rate, rate, rate], offset=[a_max / 2, 0.0, 0.0, 0.0],
                    units=["m/s^2", "rad/s", "rad/s", "rad/s"],
                    text=(f"collective mass-normalised thrust (action[0] + 1) / 2 * {a_max:g} m/s^2; body rates "
                          f"action[1:4] * {rate:g} rad/s about body x (roll), y (pitch), z (yaw), FLU"))
    if controller == "lv":
        from visfly_dist.dynamics.controllers import LV_MAX_SPEED

        return dict(controller="lv", command=["vel_x", "vel_y", "vel_z", "yaw"],
                    scale=[LV_MAX_SPEED] * 3 + [math.pi], offset=[0.0] * 4, units=["m/s"] * 3 + ["rad"],
                    text=(f"world-frame velocity set point action[0:3] * {LV_MAX_SPEED:g} m/s (z up) and yaw angle "
                          "action[3] * pi rad (0 = world +x, counter-clockwise)"))
    if controller == "ps":
        from visfly_dist.dynamics.controllers import PS_MAX_OFFSET

        origin = [float(c) for c in position_origin]
        return dict(controller="ps", command=["pos_x", "pos_y", "pos_z", "yaw"],
                    scale=[PS_MAX_OFFSET] * 3 + [math.pi], offset=origin + [0.0], units=["m"] * 3 + ["rad"],
                    text=(f"world-frame position set point {origin} + action[0:3] * {PS_MAX_OFFSET:g} m and yaw angle "
                          "action[3] * pi rad"))
    if controller == "srt":
        a, b, c = (float(x) for x in airframe.thrust_coeffs)
        w_max = float(airframe.rotor_speed_range[1])
        t_max = a * w_max * w_max + b * w_max + c
        return dict(controller="srt", command=["thrust_0", "thrust_1", "thrust_2", "thrust_3"], scale=[t_max / 2] * 4,
                    offset=[t_max / 2] * 4, units=["N"] * 4,
                    text=f"each rotor's thrust (action[i] + 1) / 2 * {t_max:.4g} N (the airframe's thrust at its top rotor speed)")
    raise ConfigError(f"controller {controller!r} has no documented mapping; known: ctbr, lv, ps, srt")


class RecurrentCore(Protocol):
    """What the export needs of a recurrent policy's memory, placed between the features extractor
    and the actor MLP: ``forward(features (B, F), hidden (B, *hidden_shape)) -> (features', hidden')``.

    An LSTM's ``(h, c)`` is packed into one tensor by its adapter (e.g. ``torch.stack`` on a new axis).
    Whoever adds recurrent training provides it; feed zeros as ``hidden`` at an episode's start.
    """

    hidden_shape: tuple[int, ...]

    def __call__(self, features: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]: ...


class LstmCore(nn.Module):
    """A :class:`RecurrentCore` of an ``nn.LSTM`` (RecurrentPPO's ``policy.lstm_actor``): one step,
    ``hidden`` ``(B, 2, layers, units)`` packing the LSTM's ``(h, c)`` (each ``(layers, B, units)`` in torch)."""

    def __init__(self, lstm: nn.LSTM) -> None:
        super().__init__()
        if lstm.batch_first or lstm.bidirectional:
            raise ConfigError("LstmCore takes a sequence-first, one-directional LSTM (RecurrentPPO's)")
        self.lstm = lstm
        self.hidden_shape: tuple[int, ...] = (2, lstm.num_layers, lstm.hidden_size)

    def forward(self, features: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        h, c = hidden[:, 0].transpose(0, 1).contiguous(), hidden[:, 1].transpose(0, 1).contiguous()
        out, (h, c) = self.lstm(features.unsqueeze(0), (h, c))
        return out[0], torch.stack((h, c)).permute(2, 0, 1, 3)

    @staticmethod
    def pack(state: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
        """SB3-contrib's ``(h, c)`` state of ``predict`` (each ``(layers, B, units)``) as ``hidden`` ``(B, 2, layers, units)``."""
        return np.stack([np.asarray(state[0]), np.asarray(state[1])]).transpose(2, 0, 1, 3).astype(np.float32)

    @staticmethod
    def unpack(hidden: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Inverse of :meth:`pack`."""
        hidden = np.asarray(hidden)
        return hidden[:, 0].transpose(1, 0, 2).copy(), hidden[:, 1].transpose(1, 0, 2).copy()


@dataclass
class ObsNormalization:
    """Frozen observation statistics: per key ``(x - mean) / sqrt(var + epsilon)``, clipped to ``±clip``."""

    mean: dict[str, np.ndarray]
    var: dict[str, np.ndarray]
    clip: float = 10.0
    epsilon: float = 1e-8

    @classmethod
    def load(cls, path: Path) -> "ObsNormalization":
        """Read the observation part of a checkpoint's ``*.norm.npz``."""
        with np.load(path, allow_pickle=False) as data:
            keys = sorted({name.split("/")[1] for name in data.files if name.startswith("obs/")})
            return cls(mean={k: np.asarray(data[f"obs/{k}/mean"], np.float64) for k in keys},
                       var={k: np.asarray(data[f"obs/{k}/var"], np.float64) for k in keys},
                       clip=float(data["clip_obs"]), epsilon=float(data["epsilon"]))

    @classmethod
    def of(cls, venv: Any) -> "ObsNormalization":
        """The current statistics of an SB3 ``VecNormalize``."""
        rms = venv.obs_rms if isinstance(venv.obs_rms, dict) else {}
        return cls(mean={k: np.asarray(r.mean, np.float64) for k, r in rms.items()},
                   var={k: np.asarray(r.var, np.float64) for k, r in rms.items()},
                   clip=float(venv.clip_obs), epsilon=float(venv.epsilon))

    def normalize(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """What VecNormalize does to ``obs`` (float64 arithmetic, as SB3)."""
        out = dict(obs)
        for k in self.mean:
            out[k] = np.clip((obs[k] - self.mean[k]) / np.sqrt(self.var[k] + self.epsilon), -self.clip, self.clip)
        return out


class DeployedActor(nn.Module):
    """Raw observations (positional, in ``keys`` order; then ``hidden`` when recurrent) -> clipped
    deterministic action (and the next hidden state). See the module docstring."""

    low: torch.Tensor
    high: torch.Tensor

    def __init__(self, policy: Any, keys: Sequence[str], normalization: ObsNormalization | None = None,
                 core: RecurrentCore | None = None) -> None:
        super().__init__()
        from stable_baselines3.common.distributions import DiagGaussianDistribution, SquashedDiagGaussianDistribution

        dist = policy.action_dist
        if not isinstance(dist, (DiagGaussianDistribution, SquashedDiagGaussianDistribution)) and not policy.use_sde:
            raise ConfigError(f"export supports Gaussian (Box) action policies; this one has {type(dist).__name__}")
        self.keys = list(keys)
        self.observation_space = policy.observation_space
        self.extractor = policy.pi_features_extractor
        self.mlp_extractor = policy.mlp_extractor
        self.action_net = policy.action_net
        self.squash = bool(policy.squash_output)
        self.core = core
        space = policy.action_space
        self.register_buffer("low", torch.as_tensor(space.low, dtype=torch.float32))
        self.register_buffer("high", torch.as_tensor(space.high, dtype=torch.float32))
        norm = normalization or ObsNormalization({}, {})
        unknown = sorted(set(norm.mean) - set(self.keys))
        if unknown:
            raise ConfigError(f"normalisation statistics for {unknown}, which the policy does not observe; another task's?")
        self.normalized = [k for k in self.keys if k in norm.mean]
        self.clip = float(norm.clip)
        for i, k in enumerate(self.normalized):
            # float64, as VecNormalize computes: in float32 a large raw value (e.g. a far moving
            # obstacle) minus its mean loses the digits that the 1e-5 agreement needs
            self.register_buffer(f"mean_{i}", torch.as_tensor(norm.mean[k], dtype=torch.float64))
            self.register_buffer(f"std_{i}", torch.as_tensor(np.sqrt(norm.var[k] + norm.epsilon), dtype=torch.float64))

    def forward(self, *inputs: torch.Tensor) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        obs: dict[str, torch.Tensor] = {}
        for key, x in zip(self.keys, inputs):
            x = x.float()
            if key in self.normalized:
                i = self.normalized.index(key)
                # float64 for the shift and scale, float32 for the clip: onnxruntime has no float64 Clip before opset 12
                x = ((x.double() - getattr(self, f"mean_{i}")) / getattr(self, f"std_{i}")).float().clamp(-self.clip, self.clip)
            obs[key] = x
        features = self.extractor(obs)
        hidden = None
        if self.core is not None:
            features, hidden = self.core(features, inputs[len(self.keys)])
        mean = self.action_net(self.mlp_extractor.forward_actor(features))
        if self.squash:
            mean = torch.tanh(mean)
        action = torch.maximum(torch.minimum(mean, self.high), self.low)
        return action if hidden is None else (action, hidden)


@dataclass
class ExportInfo:
    """What was written: the file, its inputs and outputs, and the metadata stored in it."""

    path: Path
    inputs: list[dict[str, Any]]
    outputs: list[dict[str, Any]]
    metadata: dict[str, Any] = field(default_factory=dict)


def _dtype_name(dtype: Any) -> str:
    return np.dtype(dtype).name


def observation_entries(space: spaces.Space) -> dict[str, spaces.Box]:
    """The entries of ``space``, a Dict of Boxes (what the export takes).

    Raises:
        ConfigError: another kind of space.
    """
    if not isinstance(space, spaces.Dict):
        raise ConfigError(f"export needs a Dict observation space, got {space!r}")
    entries = {}
    for key, entry in space.spaces.items():
        if not isinstance(entry, spaces.Box):
            raise ConfigError(f"export needs Box observation entries; {key!r} is {entry!r}")
        entries[key] = entry
    return entries


def input_specs(observation_space: spaces.Dict, cameras: Sequence[Any] = ()) -> list[dict[str, Any]]:
    """One ``{name, shape, dtype, doc}`` per observation entry (shape without the batch axis)."""
    by_name = {c.name: c for c in cameras}
    specs = []
    for key, space in observation_entries(observation_space).items():
        if len(space.shape) == 3:
            cam = by_name.get(key)
            kind = cam.kind if cam is not None else ("rgb" if space.dtype == np.uint8 else
                                                     "depth" if np.issubdtype(space.dtype, np.floating) else "segmentation")
            far = cam.far if cam is not None else float(np.max(space.high))
            doc = camera_doc(kind, far)
            if cam is not None:
                doc += f"; {cam.hfov_deg:g} deg horizontal field of view, mounted at {list(cam.offset)} m (FLU), rotation wxyz {list(cam.rotation)}"  # noqa: E501
        else:
            doc = OBSERVATION_DOCS.get(key, "see the task's get_observation")
        specs.append(dict(name=key, shape=list(space.shape), dtype=_dtype_name(space.dtype), doc=doc))
    return specs


def export_policy(policy: Any, out: str | Path, normalization: ObsNormalization | None = None,
                  core: RecurrentCore | None = None, metadata: dict[str, Any] | None = None,
                  cameras: Sequence[Any] = (), opset: int = OPSET) -> ExportInfo:
    """Write ``policy``'s (an SB3 ``ActorCriticPolicy`` with a Dict observation space) deterministic
    actor to ``out`` (ONNX), with ``normalization`` and the action clipping inside.

    Args:
        policy: ``model.policy`` of a PPO (or A2C) model.
        out: the ``.onnx`` file.
        normalization: the observation statistics of training (``None``: the policy sees raw observations).
        core: an optional recurrent core (:class:`RecurrentCore`); adds ``hidden_in``/``hidden_out``.
        metadata: merged into the file's ``visfly`` metadata (task, controller, rates...).
        cameras: the task's ``CameraSpec``s, to document the image inputs (field of view, mount).
        opset: ONNX opset, at least :data:`MIN_OPSET`.

    Raises:
        ConfigError: an opset below :data:`MIN_OPSET`.
    """
    import onnx

    if not isinstance(opset, int) or opset < MIN_OPSET:
        raise ConfigError(f"opset={opset!r}: the lowest checked against onnxruntime is {MIN_OPSET}")

    space = policy.observation_space
    entries = observation_entries(space)
    keys = list(entries)
    actor = DeployedActor(policy, keys, normalization, core).to("cpu").eval()
    dummies = [torch.as_tensor(np.zeros((1, *s.shape), dtype=s.dtype)) for s in entries.values()]
    names, outputs = list(keys), [ACTION_OUTPUT]
    if core is not None:
        dummies.append(torch.zeros((1, *core.hidden_shape)))
        names.append(HIDDEN_INPUT)
        outputs.append(HIDDEN_OUTPUT)
    dynamic = {name: {0: "batch"} for name in names + outputs}
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    # The TorchScript-based exporter: the policy is plain layers, it needs no onnxscript, and the
    # image trunk takes its plain (unfused) path while exporting (extractors.ConvPoolSequential).
    with torch.no_grad(), warnings.catch_warnings():
        # the LSTM's initial state is an input (hidden_in), so any batch size runs
        warnings.filterwarnings("ignore", message="Exporting a model to ONNX with a batch_size other than 1")
        warnings.filterwarnings("ignore", message="Converting a tensor to a Python boolean")  # nn.LSTM's shape checks
        torch.onnx.export(actor, tuple(dummies), str(out), input_names=names, output_names=outputs,
                          dynamic_axes=dynamic, opset_version=opset, dynamo=False)
    inputs = input_specs(space, cameras)
    for spec in inputs:
        spec["normalized_inside"] = spec["name"] in actor.normalized
    outs = [dict(name=ACTION_OUTPUT, shape=list(policy.action_space.shape), dtype="float32",
                 doc="the controller's command in [-1, 1] (deterministic: the policy's mean action, clipped)")]
    if core is not None:
        hidden = dict(shape=list(core.hidden_shape), dtype="float32")
        inputs.append(dict(name=HIDDEN_INPUT, doc="recurrent state: zeros at an episode's start, else the last hidden_out", **hidden))
        outs.append(dict(name=HIDDEN_OUTPUT, doc="recurrent state to feed back as the next step's hidden_in", **hidden))
    meta = {"format": 1, "inputs": inputs, "outputs": outs, "recurrent": core is not None, **(metadata or {})}
    model = onnx.load(str(out))
    onnx.helper.set_model_props(model, {METADATA_KEY: json.dumps(meta)})
    model.doc_string = "visfly-dist policy: " + ", ".join(f"{i['name']} {i['shape']}" for i in inputs) + f" -> {ACTION_OUTPUT}"
    onnx.checker.check_model(model)
    onnx.save(model, str(out))
    return ExportInfo(out, inputs, outs, meta)


def task_metadata(task: str, env_settings: dict[str, Any]) -> tuple[dict[str, Any], tuple[Any, ...]]:
    """Task, controller, control rate and action mapping of ``task`` with ``env_settings`` (``make_env``
    keyword arguments), and its cameras; builds the task's config only, starts no worker."""
    from visfly_dist.dynamics import load_airframe
    from visfly_dist.tasks import task_class

    config_class = task_class(task).config_class
    settings = {k: v for k, v in env_settings.items() if k in config_class.field_names()}
    cfg = config_class(**settings)
    airframe = load_airframe(cfg.airframe)
    mapping = action_mapping(cfg.controller, airframe, getattr(cfg, "position_origin", (0.0, 0.0, 0.0)))
    return {"task": task, "controller": cfg.controller, "ctrl_dt": float(cfg.ctrl_dt),
            "control_rate_hz": round(1.0 / float(cfg.ctrl_dt), 6), "airframe": str(cfg.airframe),
            "action_delay_s": float(cfg.action_delay_s), "action_mapping": mapping}, tuple(cfg.cameras)


def check_exportable(checkpoint: Path) -> None:
    """Raise ConfigError unless ``checkpoint`` is an existing PPO ``.zip`` (the kind export reads):
    checked before anything else about it, so a BPTT/SHAC ``.npz`` is told so, not sent after its
    normalisation statistics."""
    if checkpoint.suffix == ".npz":
        raise ConfigError(f"--checkpoint {str(checkpoint)!r} is a BPTT/SHAC actor (.npz): export takes PPO checkpoints "
                          "(.zip) only so far; evaluate it with 'visfly-dist eval' (docs/DEPLOY.md)")
    if not checkpoint.is_file() or checkpoint.suffix != ".zip":
        raise ConfigError(f"--checkpoint {str(checkpoint)!r} must be an existing PPO .zip written by 'visfly-dist train'")


def export_checkpoint(task: str, checkpoint: str | Path, out: str | Path, env_settings: dict[str, Any] | None = None,
                      opset: int = OPSET) -> ExportInfo:
    """Export a ``visfly-dist train`` checkpoint (``.zip``, with its ``*.norm.npz`` when there is one);
    a RecurrentPPO one (``--recurrent``) with its actor LSTM as the core (``hidden_in``/``hidden_out``).

    ``env_settings`` are the ``make_env`` settings of the run (default: those of its ``config.json``
    when found, else the task's defaults); they only fill the metadata.
    """
    from stable_baselines3 import PPO
    from stable_baselines3.common.on_policy_algorithm import OnPolicyAlgorithm

    from visfly_dist.training.checkpoints import norm_path
    from visfly_dist.training.evaluation import find_run_config, is_recurrent_checkpoint, missing_normalization
    from visfly_dist.training.run import env_kwargs

    checkpoint = Path(checkpoint)
    check_exportable(checkpoint)
    run_cfg = find_run_config(checkpoint)
    if run_cfg is not None and run_cfg.task != task:
        raise ConfigError(f"{str(checkpoint)!r} was trained on task {run_cfg.task!r} (its config.json), not {task!r}")
    missing_normalization(checkpoint, run_cfg)  # raises where the run normalised and NAME.norm.npz is not beside it
    if env_settings is None:
        env_settings = env_kwargs(run_cfg.resolved()) if run_cfg is not None else {}
    recurrent = is_recurrent_checkpoint(checkpoint)
    model: OnPolicyAlgorithm
    core: LstmCore | None = None
    if recurrent:
        from sb3_contrib import RecurrentPPO

        model = RecurrentPPO.load(checkpoint, device="cpu")
        assert isinstance(model.policy.lstm_actor, nn.LSTM)  # RecurrentPPO's policy (typed as any actor-critic policy)
        core = LstmCore(model.policy.lstm_actor)
    else:
        model = PPO.load(checkpoint, device="cpu")
    stats = norm_path(checkpoint)
    normalization = ObsNormalization.load(stats) if stats.is_file() else None
    meta, cameras = task_metadata(task, env_settings)
    task_space = set(OBSERVATION_DOCS) | {c.name for c in cameras}
    missing = [k for k in observation_entries(model.observation_space) if k not in task_space]
    if missing:
        raise ConfigError(f"checkpoint {checkpoint} observes {missing}, which task {task!r} does not give; is it another task's?")
    meta.update(source_checkpoint=str(checkpoint), normalization=str(stats) if normalization is not None else None)
    if core is not None:
        meta["recurrent_core"] = dict(kind="lstm", layers=core.lstm.num_layers, units=core.lstm.hidden_size,
                                      text="hidden[:, 0] is the LSTM's h, hidden[:, 1] its c, each (layers, units)")
    return export_policy(model.policy, out, normalization, core=core, metadata=meta, cameras=cameras, opset=opset)


def describe(info: ExportInfo) -> str:
    """A few lines for the terminal: inputs, outputs, rate and mapping."""
    meta = info.metadata
    lines = [f"wrote {info.path}"]
    for spec in info.inputs:
        norm = " (normalised inside)" if spec.get("normalized_inside") else ""
        lines.append(f"  input  {spec['name']:<10} {spec['dtype']:<8} (B, {', '.join(map(str, spec['shape']))}){norm}")
    for spec in info.outputs:
        lines.append(f"  output {spec['name']:<10} {spec['dtype']:<8} (B, {', '.join(map(str, spec['shape']))})")
    if "controller" in meta:
        lines.append(f"  run at {meta['control_rate_hz']:g} Hz (ctrl_dt {meta['ctrl_dt']:g} s); "
                     f"{meta['controller']}: {meta['action_mapping']['text']}")
    return "\n".join(lines)


def read_metadata(path: str | Path) -> dict[str, Any]:
    """The ``visfly`` metadata of an exported file."""
    import onnx

    model = onnx.load(str(path), load_external_data=False)
    props = {p.key: p.value for p in model.metadata_props}
    return json.loads(props[METADATA_KEY]) if METADATA_KEY in props else {}


__all__ = ["DeployedActor", "ExportInfo", "LstmCore", "ObsNormalization", "RecurrentCore", "action_mapping", "describe",
           "export_checkpoint", "export_policy", "read_metadata", "task_metadata"]
