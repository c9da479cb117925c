"""Training on visfly-dist envs: feature extractors, PPO runs, evaluation and videos.

- ``extractors``: ``VisflyExtractor`` (per-entry CNN/MLP encoders for Dict observations) and
  ``visfly_policy_kwargs()`` for any SB3 ``MultiInputPolicy``;
- ``config`` / ``ppo`` / ``train_cli``: ``visfly-dist train TASK`` (PPO with logs, checkpoints,
  success curve);
- ``bptt`` / ``shac`` / ``diff_common``: ``visfly-dist train TASK --algo bptt|shac``, training through
  the differentiable dynamics (``train_bptt(TrainConfig(...))`` / ``train_shac`` from Python);
- ``evaluation`` / ``video`` / ``eval_cli``: ``visfly-dist eval TASK --checkpoint PATH``;
- ``callbacks`` / ``checkpoints``: the pieces a run is made of.

Training with your own algorithm::

    from stable_baselines3 import PPO
    from visfly_dist import make_env
    from visfly_dist.training.extractors import visfly_policy_kwargs

    env = make_env("navigation", num_envs=100)
    model = PPO("MultiInputPolicy", env, policy_kwargs=visfly_policy_kwargs())
    model.learn(1_000_000)
    env.close()
"""
