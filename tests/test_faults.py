"""Faults an operator causes: a checkpoint that cannot be written, a component that cannot start.

Each case below ended the run, or restarted a component again and again, before issue 18.
"""

from __future__ import annotations

import csv
import shutil

from tests.helpers import Processes, wait_for

SMALL = ["--env", "InvertedPendulum-v5", "--hidden", "32", "32", "--learning-starts", "300", "--batch-size", "32",
         "--eval-interval", "1000", "--eval-episodes", "1"]


def test_a_learner_checkpoint_that_cannot_be_written_is_counted_and_training_goes_on(tmp_path):
    """Before: the learner died on the failed write, restarted from its older checkpoint five times
    (losing updates each time) and the run exited 1."""
    procs = Processes(tmp_path)
    run_dir = tmp_path / "runs" / "ckpt"
    train = procs.start("train", "train", "--run", "ckpt", "--runs-dir", str(tmp_path / "runs"), *SMALL,
                        "--single-process", "--total-steps", "5000", "--checkpoint-interval", "200")
    try:
        learner_pt = run_dir / "checkpoints" / "learner.pt"
        wait_for(learner_pt.exists, 120, "the first learner checkpoint")
        learner_pt.unlink()
        learner_pt.mkdir()  # every later write fails: the rename onto a directory is refused
        assert train.wait(600) == 0, procs.log("train")
    finally:
        procs.stop_all()
    rows = list(csv.DictReader(open(run_dir / "progress.csv")))
    assert int(rows[-1]["env_steps"]) >= 5000 and int(rows[-1]["updates"]) >= 4000
    assert int(rows[-1]["checkpoints_failed"]) >= 10  # one per 200 updates after the sabotage, the last one too
    log = (run_dir / "logs" / "single-process.log").read_text()
    assert log.count("training goes on, and failures are counted") == 1  # warned once
    assert "the final checkpoint could not be written" in log
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["buffer.ckpt", "learner.pt"]  # no temp file
    shutil.rmtree(learner_pt)
