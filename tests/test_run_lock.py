"""One run directory, one run: a second launcher, or a --resume of a live run, is refused before it writes.

Before the lock, two `silcr train` with the same --run in the same directory both ran and both
reported done: progress.csv ended with rows of both interleaved and config.toml held the
second run's seed.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys

from silcr.common.run_lock import RunInUse, check_free, hold
from tests.helpers import REPO, Processes, free_port, wait_for

SINGLE = ["--env", "InvertedPendulum-v5", "--hidden", "32", "32", "--learning-starts", "200", "--batch-size", "32",
          "--eval-interval", "1000", "--eval-episodes", "1", "--single-process"]


def _train(tmp_path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "silcr.cli", "train", "--run", "one", "--runs-dir",
                           str(tmp_path / "runs"), *args], capture_output=True, text=True, timeout=120, cwd=REPO)


def test_a_second_launcher_and_a_resume_of_a_live_run_are_refused_before_writing(tmp_path):
    procs = Processes(tmp_path)
    run_dir = tmp_path / "runs" / "one"
    port = free_port()
    first = procs.start("first", "train", "--run", "one", "--runs-dir", str(tmp_path / "runs"), "--seed", "1",
                        "--total-steps", "200000", "--zenoh-listen", f"tcp/127.0.0.1:{port}", *SINGLE)
    try:
        wait_for(lambda: (run_dir / "progress.csv").exists(), 120, "the first run's progress.csv")
        before = {p.name: p.read_bytes() for p in run_dir.iterdir() if p.name in ("config.toml", ".lock")}
        for extra in ([], ["--resume"], ["--zenoh-listen", f"tcp/127.0.0.1:{free_port()}"]):
            second = _train(tmp_path, "--seed", "2", "--total-steps", "2000", *SINGLE, *extra)
            assert second.returncode == 2 and "Traceback" not in second.stderr, second.stderr
            assert f"is in use by a live run (process {first.pid})" in second.stderr, second.stderr
        # a distributed launcher too, refused before its port check or its router
        second = _train(tmp_path, "--seed", "2", "--zenoh-listen", f"tcp/127.0.0.1:{port}")
        assert second.returncode == 2 and "in use by a live run" in second.stderr, second.stderr
        assert {p.name: p.read_bytes() for p in run_dir.iterdir() if p.name in before} == before
        assert b"seed = 1" in before["config.toml"]
        assert first.poll() is None  # the live run goes on
        # a crashed launcher leaves no stale lock: the kernel drops it with the process
        os.kill(first.pid, signal.SIGKILL)
        first.wait(30)
    finally:
        procs.stop_all()
    resumed = _train(tmp_path, "--seed", "1", "--total-steps", "2000", *SINGLE, "--resume")
    assert resumed.returncode == 0, resumed.stderr[-2000:]


def test_the_lock_is_held_for_the_block_and_released_after(tmp_path):
    run_dir = tmp_path / "r"
    check_free(run_dir)
    assert not run_dir.exists()  # checking creates nothing
    with hold(run_dir):
        child = subprocess.run([sys.executable, "-c", "import sys; from pathlib import Path; "
                                "from silcr.common.run_lock import check_free, RunInUse\n"
                                "try:\n    check_free(Path(sys.argv[1]))\nexcept RunInUse as e:\n    print(e)",
                                str(run_dir)], capture_output=True, text=True, timeout=60)
        assert f"in use by a live run (process {os.getpid()})" in child.stdout, child.stdout + child.stderr
    check_free(run_dir)  # released
    try:
        with hold(run_dir):
            with hold(run_dir):  # a second open file description of the same lock is refused, even in one process
                pass
        raise AssertionError("the second hold should have been refused")
    except RunInUse:
        pass
