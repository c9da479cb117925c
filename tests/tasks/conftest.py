"""The task envs shared by the task tests (built on first use, closed at the end of the session)."""

import pytest

from visfly_dist import make_env
from tests.tasks.helpers import SETTINGS


@pytest.fixture(scope="session")
def envs():
    """Task name -> its small env (``helpers.SETTINGS``), built on first use."""
    built = {}

    def get(name):
        if name not in built:
            settings = dict(SETTINGS[name])
            built[name] = make_env(name, num_envs=settings.pop("num_envs"), seed=1, **settings)
        return built[name]

    yield get
    for env in built.values():
        env.close()
