"""Faults an operator causes: a checkpoint that cannot be written, a component that cannot start.

Each case below ended the run, or restarted a component again and again, before issue 18.
"""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys

from silcr.cli import command
from silcr.common.lifecycle import EXIT_STALE_CHECKPOINT
from tests.helpers import REPO, Processes, free_port, wait_for

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
        # the run trains to its end, and then says that its checkpoint is stale (it printed "done" and exited 0)
        assert train.wait(600) == EXIT_STALE_CHECKPOINT, procs.log("train")
    finally:
        procs.stop_all()
    err = procs.log("train")
    assert "the final checkpoint of the learner could not be written" in err and str(learner_pt) in err
    assert "done." not in err
    rows = list(csv.DictReader(open(run_dir / "progress.csv")))
    assert int(rows[-1]["env_steps"]) >= 5000 and int(rows[-1]["updates"]) >= 4000
    assert int(rows[-1]["checkpoints_failed"]) >= 10  # one per 200 updates after the sabotage, the last one too
    log = (run_dir / "logs" / "single-process.log").read_text()
    assert log.count("training goes on, and failures are counted") == 1  # warned once
    assert "the final checkpoint could not be written" in log
    assert sorted(p.name for p in (run_dir / "checkpoints").iterdir()) == ["buffer.ckpt", "learner.pt"]  # no temp file
    shutil.rmtree(learner_pt)


def test_a_distributed_run_whose_final_checkpoints_fail_ends_non_zero_naming_them(tmp_path):
    """Issue 42, item 1: both components logged an error, yet `silcr train` printed "done" and exited 0, so a later
    --resume went on from stale checkpoints unawares. Now it exits EXIT_STALE_CHECKPOINT (4) and names them."""
    procs = Processes(tmp_path)
    run_dir = tmp_path / "runs" / "stale"
    train = procs.start("train", "train", "--run", "stale", "--runs-dir", str(tmp_path / "runs"), *SMALL,
                        "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--actors", "2", "--total-steps", "4000",
                        "--checkpoint-interval", "200", "--buffer-checkpoint-interval", "1")
    try:
        ckpts = run_dir / "checkpoints"
        wait_for(lambda: (ckpts / "learner.pt").exists() and (ckpts / "buffer.ckpt").exists(), 180,
                 "both first checkpoints")
        for name in ("learner.pt", "buffer.ckpt"):
            (ckpts / name).unlink()
            (ckpts / name).mkdir()  # from now on every write of it fails
        code = train.wait(600)
    finally:
        procs.stop_all()
    err = procs.log("train")
    assert code == EXIT_STALE_CHECKPOINT, err
    line = next(line for line in err.splitlines() if "could not be written" in line)
    assert "the learner and the buffer" in line and str(ckpts / "learner.pt") in line and str(ckpts / "buffer.ckpt") in line
    assert "Traceback" not in err and procs.orphans == []
    rows = list(csv.DictReader(open(run_dir / "progress.csv")))
    assert int(rows[-1]["env_steps"]) >= 4000  # the run itself finished
    for name in ("learner.pt", "buffer.ckpt"):
        shutil.rmtree(ckpts / name)


def _evil_pickle(path, marker) -> None:
    code = (f"import os, torch\nclass Evil:\n    def __reduce__(self):\n        return (os.system, ('touch {marker}',))\n"
            f"torch.save({{'sac': Evil(), 'counters': {{}}, 'config': {{}}}}, {str(path)!r})\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)


def test_a_component_that_cannot_start_is_not_restarted_and_nothing_is_rewritten(tmp_path):
    """A corrupt checkpoint under --resume: one line, exit 2, no restarts, and the other component's
    checkpoint is left byte for byte. Before: the launcher restarted the component five times, exited 1
    with a traceback, and the healthy components rewrote their checkpoints meanwhile."""
    runs = tmp_path / "runs"
    args = ["train", "--run", "bad", "--runs-dir", str(runs), *SMALL, "--actors", "1", "--total-steps", "1500",
            "--checkpoint-interval", "300"]
    first = subprocess.run(command(*args, "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"), capture_output=True,
                           text=True, timeout=600, cwd=REPO)
    assert first.returncode == 0, first.stderr
    ckpt = runs / "bad" / "checkpoints"
    good = {p.name: p.read_bytes() for p in ckpt.iterdir()}
    assert set(good) == {"learner.pt", "buffer.ckpt"}
    marker = tmp_path / "ran"
    cases = {  # the file to spoil, how, and what the one line names
        "truncated buffer": ("buffer.ckpt", lambda p: p.write_bytes(good["buffer.ckpt"][:1000]), "buffer cannot start"),
        "zeroed learner": ("learner.pt", lambda p: p.write_bytes(bytes(len(good["learner.pt"]))), "learner cannot start"),
        "a pickle that runs code": ("learner.pt", lambda p: _evil_pickle(p, marker), "could run code"),
    }
    for case, (name, spoil, needle) in cases.items():
        for n, data in good.items():
            (ckpt / n).write_bytes(data)
        spoil(ckpt / name)
        spoiled = (ckpt / name).read_bytes()
        # a larger budget, so that the checkpoints are needed (the finished run itself would start nothing at all)
        r = subprocess.run(command(*args, "--resume", "--total-steps", "3000", "--zenoh-listen",
                                   f"tcp/127.0.0.1:{free_port()}"), capture_output=True, text=True, timeout=300, cwd=REPO)
        assert r.returncode == 2, f"{case}: {r.returncode} {r.stderr}"
        errors = [line for line in r.stderr.splitlines() if "error" in line]
        assert len(errors) == 1 and needle in errors[0] and "Traceback" not in r.stderr, f"{case}: {r.stderr}"
        assert "restarting" not in r.stdout + r.stderr, case
        other = next(n for n in good if n != name)
        assert (ckpt / other).read_bytes() == good[other], f"{case}: {other} was rewritten"
        assert (ckpt / name).read_bytes() == spoiled, case
        assert sorted(p.name for p in ckpt.iterdir()) == sorted(good)  # no temporary file
    assert not marker.exists()  # the pickle's code never ran


def test_a_single_process_run_refuses_a_corrupt_learner_checkpoint_with_one_line(tmp_path):
    runs = tmp_path / "runs"
    args = ["train", "--single-process", "--run", "one", "--runs-dir", str(runs), *SMALL, "--total-steps", "800",
            "--checkpoint-interval", "200"]
    first = subprocess.run(command(*args), capture_output=True, text=True, timeout=600, cwd=REPO)
    assert first.returncode == 0, first.stderr
    learner_pt = runs / "one" / "checkpoints" / "learner.pt"
    learner_pt.write_bytes(bytes(learner_pt.stat().st_size))
    buffer_ckpt = (runs / "one" / "checkpoints" / "buffer.ckpt").read_bytes()
    r = subprocess.run(command(*args, "--resume", "--total-steps", "1600"), capture_output=True, text=True, timeout=300,
                       cwd=REPO)  # a larger budget: the finished run itself would read no checkpoint
    errors = [line for line in r.stderr.splitlines() if "error" in line]
    assert r.returncode == 2 and len(errors) == 1 and "cannot resume" in errors[0], r.stderr
    assert "Traceback" not in r.stderr
    assert (runs / "one" / "checkpoints" / "buffer.ckpt").read_bytes() == buffer_ckpt
