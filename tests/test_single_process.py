"""`silcr train --single-process`: reproducible to the last digit, Ctrl-C safe, and the divergence watch.

The learning comparison with the distributed launcher is in test_learning.py.
"""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import time

from silcr.learner.checkpoint import load_checkpoint
from tests.helpers import REPO, Processes, wait_for

WALL_CLOCK_COLUMNS = {"time", "updates_per_s", "wall_time"}
SMALL = ["--env", "InvertedPendulum-v5", "--hidden", "32", "32", "--learning-starts", "500", "--eval-interval", "1000",
         "--eval-episodes", "2", "--actors", "2", "--envs-per-actor", "2", "--weights-interval", "20",
         "--checkpoint-interval", "1000", "--torch-threads", "1"]  # pinned: the default chooses by timing


def _train(tmp_path, run: str, *extra: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "silcr.cli", "train", "--single-process", "--run", run,
                           "--runs-dir", str(tmp_path), *extra], capture_output=True, text=True, cwd=REPO, timeout=600)


def _rows(path) -> list[dict[str, str]]:
    return list(csv.DictReader(open(path)))


def test_the_same_seed_gives_the_same_progress_csv(tmp_path):
    runs = {}
    for name, seed in [("a", "3"), ("b", "3"), ("other-seed", "4")]:
        r = _train(tmp_path, name, *SMALL, "--total-steps", "3000", "--seed", seed)
        assert r.returncode == 0, r.stdout + r.stderr
        runs[name] = _rows(tmp_path / name / "progress.csv")
    a, b = runs["a"], runs["b"]
    assert len(a) == len(b) >= 4
    for ra, rb in zip(a, b):
        assert {k: v for k, v in ra.items() if k not in WALL_CLOCK_COLUMNS} == \
               {k: v for k, v in rb.items() if k not in WALL_CLOCK_COLUMNS}
    # Not a constant: another seed gives other numbers, and the run did train.
    assert [r["eval_return"] for r in runs["other-seed"]] != [r["eval_return"] for r in a]
    assert int(a[-1]["updates"]) >= 2500 and float(a[-1]["q_mean"]) != 0.0
    assert all(r["q_bound_exceeded"] == "0" for r in a)  # a healthy run: the divergence counter stays at 0
    # The actors' own returns: InvertedPendulum-v5 pays 1 a step but none for the step that falls (summed at the
    # end by the episodic reward), so each row's mean return of the last 100 episodes is their mean length less
    # the share that fell (all, this early); it moves as the policy learns.
    rollouts = [(float(r["rollout_return"]), float(r["rollout_length"])) for r in a if r["rollout_return"]]
    assert len(rollouts) >= len(a) - 1 and all(length - 1 <= ret <= length and ret > 0 for ret, length in rollouts)
    assert len({ret for ret, _ in rollouts}) > 1


def test_ctrl_c_leaves_checkpoints_and_resume_finishes_the_run(tmp_path):
    procs = Processes(tmp_path)
    args = ["train", "--single-process", "--run", "cut", "--runs-dir", str(tmp_path), *SMALL, "--total-steps", "6000",
            "--buffer-checkpoint-interval", "0"]
    ckpt = tmp_path / "cut" / "checkpoints" / "learner.pt"
    try:
        train = procs.start("train1", *args, new_session=True)
        wait_for(lambda: ckpt.exists() and load_checkpoint(ckpt)["counters"]["updates"] >= 1000, 240,
                 "a learner checkpoint")
        train.send_signal(signal.SIGINT)
        assert train.wait(60) == 130, procs.log("train1")
        stopped_at = load_checkpoint(ckpt)["counters"]["updates"]
        assert stopped_at < 5500
        assert sorted(p.name for p in ckpt.parent.iterdir()) == ["buffer.ckpt", "learner.pt"]  # no temporary file
        train = procs.start("train2", *args, "--resume")
        assert train.wait(300) == 0, procs.log("train2")
    finally:
        procs.stop_all()
    assert procs.orphans == []
    log = (tmp_path / "cut" / "logs" / "single-process.log").read_text()
    assert "resumed from" in log and "restored D_O" in log
    rows = _rows(tmp_path / "cut" / "progress.csv")
    updates = [int(r["updates"]) for r in rows]
    assert updates == sorted(updates) and updates[-1] >= 5500 > stopped_at


def test_a_resume_after_a_hard_kill_keeps_one_update_per_step_over_the_whole_run(tmp_path):
    """SIGKILL leaves the learner's checkpoint (every 1,000 updates) and the buffer's (every 0.2 s
    here) at different moments; the resumed run still ends with one update per env step after the
    warm-up, as a run that was never cut does (updates = env_steps - learning_starts)."""
    procs = Processes(tmp_path)
    args = ["train", "--single-process", "--run", "killed", "--runs-dir", str(tmp_path), *SMALL,
            "--total-steps", "6000", "--buffer-checkpoint-interval", "0.2"]
    ckpts = tmp_path / "killed" / "checkpoints"
    learner_ckpt, buffer_ckpt = ckpts / "learner.pt", ckpts / "buffer.ckpt"
    try:
        train = procs.start("train1", *args, new_session=True)
        # Kill between two learner checkpoints, once the buffer's is newer than the learner's.
        wait_for(lambda: learner_ckpt.exists() and load_checkpoint(learner_ckpt)["counters"]["updates"] >= 1000
                 and buffer_ckpt.exists() and buffer_ckpt.stat().st_mtime > learner_ckpt.stat().st_mtime + 0.5,
                 240, "a buffer checkpoint newer than the learner's")
        os.killpg(train.pid, signal.SIGKILL)
        train.wait(30)
        train = procs.start("train2", *args, "--resume")
        assert train.wait(300) == 0, procs.log("train2")
    finally:
        procs.stop_all()
    log = (tmp_path / "killed" / "logs" / "single-process.log").read_text()
    assert "takes the learner's count, so" in log, log[-2000:]
    last = _rows(tmp_path / "killed" / "progress.csv")[-1]
    assert int(last["env_steps"]) >= 6000
    assert int(last["updates"]) == int(last["env_steps"]) - 500


def test_a_diverging_learner_is_counted_and_warned_about(tmp_path):
    """Provoked on purpose: Polyak rate 1 (no target network) and a 10x learning rate, no clipping, and the
    paper's plain critics (the default LayerNorm critics with the clipped target stay under the bound here)."""
    t0 = time.monotonic()
    r = _train(tmp_path, "diverge", "--env", "Hopper-v5", "--hidden", "256", "256", "--tau", "1", "--lr", "0.003",
               "--grad-clip", "0", "--critic-norm", "none", "--q-target-clip", "none", "--learning-starts", "1000",
               "--total-steps", "4000", "--eval-interval", "1000",
               "--eval-episodes", "1", "--seed", "0")
    assert r.returncode == 0, r.stdout + r.stderr
    warnings = [line for line in r.stdout.splitlines() if "warning: the critics are diverging" in line]
    assert len(warnings) == 1, r.stdout  # printed once, when the bound is first passed
    rows = _rows(tmp_path / "diverge" / "progress.csv")
    exceeded = [int(r["q_bound_exceeded"]) for r in rows]
    assert exceeded == sorted(exceeded) and exceeded[-1] > 100, exceeded
    last = rows[-1]
    assert float(last["q_max"]) > 1.5 * float(last["q_bound"])
    assert time.monotonic() - t0 < 300


def test_the_closing_evaluation_plays_final_eval_episodes(tmp_path):
    """--final-eval-episodes: the run's last number over more episodes than the schedule's. Here the schedule's
    last evaluation (1 episode) falls on the final step, so the closing one (4 episodes) is a row of its own."""
    r = _train(tmp_path, "final", *SMALL, "--total-steps", "1000", "--eval-interval", "500", "--eval-episodes", "1",
               "--final-eval-episodes", "4")
    assert r.returncode == 0, r.stdout + r.stderr
    rows = _rows(tmp_path / "final" / "progress.csv")
    steps = [int(row["env_steps"]) for row in rows]
    assert steps[-1] == steps[-2] >= 1000
    log = (tmp_path / "final" / "logs" / "single-process.log").read_text()
    assert re.search(rf"final eval at {steps[-1]} env steps, \d+ updates: return [\d.]+ \+- [\d.]+ over 4 episodes", log), log
    assert len(re.findall(r"eval at \d+ env steps, .* over 1 episodes", log)) == len(rows) - 1
