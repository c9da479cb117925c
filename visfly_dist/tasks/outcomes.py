"""Why an episode ended: one cause per finished episode, read from the step info.

| cause           | when                                                                        |
|-----------------|-----------------------------------------------------------------------------|
| ``success``     | the task's success state (``is_success``)                                   |
| ``collision``   | touched an obstacle (or, in team tasks, a teammate)                          |
| ``out_of_bounds`` | left the flight region (the scene's box; hover and tracking add a distance to the target) |
| ``lost``        | no scene worker answered for the agent                                      |
| ``failure``     | another task failure (inside an obstacle, landing pad lost from view)       |
| ``time_limit``  | ``max_episode_steps`` reached                                               |
| ``swapped``     | the agent's scene was replaced, or a teammate's episode ended (team tasks)  |

The first matching row wins, top to bottom.
"""

from __future__ import annotations

from typing import Any, Mapping

END_CAUSES = ("success", "collision", "out_of_bounds", "lost", "failure", "time_limit", "swapped")
"""Every cause :func:`end_cause` returns."""


def end_cause(info: Mapping[str, Any], episode_length: int | None = None, max_episode_steps: int | None = None) -> str:
    """The cause of the episode that ended with the SB3 step ``info`` of one agent.

    Args:
        info: the agent's info dict from ``VecEnv.step`` at its ``done``.
        episode_length: steps of the episode (tells a time limit from other truncations).
        max_episode_steps: the env's episode limit.
    """
    if info.get("is_success"):
        return "success"
    if info.get("collision"):
        return "collision"
    if info.get("out_of_bounds"):
        return "out_of_bounds"
    if info.get("lost"):
        return "lost"
    if not info.get("TimeLimit.truncated"):
        return "failure"
    if episode_length is None or max_episode_steps is None or episode_length >= max_episode_steps:
        return "time_limit"
    return "swapped"
