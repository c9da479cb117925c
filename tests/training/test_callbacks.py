"""SuccessCallback's figures from step infos (pure logic: the callback is fed SB3's step locals)."""

from types import SimpleNamespace

import numpy as np

from visfly_dist.training.callbacks import SuccessCallback


def _fed(tmp_path, steps):
    callback = SuccessCallback(tmp_path, total_timesteps=100, verbose=0)
    env = SimpleNamespace(unwrapped=SimpleNamespace(config=SimpleNamespace(max_episode_steps=50)))
    callback.model = SimpleNamespace(get_env=lambda: env)
    for infos in steps:
        callback.locals = {"dones": np.ones(len(infos), dtype=bool), "infos": infos}
        callback._on_step()
    return callback


def _end(length, **flags):
    return {"episode": {"r": float(length), "l": length, "t": 0.0}, "TimeLimit.truncated": flags.pop("cut", False), **flags}


def test_episodes_cut_by_a_lost_worker_stay_out_of_the_figures(tmp_path):
    outage = [[_end(1, lost=True, cut=True)] * 4] * 10  # a worker down for ten steps: forty one-step episodes
    callback = _fed(tmp_path, [[_end(20, is_success=True), _end(30, collision=True)], *outage])
    assert callback.summary() == {"success_rate": 0.5, "mean_return": 25.0, "mean_length": 25.0}
    assert (callback.episodes_total, callback.lost_total) == (2, 40)
    shares = callback.cause_shares()  # the outage still shows among the end causes
    assert shares["lost"] == 40 / 42 and shares["success"] == 1 / 42
