"""The learner's torch threads: chosen by timing the update, logged, honoured; --torch-threads overrides; how idle
threads wait."""

from __future__ import annotations

import logging
import os
import subprocess
import sys

import pytest
import torch

import silcr
from silcr.cli import command
from tests.helpers import REPO

from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.learner import threads
from silcr.learner.update import Update


@pytest.fixture(autouse=True)
def _keep_threads():
    before = torch.get_num_threads()
    yield
    torch.set_num_threads(before)


def test_the_faster_count_is_kept_whichever_it_is():
    for faster in (1, 4):
        calls = []

        def timer(step, n, updates):
            calls.append(n)
            return 1.0 if n == faster else 2.0

        best, times = threads.choose_threads(lambda: None, 4, timer=timer)
        assert best == faster and times == {faster: 1.0, 5 - faster: 2.0}
        assert calls == [1, 4, 1, 4]  # alternated, so load from elsewhere hits both
    assert threads.choose_threads(lambda: None, 1, timer=lambda s, n, u: 1.0)[0] == 1  # one core: nothing to time


@pytest.mark.parametrize("faster", [1, 2])
def test_the_learner_logs_its_choice_and_uses_it(caplog, monkeypatch, faster):
    spec = EnvSpec.of("InvertedPendulum-v5")
    monkeypatch.setattr("silcr.learner.update.usable_cores", lambda: 2)
    timed = []
    real = threads.time_per_update

    def rigged(step, n, updates):  # make `faster` the faster, whatever this machine measures
        timed.append(n)
        return real(step, n, 2) * (1.0 if n == faster else 100.0)

    monkeypatch.setattr(threads, "time_per_update", rigged)
    with caplog.at_level(logging.INFO, logger="learner"):
        update = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], batch_size=16, device="cpu"), spec)
    assert sorted(set(timed)) == [1, 2]
    # honoured: the count in use is the choice, not the last one timed (2)
    assert update.torch_threads == faster and torch.get_num_threads() == faster
    assert any(r.getMessage().startswith(f"torch threads: {faster} (timed the update: 1 thread") for r in caplog.records)


def test_torch_threads_overrides_the_choice(caplog, monkeypatch):
    spec = EnvSpec.of("InvertedPendulum-v5")
    monkeypatch.setattr(threads, "time_per_update", lambda *a: pytest.fail("timed anyway"))
    with caplog.at_level(logging.INFO, logger="learner"):
        update = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], torch_threads=1, device="cpu"), spec)
    assert update.torch_threads == 1 and torch.get_num_threads() == 1
    assert not any("torch threads" in r.getMessage() for r in caplog.records)


def test_the_probe_changes_nothing_the_run_draws():
    """The probe trains a throwaway copy before the seed is set: the networks start the same either way."""
    spec = EnvSpec.of("InvertedPendulum-v5")
    chosen = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], device="cpu"), spec)
    pinned = Update(Config(run="t", env=spec.env_id, hidden=[32, 32], torch_threads=1, device="cpu"), spec)
    for a, b in zip(chosen.sac.actor_arrays().values(), pinned.sac.actor_arrays().values()):
        assert (a == b).all()


# -- how idle OpenMP threads wait: spinning briefly in `silcr train --single-process` (silcr/__init__.py) --------

SPIN_PROBE = """
import os, sys
import silcr
if sys.argv[1] == "torch first":
    import torch
print(silcr.spin_openmp_threads_briefly(), os.environ.get("OMP_WAIT_POLICY"), os.environ.get("GOMP_SPINCOUNT"))
"""


def _without_thread_settings(**extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    return env | extra


@pytest.mark.parametrize("case, env, want", [
    ("alone", _without_thread_settings(), "True None " + silcr.ALONE_SPIN_COUNT),
    ("the user's policy wins", _without_thread_settings(OMP_WAIT_POLICY="PASSIVE"), "False PASSIVE None"),
    ("the user's spin count wins", _without_thread_settings(GOMP_SPINCOUNT="5"), "False PASSIVE 5"),
    ("torch first", _without_thread_settings(), "False PASSIVE None"),  # too late: libgomp has read its settings
])
def test_idle_threads_spin_briefly_only_when_nobody_chose_and_torch_is_not_loaded(case, env, want):
    r = subprocess.run([sys.executable, "-c", SPIN_PROBE, case], capture_output=True, text=True, env=env, timeout=120)
    assert r.stdout.strip() == want, r.stdout + r.stderr


@pytest.mark.parametrize("policy", [None, "PASSIVE"])
def test_single_process_runs_spin_unless_started_with_a_policy(tmp_path, policy):
    """`silcr train --single-process` from a user's shell spins briefly; one started by a silcr sweep (which
    shares the cores, and passes on its PASSIVE) or with the user's own policy does not. Its log says which."""
    env = _without_thread_settings(**({"OMP_WAIT_POLICY": policy} if policy else {}))
    r = subprocess.run(command("train", "--single-process", "--run", "s", "--runs-dir", str(tmp_path), "--env",
                               "InvertedPendulum-v5", "--hidden", "16", "16", "--learning-starts", "200",
                               "--total-steps", "300", "--eval-episodes", "0"),
                       capture_output=True, text=True, env=env, timeout=300, cwd=REPO)
    assert r.returncode == 0, r.stdout + r.stderr
    log = (tmp_path / "s" / "logs" / "single-process.log").read_text()
    if policy is None:
        assert f"idle torch threads spin {silcr.ALONE_SPIN_COUNT} times before sleeping" in log, log
    else:
        assert "idle torch threads as set before the run (OMP_WAIT_POLICY=PASSIVE, GOMP_SPINCOUNT=None)" in log, log
