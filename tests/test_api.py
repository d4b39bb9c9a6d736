"""The Python API (issue 38): SILCR(env, ...).learn(n), save, load, predict, in Stable-Baselines3's shape,
on real MuJoCo envs, real files and, for actors > 0, the real distributed system."""

from __future__ import annotations

import csv
import os
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
import torch

import silcr
from silcr import SAC, SILCR
from silcr.learner.model_file import MODEL_VERSION, ModelFileError
from tests.helpers import free_port

ENV = "InvertedPendulum-v5"
SMALL = dict(hidden=(16, 16), learning_starts=300, expert_capacity=1000, batch_size=32, eval_interval=500,
             eval_episodes=1, torch_threads=1)


def _rows(model) -> list[dict[str, str]]:
    with open(model.run_dir / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


def _observations(n: int = 16) -> np.ndarray:
    env = gym.make(ENV)
    out = [env.reset(seed=s)[0] for s in range(n)]
    env.close()
    return np.stack(out).astype(np.float32)


def _children() -> list[str]:
    """Live processes whose parent is this one (the distributed system's components), but multiprocessing's
    resource tracker, which serves every spawned process of this one and ends with it."""
    me, found = os.getpid(), []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                fields = (d / "stat").read_text().rsplit(")", 1)[1].split()
                cmdline = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            except OSError:
                continue
            if int(fields[1]) == me and fields[0] != "Z" and "resource_tracker" not in cmdline:
                found.append(f"{d.name}: {cmdline[:120]}")
    return found


def test_the_classes_come_from_the_registry():
    from silcr.common.algorithms import ALGORITHMS

    for name in ALGORITHMS:
        cls = getattr(silcr, name.upper())
        assert issubclass(cls, silcr.Model) and cls.algo == name and ALGORITHMS[name].summary in cls.__doc__
    with pytest.raises(AttributeError):
        silcr.NOT_AN_ALGORITHM  # noqa: B018


def test_the_classes_are_written_out_where_type_checkers_see_them():
    """Each registry entry has a class defined in silcr/api.py (a `class` statement, not `type()`), and the
    package root names every API class under TYPE_CHECKING, so that IDEs resolve `silcr.SILCR`."""
    import ast

    from silcr.common.algorithms import ALGORITHMS

    api = ast.parse(Path(silcr.api.__file__).read_text())
    defined = {n.name for n in api.body if isinstance(n, ast.ClassDef)}
    assert {a.upper() for a in ALGORITHMS} | {"Model", "Callback"} <= defined
    root = ast.parse(Path(silcr.__file__).read_text())
    checked = {a.asname or a.name for n in ast.walk(root) if isinstance(n, ast.If) and "TYPE_CHECKING" in ast.unparse(n.test)
               for i in n.body if isinstance(i, ast.ImportFrom) and i.module == "silcr.api" for a in i.names}
    assert checked == set(silcr.API_NAMES) == set(silcr.api.__all__) == {a.upper() for a in ALGORITHMS} | {"Model",
                                                                                                         "Callback"}


def test_learn_save_load_predict_gives_the_same_actions(tmp_path):
    model = SILCR(ENV, runs_dir=tmp_path / "runs", seed=3, **SMALL)
    assert model.run_dir.parent == tmp_path / "runs" and not model.run_dir.exists()  # nothing written yet
    assert model.learn(1000) is model
    obs = _observations()
    actions, state = model.predict(obs, deterministic=True)
    assert state is None and actions.shape == (16, 1) and np.all(np.abs(actions) <= 3.0)  # the env's bounds, [-3, 3]
    one, _ = model.predict(obs[0])
    assert one.shape == (1,) and np.array_equal(one, actions[0])
    model.save(tmp_path / "pendulum.silcr")
    loaded = SILCR.load(tmp_path / "pendulum.silcr")
    assert np.array_equal(loaded.predict(obs, deterministic=True)[0], actions)
    sampled = loaded.predict(obs, deterministic=False)[0]
    assert sampled.shape == actions.shape and not np.array_equal(sampled, actions)
    assert loaded.observation_space.shape == (4,) and loaded.action_space.high[0] == pytest.approx(3.0)
    with pytest.raises(ValueError, match="observation: shape"):
        loaded.predict(np.zeros(5))
    with pytest.raises(ValueError, match="include_training_state=True"):
        loaded.learn(100)  # loaded for predict only
    model.close()
    rows = _rows(model)
    assert int(rows[-1]["env_steps"]) >= 1000 and (model.run_dir / "config.toml").exists()
    assert (model.run_dir / "checkpoints" / "learner.pt").exists() and (model.run_dir / "checkpoints" / "buffer.ckpt").exists()


def test_sb3s_evaluate_policy_runs_on_a_loaded_model(tmp_path):
    from stable_baselines3.common.evaluation import evaluate_policy

    model = SILCR(ENV, runs_dir=tmp_path / "runs", **SMALL)
    model.save(tmp_path / "untrained.silcr")  # before any learn: the untrained policy
    loaded = SILCR.load(tmp_path / "untrained.silcr")
    mean, std = evaluate_policy(loaded, gym.make(ENV), n_eval_episodes=3, warn=False)
    assert 1 <= mean < 100 and std >= 0  # an untrained policy falls within a few dozen steps
    assert not (tmp_path / "runs").exists()


def test_a_second_learn_goes_on_with_the_same_buffers_and_counters(tmp_path):
    model = SILCR(ENV, runs_dir=tmp_path / "runs", seed=1, **SMALL)
    model.learn(800)
    first = _rows(model)
    steps = model.num_timesteps
    model.learn(700)
    rows = _rows(model)
    assert rows[: len(first)] == first and len(rows) > len(first)
    assert [r["env_steps"] for r in rows].count("0") == 1  # the untrained policy evaluated once, at the start
    assert int(rows[-1]["env_steps"]) >= 1500 and model.num_timesteps >= steps + 700
    assert int(rows[-1]["updates"]) > int(first[-1]["updates"])
    # the training state in the file: a new model goes on from its counters and tables
    model.save(tmp_path / "m.silcr", include_training_state=True)
    model.close()
    again = SILCR.load(tmp_path / "m.silcr", include_training_state=True, runs_dir=tmp_path / "runs2", run="again")
    assert again.num_timesteps == model.num_timesteps
    again.learn(500)
    resumed = _rows(again)
    assert int(resumed[0]["updates"]) > int(rows[-1]["updates"]) - 500  # went on from the saved learner
    assert int(resumed[-1]["env_steps"]) >= model.num_timesteps + 500
    again.close()


def test_a_model_whose_final_checkpoint_cannot_be_written_says_which_file_is_stale(tmp_path):
    """The API reports a stale checkpoint as `silcr train` does (deploy/console.py's `StaleCheckpoints`, an OSError)."""
    from silcr.common.run_lock import check_free
    from silcr.deploy.console import StaleCheckpoints

    model = SILCR(ENV, runs_dir=tmp_path / "runs", seed=1, **SMALL)
    model.learn(600)
    ckpt = model.run_dir / "checkpoints" / "buffer.ckpt"
    ckpt.unlink(missing_ok=True)
    ckpt.mkdir()  # the final buffer checkpoint's rename onto it fails
    with pytest.raises(StaleCheckpoints, match="the final checkpoint of the buffer could not be written") as e:
        model.close()
    assert isinstance(e.value, OSError) and str(ckpt) in str(e.value) and e.value.components == ["buffer"]
    model.close()  # said once: the model is closed
    ckpt.rmdir()
    check_free(model.run_dir)  # the run directory was released (RunInUse otherwise)


def test_a_bad_option_raises_naming_it_before_any_file_exists(tmp_path):
    runs = tmp_path / "runs"
    for options, name in ((dict(hidden=(0,)), "hidden"), (dict(tau=2.0), "tau"), (dict(hiden=(64,)), "hiden"),
                          (dict(expert_capacity=10), "expert_capacity"),
                          (dict(total_steps=100), "total_steps"), (dict(critic_norm="batch"), "critic_norm")):
        with pytest.raises(ValueError) as e:
            SILCR(ENV, runs_dir=runs, **options)
        assert str(e.value).startswith(f"{name}:"), e.value
        assert "--" not in str(e.value).split(":")[0]  # the Python name, not the flag
    with pytest.raises(ValueError, match="q_target_clip"):
        SAC(ENV, runs_dir=runs, q_target_clip="bound")
    with pytest.raises(ValueError, match="actors"):
        SILCR(ENV, runs_dir=runs, actors=-1)
    with pytest.raises(ValueError, match="env"):
        SILCR(gym.make(ENV), runs_dir=runs)
    with pytest.raises(ValueError, match="total_steps"):
        SILCR(ENV, runs_dir=runs).learn(0)
    assert not runs.exists()


def test_model_files_from_another_algorithm_or_a_newer_silcr_are_refused(tmp_path):
    SAC(ENV, runs_dir=tmp_path / "runs", reward="dense", hidden=(8, 8)).save(tmp_path / "sac.silcr")
    with pytest.raises(ModelFileError, match="holds a sac model.*silcr.SAC.load"):
        SILCR.load(tmp_path / "sac.silcr")
    assert SAC.load(tmp_path / "sac.silcr").cfg.reward == "dense"
    payload = torch.load(tmp_path / "sac.silcr", weights_only=True)
    payload["version"] = MODEL_VERSION + 1
    torch.save(payload, tmp_path / "newer.silcr")
    with pytest.raises(ModelFileError, match="newer silcr"):
        SAC.load(tmp_path / "newer.silcr")
    (tmp_path / "junk.silcr").write_bytes(b"not a model")
    with pytest.raises(ModelFileError, match="unreadable or corrupt"):
        SAC.load(tmp_path / "junk.silcr")
    torch.save({"sac": {}, "counters": {}, "config": {}}, tmp_path / "learner.pt")
    with pytest.raises(ModelFileError, match="is a learner checkpoint"):
        SAC.load(tmp_path / "learner.pt")
    with pytest.raises(ModelFileError, match="without its training state"):
        SAC.load(tmp_path / "sac.silcr", include_training_state=True)
    with pytest.raises(ValueError, match="no training state"):
        SAC(ENV, runs_dir=tmp_path / "runs", reward="dense").save(tmp_path / "x.silcr", include_training_state=True)


class Corridor(gym.Env):
    """A user's own env: walk right along a line to its end within 50 steps; the episodic reward pays the
    distance reached at the end."""

    def __init__(self) -> None:
        self.observation_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.x, self.t = 0.0, 0
        return np.array([self.x, 0.0], np.float32), {}

    def step(self, action):
        self.x = float(np.clip(self.x + 0.1 * float(np.asarray(action)[0]), -1.0, 1.0))
        self.t += 1
        obs = np.array([self.x, self.t / 50], np.float32)
        return obs, self.x, self.x >= 1.0, self.t >= 50, {}


def test_a_user_env_by_callable_trains_in_this_process(tmp_path):
    model = SILCR(Corridor, runs_dir=tmp_path / "runs", hidden=(16, 16), learning_starts=200, expert_capacity=200,
                  batch_size=32, eval_interval=400, eval_episodes=1, torch_threads=1)
    assert model.env_id == f"{__name__}:Corridor"  # importable: every process can make it
    model.learn(800)
    assert model.predict(np.zeros(2, np.float32))[0].shape == (1,)
    assert int(_rows(model)[-1]["env_steps"]) >= 800
    model.close()
    # a lambda is not importable: registered in this process, which is enough with actors=0 ...
    local = SILCR(lambda: Corridor(), runs_dir=tmp_path / "runs", hidden=(8, 8), learning_starts=100,
                  expert_capacity=100, eval_interval=200, eval_episodes=1, torch_threads=1)
    assert local.env_id.startswith("silcr-api/")
    local.learn(300)
    local.close()
    # ... and refused, with the reason, when actor processes would have to make it
    with pytest.raises(ValueError, match="cannot be imported by the actor processes"):
        SILCR(lambda: Corridor(), actors=2, runs_dir=tmp_path / "runs")


def test_a_callback_sees_every_evaluation_and_can_stop_training(tmp_path):
    seen = []

    class StopAfterTwo(silcr.Callback):
        def on_evaluation(self, row, model):
            seen.append(int(row["env_steps"]))
            return len(seen) < 2

    model = SILCR(ENV, runs_dir=tmp_path / "runs", **SMALL)
    model.learn(3000, callback=StopAfterTwo())
    assert len(seen) == 2 and seen[0] == 0 and 500 <= seen[1] < 600  # the untrained policy's, then the first
    assert model.num_timesteps < 1000  # stopped at the second evaluation
    assert (model.run_dir / "checkpoints" / "learner.pt").exists()
    calls = []
    model.learn(600, callback=lambda info: calls.append(info["row"]["eval_return"]))  # a function works too
    assert calls
    model.close()


@pytest.mark.slow
def test_a_distributed_learn_with_two_actors_leaves_no_process_behind(tmp_path):
    rows_seen = []
    model = SILCR(ENV, actors=2, runs_dir=tmp_path / "runs", zenoh_listen=f"tcp/127.0.0.1:{free_port()}", **SMALL)
    assert model.learn(1500, callback=lambda info: rows_seen.append(info["row"])) is model
    assert _children() == []
    rows = _rows(model)
    assert int(rows[-1]["env_steps"]) >= 1500 and rows_seen  # the callback read the learner's rows as they came
    assert (model.run_dir / "logs" / "learner.log").exists()
    obs = _observations(4)
    actions = model.predict(obs)[0]
    model.save(tmp_path / "d.silcr")
    assert np.array_equal(SILCR.load(tmp_path / "d.silcr").predict(obs)[0], actions)
    # a second learn resumes the same run from its checkpoints
    model.learn(500)
    assert _children() == [] and int(_rows(model)[-1]["env_steps"]) >= 2000
    # a callback's False stops it cleanly, with no process left either
    model.learn(20_000, callback=lambda info: False)
    assert _children() == [] and int(_rows(model)[-1]["env_steps"]) < 20_000


@pytest.mark.slow
def test_silcr_learns_inverted_pendulum_through_the_api(tmp_path):
    """tests/test_learning.py's task and thresholds, through `SILCR(...).learn` in this process."""
    from tests.test_learning import BEST_RETURN_FLOOR, FINAL_RETURN_FLOOR, RANDOM_RETURN_CEILING

    model = SILCR(ENV, runs_dir=tmp_path / "runs", seed=1, hidden=(64, 64), learning_starts=1000,
                  eval_interval=3000, eval_episodes=5, envs_per_actor=2)
    model.learn(20_000)
    returns = [float(r["eval_return"]) for r in _rows(model)]
    assert returns[0] < RANDOM_RETURN_CEILING, returns
    assert max(returns) >= BEST_RETURN_FLOOR, f"SILCR did not learn through the API: {returns}"
    assert sum(returns[-2:]) / 2 >= FINAL_RETURN_FLOOR, f"SILCR did not keep what it learned: {returns}"
    model.close()
