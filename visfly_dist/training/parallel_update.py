"""PPO's update with each minibatch split across threads (data parallel on one host).

SB3's update runs each minibatch's forward and backward pass as one batch; with several torch
threads, every operator of the small image CNN is split across OpenMP threads, which meet at a
barrier after each operator. On a 2-core host those barriers cost much of the gain, and on a
loaded host a barrier waits for a core that other work holds (updates measured 3-10x slower).

Here each minibatch is cut into ``shards`` contiguous parts. Every part runs its own forward and
backward pass on its own Python thread with one torch thread (torch releases the GIL inside its
kernels), and the gradients accumulate into the shared parameters (autograd serialises that per
parameter). The threads meet once per minibatch, not once per operator. Each part's loss is its
share of the minibatch's loss (its terms summed and divided by the minibatch size), so the summed
gradient is the minibatch's gradient: the same update as SB3's ``PPO.train``, up to float rounding
order. Advantages are normalised over the whole minibatch first, as SB3 does.

The action distribution is rebuilt per part from a shallow copy of the policy's, because SB3's
``evaluate_actions`` stores the distribution on the shared policy object, which two threads would
overwrite under each other.
"""

from __future__ import annotations

import copy
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, replace
from typing import Any, Callable

import numpy as np
import torch
import torch.nn.functional as F
from gymnasium import spaces
from stable_baselines3.common.distributions import DiagGaussianDistribution, Distribution, StateDependentNoiseDistribution
from stable_baselines3.common.policies import ActorCriticPolicy
from stable_baselines3.common.utils import explained_variance

from visfly_dist.errors import ConfigError


@dataclass
class ShardStats:
    """Sums over one part of a minibatch (divide by the minibatch size for means), as 0-dim tensors
    on the policy's device: reading one back waits for the device to finish, so an update on a GPU
    reads them once, at its end (:func:`mean_stats`), not after every minibatch."""

    policy_loss: torch.Tensor
    value_loss: torch.Tensor
    entropy_loss: torch.Tensor
    clipped: torch.Tensor
    approx_kl: torch.Tensor


def mean_stats(stats: list[ShardStats]) -> dict[str, float]:
    """Each field's mean over ``stats`` (one read-back from the device)."""
    names = list(ShardStats.__dataclass_fields__)
    table = torch.stack([torch.stack([getattr(s, name).float() for name in names]) for s in stats])
    return dict(zip(names, table.mean(dim=0).tolist()))


@dataclass
class UpdateSettings:
    """What one PPO update needs besides the policy and the buffer (SB3's attributes, evaluated)."""

    clip_range: float
    clip_range_vf: float | None
    ent_coef: float
    vf_coef: float
    normalize_advantage: bool


def evaluate_actions(policy: ActorCriticPolicy, obs: Any, actions: torch.Tensor,
                     dist: Distribution) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """``policy.evaluate_actions`` with the action distribution kept in ``dist`` (a per-thread copy)."""
    features = policy.extract_features(obs)
    if policy.share_features_extractor:
        latent_pi, latent_vf = policy.mlp_extractor(features)
    else:
        pi_features, vf_features = features
        latent_pi = policy.mlp_extractor.forward_actor(pi_features)
        latent_vf = policy.mlp_extractor.forward_critic(vf_features)
    mean_actions = policy.action_net(latent_pi)
    if isinstance(dist, DiagGaussianDistribution):
        dist.proba_distribution(mean_actions, policy.log_std)
    elif isinstance(dist, StateDependentNoiseDistribution):
        dist.proba_distribution(mean_actions, policy.log_std, latent_pi)
    else:
        dist.proba_distribution(action_logits=mean_actions)
    return policy.value_net(latent_vf), dist.log_prob(actions), dist.entropy()


def shard_loss_backward(policy: ActorCriticPolicy, data: Any, advantages: torch.Tensor, rows: slice,
                        batch_size: int, settings: UpdateSettings, discrete: bool) -> ShardStats:
    """Forward and backward pass of rows ``rows`` of a minibatch; gradients accumulate in ``policy``."""
    obs = {k: v[rows] for k, v in data.observations.items()} if isinstance(data.observations, dict) else data.observations[rows]
    actions = data.actions[rows]
    if discrete:
        actions = actions.long().flatten()
    values, log_prob, entropy = evaluate_actions(policy, obs, actions, copy.copy(policy.action_dist))
    values = values.flatten()
    adv = advantages[rows]
    old_log_prob = data.old_log_prob[rows]
    ratio = torch.exp(log_prob - old_log_prob)
    clip = settings.clip_range
    policy_loss = -torch.min(adv * ratio, adv * torch.clamp(ratio, 1 - clip, 1 + clip)).sum() / batch_size
    old_values = data.old_values[rows]
    values_pred = values if settings.clip_range_vf is None else (
        old_values + torch.clamp(values - old_values, -settings.clip_range_vf, settings.clip_range_vf))
    value_loss = F.mse_loss(data.returns[rows], values_pred, reduction="sum") / batch_size
    entropy_loss = (log_prob.sum() if entropy is None else -entropy.sum()) / batch_size
    loss = policy_loss + settings.ent_coef * entropy_loss + settings.vf_coef * value_loss
    loss.backward()
    with torch.no_grad():
        log_ratio = log_prob - old_log_prob
        approx_kl = ((torch.exp(log_ratio) - 1) - log_ratio).sum()
        clipped = (torch.abs(ratio - 1) > clip).float().sum()
    return ShardStats(policy_loss.detach(), value_loss.detach(), entropy_loss.detach(), clipped, approx_kl)


def shard_slices(size: int, shards: int) -> list[slice]:
    """``shards`` contiguous, near-equal, non-empty slices covering ``range(size)`` (fewer if ``size < shards``)."""
    if shards < 1:
        raise ConfigError(f"shards={shards} must be >= 1")
    bounds = np.linspace(0, size, min(shards, size) + 1).round().astype(int)
    return [slice(int(a), int(b)) for a, b in zip(bounds[:-1], bounds[1:]) if b > a]


def minibatch_gradients(policy: ActorCriticPolicy, data: Any, settings: UpdateSettings, discrete: bool,
                        pool: ThreadPoolExecutor | None, shards: int) -> ShardStats:
    """Gradients of one minibatch accumulated into ``policy`` (zero them first), its ``shards`` parts
    run on the calling thread and ``pool`` (``None`` for one part); returns the loss terms (means)
    and the clipped share and KL."""
    batch_size = len(data.advantages)
    advantages = data.advantages
    if settings.normalize_advantage and batch_size > 1:
        advantages = (advantages - advantages.mean()) / (advantages.std() + 1e-8)
    parts = shard_slices(batch_size, shards)

    def run(rows: slice) -> ShardStats:
        return shard_loss_backward(policy, data, advantages, rows, batch_size, settings, discrete)

    futures = [pool.submit(run, rows) for rows in parts[1:]] if pool is not None else []
    results = [run(parts[0])] + [f.result() for f in futures]
    total = ShardStats(*(sum(getattr(r, name) for r in results) for name in ShardStats.__dataclass_fields__))
    return replace(total, clipped=total.clipped / batch_size, approx_kl=total.approx_kl / batch_size)


def sharded_ppo_train(model: Any, shards: int) -> None:
    """SB3 ``PPO.train`` with each minibatch's passes split over ``shards`` threads: same steps, same logs.

    Run it with one torch thread (``torch.set_num_threads(1)``): the parallelism is the shards'.
    """
    if shards < 1:
        raise ConfigError(f"shards={shards} must be >= 1")
    policy = model.policy
    policy.set_training_mode(True)
    model._update_learning_rate(policy.optimizer)
    progress = model._current_progress_remaining
    settings = UpdateSettings(
        clip_range=float(model.clip_range(progress)),
        clip_range_vf=None if model.clip_range_vf is None else float(model.clip_range_vf(progress)),
        ent_coef=float(model.ent_coef), vf_coef=float(model.vf_coef), normalize_advantage=model.normalize_advantage)
    discrete = isinstance(model.action_space, spaces.Discrete)
    stats: list[ShardStats] = []
    approx_kl: list[float] = []  # of the last epoch, as SB3 logs it
    pool = ThreadPoolExecutor(max_workers=shards - 1, thread_name_prefix="ppo-shard") if shards > 1 else None
    try:
        for epoch in range(model.n_epochs):
            approx_kl = []
            stop = False
            for data in model.rollout_buffer.get(model.batch_size):
                policy.optimizer.zero_grad()
                batch = minibatch_gradients(policy, data, settings, discrete, pool, shards)
                stats.append(batch)
                kl = float(batch.approx_kl)
                approx_kl.append(kl)
                if model.target_kl is not None and kl > 1.5 * model.target_kl:
                    stop = True
                    if model.verbose >= 1:
                        print(f"Early stopping at step {epoch} due to reaching max kl: {kl:.2f}")
                    break
                torch.nn.utils.clip_grad_norm_(policy.parameters(), model.max_grad_norm)
                policy.optimizer.step()
            model._n_updates += 1
            if stop:
                break
    finally:
        if pool is not None:
            pool.shutdown(wait=True)
    buffer, last, means = model.rollout_buffer, mean_stats(stats[-1:]), mean_stats(stats)
    record: Callable[..., None] = model.logger.record
    record("train/entropy_loss", means["entropy_loss"])
    record("train/policy_gradient_loss", means["policy_loss"])
    record("train/value_loss", means["value_loss"])
    record("train/approx_kl", np.mean(approx_kl))
    record("train/clip_fraction", means["clipped"])
    record("train/loss", last["policy_loss"] + settings.ent_coef * last["entropy_loss"] + settings.vf_coef * last["value_loss"])
    record("train/explained_variance", explained_variance(buffer.values.flatten(), buffer.returns.flatten()))
    if hasattr(policy, "log_std"):
        record("train/std", torch.exp(policy.log_std).mean().item())
    record("train/n_updates", model._n_updates, exclude="tensorboard")
    record("train/clip_range", settings.clip_range)
    if settings.clip_range_vf is not None:
        record("train/clip_range_vf", settings.clip_range_vf)
