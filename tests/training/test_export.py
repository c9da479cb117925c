"""``visfly-dist export`` and ``deploy/onnx_runner.py``: the ONNX actor acts as the torch policy does.

For each PPO task whose observations differ, a PPO model is built as ``visfly-dist train`` builds it
(``build_env`` / ``build_model``: VecNormalize statistics gathered over a real rollout), saved as a
checkpoint, exported by the command, and the standalone runner (a subprocess in which importing torch
or visfly_dist fails) steps through 200 recorded real observations. Its actions must equal the torch
policy's deterministic ones (normalisation and clipping included) to 1e-5.
"""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from visfly_dist.cli import main
from visfly_dist.errors import ConfigError
from visfly_dist.training.checkpoints import save_checkpoint
from visfly_dist.training.config import TrainConfig
from visfly_dist.training.export import ObsNormalization, action_mapping, export_policy, read_metadata
from visfly_dist.training.ppo import build_env, build_model, write_config

REPO = Path(__file__).resolve().parents[2]
RUNNER = REPO / "deploy" / "onnx_runner.py"
OBSERVATIONS = 200
TASKS = {"navigation": 2, "hover": 2, "tracking": 2, "gap_crossing": 3, "landing": 2, "racing": 2, "navigation_moving": 2}
"""Task -> agents (gap crossing flies teams of 3): every registered task."""

NO_TORCH = ("import runpy, sys\n"
            "for name in ('torch', 'visfly_dist', 'stable_baselines3'):\n"
            "    sys.modules[name] = None  # importing them now fails\n"
            "sys.argv = sys.argv[1:]\n"
            "runpy.run_path(sys.argv[0], run_name='__main__')\n")


def run_runner(*args: str) -> subprocess.CompletedProcess:
    """``python deploy/onnx_runner.py ARGS`` in a fresh interpreter where torch cannot be imported."""
    return subprocess.run([sys.executable, "-c", NO_TORCH, str(RUNNER), *args], capture_output=True, text=True,
                          timeout=120, check=True)


@pytest.fixture(scope="module", params=list(TASKS))
def recorded(request: pytest.FixtureRequest, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A checkpoint of ``task`` (real normalisation statistics), 200 raw observations of its real env,
    and the torch policy's deterministic actions on them."""
    task, n = request.param, TASKS[request.param]
    run_dir = tmp_path_factory.mktemp(f"export-{task}")
    cfg = TrainConfig(task=task, num_envs=n, n_steps=16, batch_size=16, seed=3, out=str(run_dir), workers=1,
                      backend="raycast", algo="ppo", progress=False).resolved().validate()
    env = build_env(cfg)
    try:
        model = build_model(cfg, env)
        with torch.no_grad():  # larger actions than a fresh policy's (std 0.01 init), so that clipping to [-1, 1] shows
            model.policy.action_net.weight.normal_(0.0, 1.0, generator=torch.Generator().manual_seed(5))
        steps = math.ceil(OBSERVATIONS / n)
        raw: list[dict[str, np.ndarray]] = []
        obs = env.reset()
        for _ in range(steps):  # sampled actions: varied flight; VecNormalize learns its statistics meanwhile
            raw.append(env.get_original_obs())
            actions, _ = model.predict(obs, deterministic=False)
            obs, _, _, _ = env.step(actions)
        env.training = False
        write_config(cfg, run_dir)
        checkpoint = save_checkpoint(model, run_dir / "final.zip")
        expected = np.stack([model.predict(env.normalize_obs(o), deterministic=True)[0] for o in raw])
        stats = {k: (rms.mean.copy(), rms.var.copy()) for k, rms in env.obs_rms.items()}
    finally:
        env.close()
    observations = {k: np.stack([o[k] for o in raw]) for k in raw[0]}
    np.savez(run_dir / "observations.npz", **observations)
    return dict(task=task, n=n, run_dir=run_dir, checkpoint=checkpoint, expected=expected, stats=stats,
                observations=observations, ctrl_dt=float(env.unwrapped.config.ctrl_dt))


def test_runner_matches_the_torch_policy(recorded: dict) -> None:
    run_dir, task = recorded["run_dir"], recorded["task"]
    out = run_dir / "policy.onnx"
    assert main(["export", task, "--checkpoint", str(recorded["checkpoint"]), "--out", str(out)]) == 0
    result = run_runner(str(out), "--observations", str(run_dir / "observations.npz"), "--out", str(run_dir / "actions.npz"))
    assert "latency median" in result.stdout
    with np.load(run_dir / "actions.npz") as data:
        actions, command = data["action"], data["command"]
    expected = recorded["expected"]
    assert actions.shape == expected.shape == (math.ceil(OBSERVATIONS / recorded["n"]), recorded["n"], 4)
    assert expected.size // 4 >= OBSERVATIONS
    np.testing.assert_allclose(actions, expected, atol=1e-5, rtol=0)
    assert np.any(np.abs(expected) == 1.0) and np.any(np.abs(expected) < 0.99)  # clipped and unclipped actions
    # the statistics were not the identity (an entry that stayed constant in the short recording,
    # such as racing's gate progress, may keep them so; the state never does)
    mean, var = recorded["stats"]["state"]
    assert np.abs(mean).max() > 1e-3 and np.abs(var - 1).max() > 1e-2
    meta = read_metadata(out)
    np.testing.assert_allclose(command, np.asarray(meta["action_mapping"]["offset"])
                               + np.asarray(meta["action_mapping"]["scale"]) * actions, rtol=1e-9)


def test_metadata_documents_inputs_rate_and_command(recorded: dict) -> None:
    task, run_dir = recorded["task"], recorded["run_dir"]
    out = run_dir / "described.onnx"
    assert main(["export", task, "--checkpoint", str(recorded["checkpoint"]), "--out", str(out)]) == 0
    meta = read_metadata(out)
    names = [i["name"] for i in meta["inputs"]]
    assert names == sorted(recorded["observations"])
    assert meta["task"] == task and meta["ctrl_dt"] == pytest.approx(recorded["ctrl_dt"])
    assert meta["control_rate_hz"] == pytest.approx(1 / recorded["ctrl_dt"])
    assert meta["controller"] == ("lv" if task == "gap_crossing" else "ctbr")
    assert [o["name"] for o in meta["outputs"]] == ["action"] and not meta["recurrent"]
    for spec in meta["inputs"]:
        assert spec["shape"] == list(recorded["observations"][spec["name"]].shape[2:])
        assert spec["normalized_inside"] == (spec["name"] in recorded["stats"])
        assert spec["doc"] and "see the task" not in spec["doc"]
    if "depth" in names:
        depth = next(i for i in meta["inputs"] if i["name"] == "depth")
        assert "metres" in depth["doc"] and depth["dtype"] == "float32"
    described = run_runner(str(out), "--describe").stdout
    assert f"controller {meta['controller']}" in described and "command:" in described


@pytest.mark.parametrize("recorded", ["navigation"], indirect=True)   # one task is enough
def test_export_refuses_what_would_write_a_wrong_file(recorded: dict, tmp_path: Path, capsys) -> None:
    from visfly_dist.training.export import export_checkpoint

    task, checkpoint = recorded["task"], recorded["checkpoint"]
    other = "navigation" if task != "navigation" else "hover"
    with pytest.raises(ConfigError, match=rf"was trained on task '{task}' \(its config.json\), not '{other}'"):
        export_checkpoint(other, checkpoint, tmp_path / "x.onnx", env_settings={})
    assert main(["export", "hover", "--checkpoint", str(tmp_path / "missing.zip"), "--out", str(tmp_path / "x.onnx")]) == 2
    # a typo in --set would only fill the metadata (rate, controller): refused as training refuses it
    assert main(["export", task, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "x.onnx"),
                 "--set", "ctrl_dtt=0.02"]) == 2
    assert f"unknown setting(s) ['ctrl_dtt'] for task '{task}'" in capsys.readouterr().err
    assert main(["export", task, "--checkpoint", str(checkpoint), "--out", str(tmp_path / "x.onnx"), "--opset", "11"]) == 2
    assert "opset=11: the lowest checked against onnxruntime is 12" in capsys.readouterr().err
    copy = tmp_path / "copied"  # the model and its run's config.json, without final.norm.npz
    copy.mkdir()
    for name in ("final.zip", "config.json"):
        (copy / name).write_bytes((recorded["run_dir"] / name).read_bytes())
    assert main(["export", task, "--checkpoint", str(copy / "final.zip"), "--out", str(tmp_path / "x.onnx")]) == 2
    assert "final.norm.npz' is missing: the run trained on normalised observations" in capsys.readouterr().err
    (copy / "final.npz").write_bytes(b"")  # a BPTT/SHAC actor beside the run's config.json (normalize true)
    assert main(["export", task, "--checkpoint", str(copy / "final.npz"), "--out", str(tmp_path / "x.onnx")]) == 2
    assert "is a BPTT/SHAC actor (.npz): export takes PPO checkpoints (.zip) only" in capsys.readouterr().err
    assert not (tmp_path / "x.onnx").exists()


def test_the_runner_names_inputs_its_observations_lack(recorded: dict, tmp_path: Path) -> None:
    out = recorded["run_dir"] / "policy.onnx"
    if not out.exists():
        assert main(["export", recorded["task"], "--checkpoint", str(recorded["checkpoint"]), "--out", str(out)]) == 0
    renamed = {("State" if k == "state" else k): v for k, v in recorded["observations"].items()}
    np.savez(tmp_path / "renamed.npz", **renamed)
    done = subprocess.run([sys.executable, "-c", NO_TORCH, str(RUNNER), str(out), "--observations",
                           str(tmp_path / "renamed.npz")], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "Traceback" not in done.stderr
    assert "lack the policy's inputs ['state']; they hold" in done.stderr and "'State'" in done.stderr


def test_opset_12_runs_in_onnxruntime_as_17_does(recorded: dict) -> None:
    run_dir, task = recorded["run_dir"], recorded["task"]
    out = run_dir / "policy12.onnx"
    assert main(["export", task, "--checkpoint", str(recorded["checkpoint"]), "--out", str(out), "--opset", "12"]) == 0
    run_runner(str(out), "--observations", str(run_dir / "observations.npz"), "--out", str(run_dir / "actions12.npz"))
    with np.load(run_dir / "actions12.npz") as data:
        np.testing.assert_allclose(data["action"], recorded["expected"], atol=1e-5, rtol=0)


def test_action_mapping_of_ctbr_follows_the_airframe() -> None:
    from visfly_dist.dynamics import load_airframe

    airframe = load_airframe("visfly")
    m = action_mapping("ctbr", airframe)
    command = np.asarray(m["offset"]) + np.asarray(m["scale"]) * np.array([-1.0, 1.0, -1.0, 0.5])
    np.testing.assert_allclose(command, [0.0, airframe.max_body_rate, -airframe.max_body_rate, 0.5 * airframe.max_body_rate])
    top = np.asarray(m["offset"]) + np.asarray(m["scale"]) * np.ones(4)
    assert top[0] == pytest.approx(airframe.max_collective_accel)
    lv = action_mapping("lv")
    assert lv["scale"][:3] == [10.0] * 3 and lv["scale"][3] == pytest.approx(math.pi)


class GRUCore(nn.Module):
    """A toy recurrent core: features -> GRU cell -> features (the interface of export.RecurrentCore)."""

    hidden_shape = (8,)

    def __init__(self, features: int) -> None:
        super().__init__()
        self.cell = nn.GRUCell(features, 8)
        self.out = nn.Linear(8, features)

    def forward(self, features: torch.Tensor, hidden: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        hidden = self.cell(features, hidden)
        return torch.relu(self.out(hidden)), hidden


def test_recurrent_core_exports_its_hidden_state(tmp_path: Path) -> None:
    from gymnasium import spaces
    from stable_baselines3 import PPO

    from visfly_dist.training.export import DeployedActor
    from visfly_dist.training.extractors import visfly_policy_kwargs

    space = spaces.Dict({"state": spaces.Box(-np.inf, np.inf, (13,), np.float32),
                         "target": spaces.Box(-np.inf, np.inf, (4,), np.float32)})
    model = PPO("MultiInputPolicy", None, policy_kwargs=visfly_policy_kwargs(), device="cpu", _init_setup_model=False)
    model.observation_space, model.action_space, model.n_envs = space, spaces.Box(-1, 1, (4,), np.float32), 1
    model._setup_model()
    torch.manual_seed(0)
    core = GRUCore(model.policy.features_dim)
    rng = np.random.default_rng(1)
    norm = ObsNormalization(mean={"state": rng.normal(size=13)}, var={"state": rng.uniform(0.5, 3.0, 13)})
    info = export_policy(model.policy, tmp_path / "rnn.onnx", norm, core=core)
    assert [i["name"] for i in info.inputs] == ["state", "target", "hidden_in"]
    assert [o["name"] for o in info.outputs] == ["action", "hidden_out"]
    steps, n = 12, 3
    obs = {"state": rng.normal(size=(steps, n, 13)).astype(np.float32) * 2, "target": rng.normal(size=(steps, n, 4)).astype(np.float32)}
    starts = np.zeros((steps, n), bool)
    starts[5, 1] = True  # agent 1 starts a new episode at step 5: its state goes back to zeros
    np.savez(tmp_path / "obs.npz", episode_start=starts, **obs)
    actor = DeployedActor(model.policy, ["state", "target"], norm, core).eval()
    hidden, expected = torch.zeros(n, 8), []
    with torch.no_grad():
        for t in range(steps):
            if t > 0:
                hidden[torch.as_tensor(starts[t])] = 0.0
            action, hidden = actor(torch.as_tensor(obs["state"][t]), torch.as_tensor(obs["target"][t]), hidden)
            expected.append(action.numpy())
    run_runner(str(tmp_path / "rnn.onnx"), "--observations", str(tmp_path / "obs.npz"), "--out", str(tmp_path / "a.npz"))
    with np.load(tmp_path / "a.npz") as data:
        np.testing.assert_allclose(data["action"], np.stack(expected), atol=1e-5, rtol=0)
    assert json.loads(json.dumps(read_metadata(tmp_path / "rnn.onnx")))["recurrent"] is True
