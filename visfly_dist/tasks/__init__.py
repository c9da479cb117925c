"""Tasks: navigation, hover, landing, gap crossing (multi-agent), racing, tracking; ``make_env`` builds them by name.

``outcomes.end_cause`` names why an episode ended. ``docs/TASKS.md`` compares every task with VisFly's.
"""

from visfly_dist.tasks.registry import TASKS, make_env, task_class

__all__ = ["TASKS", "make_env", "task_class"]
