"""visfly-dist: a distributed simulator for vision-based quadrotor reinforcement learning."""

__version__ = "0.1.0"


def __getattr__(name: str):
    # ``make_env`` pulls in torch, SB3 and Zenoh; import it only when asked for.
    if name == "make_env":
        from visfly_dist.tasks import make_env

        return make_env
    raise AttributeError(f"module 'visfly_dist' has no attribute {name!r}")
