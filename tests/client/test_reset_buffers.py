"""Reset steps merge images into reused buffers: never one a caller still holds, and the held
observation and terminal observation stay as they were handed out."""

import gc

import numpy as np
import pytest
import torch

from tests.client.counter_task import make_counter
from visfly_dist.client.buffer_pool import BufferPool
from visfly_dist.errors import ConfigError


@pytest.fixture(scope="module")
def env():
    env = make_counter(seed=5)
    yield env
    env.close()


def hover(env):
    return torch.as_tensor(np.tile(env.quad.hover_action().numpy(), (env.num_envs, 1)))


def reset_step(env, agent):
    """One step in which ``agent`` succeeds (and is reset)."""
    env.force_success[agent] = True
    try:
        return env.step_tensor(hover(env))
    finally:
        env.force_success[:] = False


def pooled(env, image: torch.Tensor) -> bool:
    return any(np.shares_memory(image.numpy(), b.memory) for b in env._image_buffers._buffers)


def test_held_observations_stay_intact_across_later_reset_steps(env):
    env.reset()
    env.step_tensor(hover(env))
    held = []
    for i in range(6):  # more than the pool keeps, every one held
        result = reset_step(env, i % env.num_envs)
        held.append((result.observation, result.info["terminal_observation"],
                     result.observation["depth"].clone(), result.info["terminal_observation"]["depth"].clone()))
        env.step_tensor(hover(env))
    assert len({obs["depth"].data_ptr() for obs, *_ in held}) == len(held)  # no buffer handed out twice
    for obs, terminal, depth, terminal_depth in held:
        assert torch.equal(obs["depth"], depth) and torch.equal(terminal["depth"], terminal_depth)
    # the merge itself: the reset row changed, the others are the terminal observation's
    obs, terminal, *_ = held[1]
    assert obs["step"][:, 0].tolist()[1] == 0 and terminal["step"][1, 0] > 0
    assert torch.equal(obs["depth"][[0, 2, 3]], terminal["depth"][[0, 2, 3]])


def test_a_buffer_is_reused_once_nothing_holds_it(env):
    env.reset()
    env.step_tensor(hover(env))
    first = reset_step(env, 0).observation["depth"]
    assert pooled(env, first)
    ptr = first.data_ptr()
    env.step_tensor(hover(env))  # the env's own frame lets go of it
    assert reset_step(env, 1).observation["depth"].data_ptr() != ptr  # still held here (``first``)
    env.step_tensor(hover(env))
    view = first.numpy()[1:]  # a numpy view of the tensor holds it too
    del first
    assert reset_step(env, 2).observation["depth"].data_ptr() != ptr
    env.step_tensor(hover(env))
    del view
    assert reset_step(env, 3).observation["depth"].data_ptr() == ptr


def test_terminal_observation_rows_of_done_agents_survive_the_next_reset_steps(env):
    env.reset()
    env.step_tensor(hover(env))
    obs, _, done, infos = env.to_sb3(reset_step(env, 2))
    term = infos[2]["terminal_observation"]["depth"].copy()
    kept = {k: v.copy() for k, v in obs.items()}
    for i in range(3):
        env.to_sb3(reset_step(env, i))
    assert done.tolist() == [False, False, True, False]
    assert np.array_equal(infos[2]["terminal_observation"]["depth"], term)
    assert all(np.array_equal(obs[k], kept[k]) for k in kept)


def test_pool_reuses_only_free_buffers_and_stays_bounded():
    pool = BufferPool(size=2)
    a = pool.take((3, 4), torch.float32)
    ptr = a.data_ptr()
    b = a[1:]  # a tensor view holds the buffer
    del a
    assert pool.take((3, 4), torch.float32).data_ptr() != ptr
    del b
    assert pool.take((3, 4), torch.float32).data_ptr() == ptr
    assert pool.take((3, 4), torch.int32).dtype == torch.int32  # another dtype: another buffer
    held = [pool.take((3, 4), torch.float32) for _ in range(5)]
    assert len(pool._buffers) == 2 and len({t.data_ptr() for t in held}) == 5


@pytest.mark.parametrize("keep", [
    lambda t: t,                              # the tensor itself
    lambda t: t[1:],                          # a torch view
    lambda t: t.numpy(),                      # a numpy array over it
    lambda t: t.numpy()[2:, 1],               # a slice of that
    lambda t: torch.from_numpy(t.numpy()[1:]),  # a tensor made again with torch.from_numpy
    lambda t: [{"obs": t.view(-1)}],          # deep inside a container
    lambda t: (lambda: t),                    # in a closure
])
def test_a_held_buffer_is_never_handed_out_again_and_a_released_one_is_reused(keep):
    pool = BufferPool(size=1)
    first = pool.take((3, 4), torch.float32)
    first.fill_(7.0)
    memory = pool._buffers[0].memory
    kept = keep(first)
    extra = [kept, kept]  # more references change nothing: ownership is the lease, not a count
    del first
    second = pool.take((3, 4), torch.float32)
    assert not np.shares_memory(second.numpy(), memory)
    second.fill_(-1.0)
    assert (memory == 7.0).all()  # the held one is as it was handed out
    del kept, extra, second
    gc.collect()
    assert pool._buffers[0].memory is not memory  # the pool kept the newest buffer (size 1)
    reused = pool._buffers[0].memory
    third = pool.take((3, 4), torch.float32)
    assert np.shares_memory(third.numpy(), reused) and len(pool._buffers) == 1  # no new allocation


def test_terminal_ended_gives_the_same_step_with_only_the_ended_rows_and_no_image_copy(env):
    """``terminal="ended"`` (the tensor PPO's path): the same observation, rewards and flags as a
    plain step, the terminal rows of exactly the agents that ended, the reset written into the
    step's own images (no pooled copy), and an observation handed out before left as it was."""
    twin = make_counter(seed=5)
    try:
        for e in (env, twin):
            e.reset_tensor(seeds=[11, 12, 13, 14])
            e.step_tensor(hover(e))
        for ended in ([2], [0, 3], [], [1]):
            held = env.step_tensor(hover(env), terminal="ended").observation
            held_depth = held["depth"].clone()
            twin.step_tensor(hover(twin))
            for e in (env, twin):
                e.force_success[ended] = True
            try:
                full = twin.step_tensor(hover(twin))
                rows = env.step_tensor(hover(env), terminal="ended")
            finally:
                env.force_success[:] = twin.force_success[:] = False
            assert torch.equal(rows.terminated | rows.truncated, full.terminated | full.truncated)
            done = (rows.terminated | rows.truncated).nonzero().squeeze(1)
            assert set(ended) <= set(done.tolist())  # and those whose time ran out
            for k in full.observation:
                assert torch.equal(rows.observation[k], full.observation[k]), k
                assert torch.equal(rows.info["terminal_observation"][k], full.info["terminal_observation"][k][done]), k
            assert torch.equal(rows.reward, full.reward)
            assert not pooled(env, rows.observation["depth"])
            assert torch.equal(held["depth"], held_depth)
        with pytest.raises(ConfigError, match="terminal="):
            env.step_tensor(hover(env), terminal="some")
    finally:
        twin.close()
