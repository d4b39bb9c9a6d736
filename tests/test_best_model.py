"""A run's best policy: `<run dir>/best.silcr`, the policy of the best evaluation so far, written when an
evaluation beats it, kept across a restart, and read by `silcr eval` and `silcr.SILCR.load` (real runs,
real MuJoCo, real files)."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from silcr import SILCR
from silcr.learner import model_file
from silcr.actor.policy import initial_weights
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.learner.evaluations import Evaluations
from tests.helpers import REPO
from tests.test_api import ENV, SMALL, _observations

BEST_MODEL = "best.silcr"  # the name the README's run-directory table gives


def test_a_run_keeps_the_policy_of_its_best_evaluation(tmp_path):
    model = SILCR(ENV, runs_dir=tmp_path / "runs", seed=1, **SMALL)
    model.learn(2500)
    model.close()
    with open(model.run_dir / "progress.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    returns = [float(r["eval_return"]) for r in rows]
    first_best = rows[returns.index(max(returns))]
    best = model_file.read(model.run_dir / BEST_MODEL)
    assert best["evaluation"]["return_mean"] == pytest.approx(max(returns))
    assert best["evaluation"]["env_steps"] == int(first_best["env_steps"])  # the first to reach it, not a later tie
    assert best["evaluation"]["episodes"] == SMALL["eval_episodes"] and best["evaluation"]["deterministic"] is True
    assert best["policy"]["version"] == int(first_best["policy_version"])

    loaded = SILCR.load(model.run_dir / BEST_MODEL)
    actions = loaded.predict(_observations(), deterministic=True)[0]
    assert actions.shape == (16, 1) and np.all(np.isfinite(actions))
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(model.run_dir / BEST_MODEL), "--episodes", "2",
                        "--json"], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert out["env"] == ENV and out["policy_version"] == best["policy"]["version"] and len(out["episodes"]) == 2


def _evaluations(tmp_path, resumed: bool) -> tuple[Evaluations, object]:
    cfg = Config(run="best", env=ENV, hidden=[16], eval_episodes=2, algo="silcr")
    spec = EnvSpec.of(ENV)
    return Evaluations(cfg, spec, tmp_path, resumed), initial_weights(spec.obs_dim, spec.act_dim, [16], seed=0)


def _evaluate(evaluations: Evaluations, weights, env_steps: int) -> None:
    evaluations.run(weights, {"time": 0.0, "env_steps": env_steps, "updates": env_steps}, {}, env_steps, {})


def test_the_best_so_far_survives_a_restart_and_only_a_better_evaluation_replaces_it(tmp_path):
    first, weights = _evaluations(tmp_path, resumed=False)
    _evaluate(first, weights, 100)
    written = model_file.read(tmp_path / BEST_MODEL)["evaluation"]
    assert written["env_steps"] == 100 and written["return_mean"] == first.best_eval_return
    counters = first.state()
    first.close()

    # Restarted from a checkpoint that remembers a better evaluation: the same policy's does not replace it.
    better = dict(counters, evals=0, best_eval_return=counters["best_eval_return"] + 1.0)
    resumed, _ = _evaluations(tmp_path, resumed=True)
    resumed.restore(better)
    _evaluate(resumed, weights, 200)
    assert model_file.read(tmp_path / BEST_MODEL)["evaluation"]["env_steps"] == 100
    assert resumed.best_eval_return == better["best_eval_return"]
    resumed.close()

    # A checkpoint from before best.silcr existed remembers none: its first evaluation is the best so far.
    old = {k: v for k, v in counters.items() if k != "best_eval_return"}
    older, _ = _evaluations(tmp_path, resumed=True)
    older.restore(old)
    assert older.best_eval_return is None
    _evaluate(older, weights, 300)
    assert model_file.read(tmp_path / BEST_MODEL)["evaluation"]["env_steps"] == 300
    older.close()


def test_eval_refuses_a_model_file_of_a_newer_format_with_one_line(tmp_path):
    spec = EnvSpec.of(ENV)
    path = tmp_path / "m.silcr"
    model_file.write(path, "silcr", Config(env=ENV).to_dict(), initial_weights(spec.obs_dim, spec.act_dim, [16], 0),
                     spec)
    import torch

    payload = torch.load(path, weights_only=True)
    payload["version"] = model_file.MODEL_VERSION + 1
    torch.save(payload, path)
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(path)], capture_output=True, text=True, cwd=REPO,
                       timeout=60)
    assert r.returncode == 2 and "newer silcr" in r.stderr and "Traceback" not in r.stderr
