"""Tasks: navigation, hover, landing, gap crossing (multi-agent), racing; ``make_env`` builds them by name."""

from visfly_dist.tasks.registry import TASKS, make_env, task_class

__all__ = ["TASKS", "make_env", "task_class"]
