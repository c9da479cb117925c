"""What a lost agent is given: the last rows it was served, whatever groups and partial steps came
between, and never by writing into an observation handed out."""

from __future__ import annotations

import numpy as np

from visfly_dist.aggregator.assembler import LastGood, empty_observation
from visfly_dist.protocol.cameras import CameraSpec

CAMERA = CameraSpec(name="depth", kind="depth", width=4, height=3)
N = 6


def _observation(agents: np.ndarray, value: float):
    """Rows for ``agents``, each filled with ``value + agent`` (images and queries)."""
    obs = empty_observation([CAMERA], len(agents))
    fill = value + agents.astype(np.float32)
    obs.images["depth"][:] = fill[:, None, None, None]
    obs.collision[:] = agents % 2 == 0
    obs.inside[:] = False
    obs.nearest[:] = fill[:, None]
    obs.distance[:] = fill
    obs.lost[:] = False
    return obs


def _given(last: LastGood, agents: np.ndarray) -> np.ndarray:
    out = empty_observation([CAMERA], len(agents))
    last.fill(out, np.arange(len(agents)), agents)
    assert out.lost.all()
    np.testing.assert_array_equal(out.distance, out.images["depth"][:, 0, 0, 0])
    served = out.distance != CAMERA.far
    np.testing.assert_array_equal(out.nearest[served, 1], out.distance[served])
    return out.distance


def test_a_lost_agent_gets_its_last_served_rows_across_groups_and_partial_steps():
    last = LastGood([CAMERA], N, search_radius=CAMERA.far)
    everyone = np.arange(N)
    np.testing.assert_array_equal(_given(last, everyone), CAMERA.far)  # never served: nothing within reach
    a, b = np.array([0, 1, 2]), np.array([3, 4, 5])
    expected = np.full(N, CAMERA.far, np.float32)
    kept = []
    for step, (group, fresh_rows) in enumerate([(a, [0, 1, 2]), (b, [0, 2]), (a, [1]), (b, [0, 1, 2]),
                                                (a, [0, 2]), (np.array([1, 4]), [0, 1]), (b, [1])]):
        obs = _observation(group, 100.0 * (step + 1))
        rows = np.array(fresh_rows)
        kept.append((obs, obs.distance.copy(), obs.images["depth"].copy()))
        last.remember(obs, rows, group[rows])
        expected[group[rows]] = 100.0 * (step + 1) + group[rows]
        if step in (3, 6):  # asking writes what was kept so far into the private copy
            np.testing.assert_array_equal(_given(last, everyone), expected)
    full = _observation(everyone, 1000.0)
    last.remember(full, everyone, everyone)
    last.remember(_observation(a, 2000.0), np.array([0]), a[:1])
    np.testing.assert_array_equal(_given(last, everyone), [2000.0, 1001, 1002, 1003, 1004, 1005])
    np.testing.assert_array_equal(full.distance, 1000.0 + everyone)  # the full observation handed out is kept as it was
    for obs, distance, images in kept:
        np.testing.assert_array_equal(obs.distance, distance)
        np.testing.assert_array_equal(obs.images["depth"], images)
