"""A full disk is survived (issue 63): a distributed run whose run directory is on a small tmpfs that fills up
mid-run finishes its budget, with no traceback, a well-formed progress.csv whose rows caught up, and no
temporary file left behind. Before: the TensorBoard writer's thread raised ENOSPC and the learner died (exit 120);
the launcher then crashed writing pids.json (exit 1 at 8,884 of 30,000 steps, a 0-byte .pids.json.tmp left).

The disk stays full until the learner's stats (over Zenoh, off the disk) show a failed checkpoint and a progress row
that waits to be written (`records_waiting`), and at least 10 s: a fixed 30 s let a fast machine finish the whole
budget on a full disk. Shown failing when held rows are given up instead: the learner never holds one back.

Needs root (to mount the tmpfs); skipped with the reason otherwise.
"""

from __future__ import annotations

import csv
import os
import subprocess
import sys
import time

import pytest

from silcr.common import protocol as P
from silcr.learner.progress import PROGRESS_COLUMNS
from tests.helpers import REPO, LatestJson, client_when_up, free_port, wait_for

pytestmark = pytest.mark.slow


@pytest.fixture
def small_disk(tmp_path):
    if os.geteuid() != 0:
        pytest.skip("needs root to mount a tmpfs")
    disk = tmp_path / "disk"
    disk.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=40m", "tmpfs", str(disk)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({r.stderr.strip()})")
    yield disk
    subprocess.run(["umount", "-l", str(disk)], capture_output=True)


def _fill(disk) -> None:
    """Take every free byte of the disk."""
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT, 0o644)
    try:
        for size in (1 << 20, 4096, 1):
            try:
                while True:
                    os.write(fd, b"\0" * size)
            except OSError:
                pass
    finally:
        os.close(fd)


def test_a_run_whose_disk_fills_up_finishes_its_budget(small_disk, tmp_path):
    runs = small_disk / "runs"
    total = 9000
    port = free_port()
    keys = P.Keys("full")
    train = subprocess.Popen(
        [sys.executable, "-m", "silcr.cli", "train", "--run", "full", "--runs-dir", str(runs), "--env",
         "InvertedPendulum-v5", "--hidden", "32", "32", "--learning-starts", "500", "--expert-capacity", "1000",
         "--batch-size", "64", "--eval-interval", "500", "--eval-episodes", "2", "--checkpoint-interval", "300",
         "--buffer-checkpoint-interval", "2", "--stats-interval", "0.3", "--spi-tolerance", "300",
         "--torch-threads", "1", "--actors", "2", "--total-steps", str(total), "--zenoh-listen",
         f"tcp/127.0.0.1:{port}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    run_dir = runs / "full"
    session = None
    try:
        session = client_when_up(port)
        stats = LatestJson(session, keys.stats_learner)
        wait_for(lambda: (run_dir / "checkpoints" / "learner.pt").exists() and (run_dir / "progress.csv").exists()
                 and len((run_dir / "progress.csv").read_text().splitlines()) >= 4, 300, "a few rows and checkpoints")
        _fill(small_disk)
        filled = time.monotonic()
        wait_for(lambda: train.poll() is not None or ((s := stats.get(keys.stats_learner) or {})
                 and s.get("checkpoints_failed", 0) > 0 and s.get("records_waiting", 0) > 0), 300,
                 "the learner to meet the full disk")
        assert train.poll() is None, "the run ended before the learner held a row back on the full disk"
        time.sleep(max(0.0, 10 - (time.monotonic() - filled)))
        full_rows = len((run_dir / "progress.csv").read_text().splitlines())
        (small_disk / "filler").unlink()
        out, err = train.communicate(timeout=600)
    finally:
        if train.poll() is None:
            train.kill()
        if session is not None:
            session.close()
    assert train.returncode == 0, err[-3000:]
    logs = {p.name: p.read_text() for p in (run_dir / "logs").glob("*.log")}
    assert "Traceback" not in out + err and not any("Traceback" in text for text in logs.values()), \
        {k: v[-1500:] for k, v in logs.items() if "Traceback" in v} or err[-2000:]
    # the disk did fill while the learner wrote: its checkpoints failed (counted in the rows that waited), and
    # once there was room it said so (what it logged while the disk was full was lost with the room)
    assert "progress.csv is written again" in logs["learner.log"], logs["learner.log"][-2000:]
    with open(run_dir / "progress.csv", newline="") as f:
        reader = csv.reader(f)
        header = next(reader)
        rows = list(reader)
    assert header == PROGRESS_COLUMNS and all(len(r) == len(header) for r in rows)
    steps = [int(r[header.index("env_steps")]) for r in rows]
    assert steps == sorted(steps) and steps[-1] >= total
    # the rows of the evaluations made while the disk was full waited and were written: no hole in the schedule.
    # Rows are about 500 env steps apart when the learner keeps pace; a catch-up after a stall (the TensorBoard
    # writer reopened, acks held) stretched one gap to 1,093 here, so the hole looked for is over 2,000: the
    # rows of the 10 s or more of full disk given up rather than held.
    assert max(b - a for a, b in zip(steps, steps[1:])) <= 2000, steps
    assert len(rows) > full_rows
    assert max(int(r[header.index("checkpoints_failed")]) for r in rows) > 0
    leftovers = [p.name for p in run_dir.rglob("*") if ".tmp" in p.name]
    assert leftovers == []
