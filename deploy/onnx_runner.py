#!/usr/bin/env python3
"""Run a policy exported by ``visfly-dist export`` with numpy and onnxruntime only (no torch, no visfly_dist).

On a companion computer, one call per control step (docs/DEPLOY.md)::

    from onnx_runner import OnnxPolicy
    policy = OnnxPolicy("policy.onnx")
    policy.reset()                               # at take-off: zero the recurrent state, if any
    while flying:                                # at policy.control_rate_hz
        obs = {"depth": depth_m[None], "state": state[None], "target": target[None]}   # batch of 1
        action = policy.act(obs)[0]              # (4,) in [-1, 1]
        send(policy.command(action))             # the controller's physical command

Offline, over a recorded ``.npz`` of observations (one array per input name, ``(T, ...)`` for one
drone or ``(T, B, ...)`` for B drones; optional ``episode_start`` ``(T,)`` / ``(T, B)`` bools that
reset the recurrent state), step by step as in flight::

    python deploy/onnx_runner.py policy.onnx --observations obs.npz --out actions.npz
    python deploy/onnx_runner.py policy.onnx --describe

``actions.npz`` holds ``action`` (``(T, 4)`` or ``(T, B, 4)``), ``command`` (the physical command,
same shape) and ``latency_ms`` (per step).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

METADATA_KEY = "visfly"
HIDDEN_INPUT, HIDDEN_OUTPUT = "hidden_in", "hidden_out"


class OnnxPolicy:
    """An exported policy: raw observations in, the controller's command out.

    Args:
        path: the ``.onnx`` file.
        threads: onnxruntime intra-op threads (1 suits a small companion computer sharing its cores).
    """

    def __init__(self, path: str | Path, threads: int = 1) -> None:
        options = ort.SessionOptions()
        options.intra_op_num_threads = threads
        options.inter_op_num_threads = 1
        self.session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        meta = self.session.get_modelmeta().custom_metadata_map
        self.metadata: dict[str, Any] = json.loads(meta[METADATA_KEY]) if METADATA_KEY in meta else {}
        self.input_names = [i.name for i in self.session.get_inputs()]
        self.observation_names = [n for n in self.input_names if n != HIDDEN_INPUT]
        self.recurrent = HIDDEN_INPUT in self.input_names
        self._types = {i.name: _numpy_type(i.type) for i in self.session.get_inputs()}
        hidden = next((i for i in self.session.get_inputs() if i.name == HIDDEN_INPUT), None)
        self.hidden_shape: tuple[int, ...] = tuple(int(d) for d in hidden.shape[1:]) if hidden is not None else ()
        self.hidden: np.ndarray | None = None
        mapping = self.metadata.get("action_mapping") or {}
        self._scale = np.asarray(mapping.get("scale", [1.0] * 4), np.float64)
        self._offset = np.asarray(mapping.get("offset", [0.0] * 4), np.float64)

    @property
    def control_rate_hz(self) -> float | None:
        """The rate the policy was trained at (``1 / ctrl_dt``), when the file says."""
        return self.metadata.get("control_rate_hz")

    def reset(self, mask: np.ndarray | None = None) -> None:
        """Zero the recurrent state: all of it, or the rows where ``mask`` (``(B,)`` bool) is true."""
        if self.hidden is None or mask is None:
            self.hidden = None
        else:
            self.hidden[np.asarray(mask, bool)] = 0.0

    def act(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        """``(B, 4)`` actions in ``[-1, 1]`` for a batch of raw observations (each ``(B, ...)``).

        A recurrent policy carries its state from call to call (zeros after :meth:`reset`).
        """
        missing = [n for n in self.observation_names if n not in obs]
        if missing:
            raise KeyError(f"observation lacks {missing}; the policy takes {self.observation_names}")
        feed = {n: np.ascontiguousarray(obs[n], dtype=self._types[n]) for n in self.observation_names}
        batch = len(feed[self.observation_names[0]])
        if self.recurrent:
            if self.hidden is None or len(self.hidden) != batch:
                self.hidden = np.zeros((batch, *self.hidden_shape), np.float32)
            feed[HIDDEN_INPUT] = self.hidden
            action, self.hidden = self.session.run(["action", HIDDEN_OUTPUT], feed)
            return action
        return self.session.run(["action"], feed)[0]

    def command(self, action: np.ndarray) -> np.ndarray:
        """The controller's physical command of ``action`` (``offset + scale * action``; see the file's
        ``action_mapping``: CTBR collective m/s^2 and body rates rad/s, LV velocity m/s and yaw rad, ...)."""
        return self._offset + self._scale * np.asarray(action, np.float64)


def _numpy_type(onnx_type: str) -> type:
    return {"tensor(float)": np.float32, "tensor(uint8)": np.uint8, "tensor(uint16)": np.uint16,
            "tensor(double)": np.float64, "tensor(int64)": np.int64}.get(onnx_type, np.float32)


def run_sequence(policy: OnnxPolicy, observations: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Step ``policy`` through recorded observations, one call per step, as in flight.

    Args:
        observations: per input name ``(T, ...)`` (one drone) or ``(T, B, ...)``; optional
            ``episode_start`` ``(T,)`` or ``(T, B)`` bools (reset the recurrent state before that step).

    Returns:
        ``action`` and ``command`` shaped ``(T, [B,] 4)``, ``latency_ms`` ``(T,)``.
    """
    missing = [n for n in policy.observation_names if n not in observations]
    if missing:
        raise KeyError(f"the observations lack the policy's inputs {missing}; they hold {sorted(observations)}")
    first = policy.observation_names[0]
    spec = next((i for i in policy.metadata.get("inputs", []) if i["name"] == first), None)
    rank = len(spec["shape"]) if spec is not None else len(policy.session.get_inputs()[0].shape) - 1
    single = observations[first].ndim == rank + 1
    steps = len(observations[first])
    starts = observations.get("episode_start")
    actions, latency = [], np.zeros(steps)
    policy.reset()
    for t in range(steps):
        obs = {n: observations[n][t][None] if single else observations[n][t] for n in policy.observation_names}
        if starts is not None and t > 0:
            policy.reset(np.atleast_1d(starts[t]))
        t0 = time.perf_counter()
        action = policy.act(obs)
        latency[t] = (time.perf_counter() - t0) * 1e3
        actions.append(action[0] if single else action)
    action = np.stack(actions).astype(np.float32)
    return {"action": action, "command": policy.command(action), "latency_ms": latency}


def describe(policy: OnnxPolicy) -> str:
    meta = policy.metadata
    lines = [f"task {meta.get('task', '?')}, controller {meta.get('controller', '?')}, "
             f"{policy.control_rate_hz or '?'} Hz, recurrent: {policy.recurrent}"]
    for spec in meta.get("inputs", []):
        lines.append(f"  in  {spec['name']:<10} {spec['dtype']:<8} {spec['shape']}: {spec['doc']}")
    for spec in meta.get("outputs", []):
        lines.append(f"  out {spec['name']:<10} {spec['dtype']:<8} {spec['shape']}: {spec['doc']}")
    if "action_mapping" in meta:
        lines.append(f"  command: {meta['action_mapping']['text']}")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("model", help="the .onnx file written by 'visfly-dist export'")
    parser.add_argument("--observations", metavar="FILE.npz", help="recorded observations, one array per input name")
    parser.add_argument("--out", metavar="FILE.npz", help="write action, command and latency_ms here")
    parser.add_argument("--describe", action="store_true", help="print the inputs, outputs, rate and command mapping")
    parser.add_argument("--threads", type=int, default=1, help="onnxruntime threads (default 1)")
    args = parser.parse_args(argv)
    policy = OnnxPolicy(args.model, threads=args.threads)
    if args.describe or not args.observations:
        print(describe(policy))
    if args.observations:
        with np.load(args.observations, allow_pickle=False) as data:
            observations = {k: data[k] for k in data.files}
        try:
            result = run_sequence(policy, observations)
        except KeyError as exc:
            parser.error(f"{args.observations}: {exc.args[0]}")
        lat = result["latency_ms"]
        budget = f" (budget {1e3 / policy.control_rate_hz:.1f} ms per step)" if policy.control_rate_hz else ""
        print(f"{len(lat)} steps, latency median {np.median(lat):.3f} ms, max {lat.max():.3f} ms{budget}")
        if args.out:
            np.savez(args.out, **result)
            print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
