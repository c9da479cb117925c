"""The rollout's policy forward replayed from CUDA graphs: one launch instead of ~100 per step.

At the rollout's batch sizes (64 to 256 agents) the policy's forward on a GPU is a hundred small
kernels (the image trunk, the two MLPs, the Gaussian's sample and log-probability), each a few
microseconds of work and tens of microseconds of Python and launch: about 3 ms a step on an H200,
a fifth of the learner's time per step. Captured once per batch size in a CUDA graph
(``torch.cuda.graphs``), a step copies its observation into the graph's input tensors and replays
it. The graph reads the parameters where they live, so the optimizer's in-place updates are seen;
the Gaussian's noise comes from the CUDA generator, which advances on every replay.

Only rollouts without gradients use it (``TensorPPO._act``); anything that cannot be captured
(a CPU policy, an extractor that syncs with the host, a torch without graphs) runs eagerly, and a
failed capture says why once. ``VISFLY_CUDA_GRAPHS=0`` keeps every forward eager.

A replay runs no Python: anything the forward computes from the parameters and keeps on the Python
side would stay as it was at the capture (the CPU's phase form of the first convolution keeps its
kernel so, :func:`~visfly_dist.training.conv_pool.phase_params`; a GPU runs the plain form). After every update,
:meth:`GraphedForward.verify` replays each graph and compares it with the eager policy on the same
observations; on a mismatch the graphs are dropped and the rollout goes eager, saying so.
"""

from __future__ import annotations

import contextlib
import os
from typing import Any, Callable, Iterator

import torch
from stable_baselines3.common.policies import ActorCriticPolicy

MAX_GRAPHS = 4
"""Batch sizes captured at most (a rollout has one or two: everyone, or the two groups)."""
WARMUP_CALLS = 3
"""Eager calls on a side stream before a capture (cuDNN picks its algorithms, caches fill)."""
VERIFY_TOLERANCE = 1e-2
"""Relative and absolute tolerance of :meth:`GraphedForward.verify` on values and log-probabilities
(TF32 convolutions differ in the last bits; a stale layer differs by far more)."""

DISABLE_ENV = "VISFLY_CUDA_GRAPHS"

Outputs = tuple[torch.Tensor, torch.Tensor, torch.Tensor]


class GraphedForward:
    """``policy(obs)`` -> ``(actions, values, log_probs)`` without gradients, from CUDA graphs.

    Args:
        policy: SB3 actor-critic policy (called as ``policy(obs)``).
        log: receives one line when a capture or a check fails (the reason) and the forward goes eager.
    """

    def __init__(self, policy: ActorCriticPolicy, log: Callable[[str], None] = print) -> None:
        self.policy = policy
        self.log = log
        self._graphs: dict[tuple[Any, ...], tuple[torch.cuda.CUDAGraph, dict[str, torch.Tensor], Outputs]] = {}
        self.disabled: str | None = f"disabled by {DISABLE_ENV}=0" if os.environ.get(DISABLE_ENV) == "0" else None

    def __call__(self, obs: dict[str, torch.Tensor]) -> Outputs:
        """The policy's outputs for ``obs`` (fresh tensors); eager unless on CUDA without grad."""
        first = next(iter(obs.values()))
        if self.disabled is not None or first.device.type != "cuda" or torch.is_grad_enabled():
            return self.policy(obs)
        key = tuple((k, tuple(v.shape), v.dtype) for k, v in obs.items())
        entry = self._graphs.get(key)
        if entry is None:
            if len(self._graphs) >= MAX_GRAPHS:
                return self.policy(obs)
            entry = self._capture(key, obs)
            if entry is None:
                return self.policy(obs)
        graph, inputs, outputs = entry
        for k, v in obs.items():
            inputs[k].copy_(v)
        graph.replay()
        return outputs[0].clone(), outputs[1].clone(), outputs[2].clone()

    def verify(self) -> bool:
        """Replay every graph on its last observations and compare with the eager policy there
        (values, and the log-probabilities of the replay's actions); on a mismatch drop the graphs
        and go eager. Call it after parameter updates. Returns whether the graphs (if any) agree."""
        with torch.no_grad():
            for graph, inputs, outputs in self._graphs.values():
                graph.replay()
                actions, values, log_probs = (o.clone() for o in outputs)
                eager_values, eager_log_probs, _ = self.policy.evaluate_actions(inputs, actions)
                if not (torch.allclose(values, eager_values, VERIFY_TOLERANCE, VERIFY_TOLERANCE)
                        and torch.allclose(log_probs, eager_log_probs, VERIFY_TOLERANCE, VERIFY_TOLERANCE)):
                    worst = float(torch.max((values - eager_values).abs().max(), (log_probs - eager_log_probs).abs().max()))
                    self.disabled = f"a replay differed from the eager policy by up to {worst:.3g} after an update"
                    self.log(f"policy forward: {self.disabled}; the rollout runs it eagerly from now on")
                    self._graphs.clear()
                    return False
        return True

    def _capture(self, key: tuple[Any, ...], obs: dict[str, torch.Tensor]) -> Any:
        inputs = {k: v.detach().clone() for k, v in obs.items()}
        try:
            with _no_distribution_checks():
                side = torch.cuda.Stream()
                side.wait_stream(torch.cuda.current_stream())
                with torch.cuda.stream(side):
                    for _ in range(WARMUP_CALLS):
                        self.policy(inputs)
                torch.cuda.current_stream().wait_stream(side)
                graph = torch.cuda.CUDAGraph()
                with torch.cuda.graph(graph):
                    outputs = self.policy(inputs)
        except (RuntimeError, AttributeError) as exc:  # e.g. a host sync inside the forward
            self.disabled = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
            self.log(f"policy forward: CUDA graph capture failed, the rollout runs it eagerly ({self.disabled})")
            return None
        self._graphs[key] = (graph, inputs, outputs)
        return self._graphs[key]


@contextlib.contextmanager
def _no_distribution_checks() -> Iterator[None]:
    """torch.distributions' argument checks read values back to the host (``if not valid.all()``),
    which a capture forbids; the policy's Gaussian is built from finite means and a positive std."""
    before = torch.distributions.Distribution._validate_args
    torch.distributions.Distribution.set_default_validate_args(False)
    try:
        yield
    finally:
        torch.distributions.Distribution.set_default_validate_args(before)
