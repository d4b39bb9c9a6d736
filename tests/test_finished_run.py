"""The finished-run rule (common/run_end.py): starting a finished run again, by any launcher or component, changes
nothing and exits 0 with one line; raising the budget goes on; without --resume, a new run is never started over a
run the directory holds. Real runs, real processes, real files."""

from __future__ import annotations

import hashlib
import json
import subprocess
import sys

import pytest

from silcr.common import run_layout
from silcr.deploy.local import port_in_use
from tests.helpers import REPO, free_port, wait_for

ENV = "InvertedPendulum-v5"
SMALL = ["--env", ENV, "--hidden", "16", "16", "--learning-starts", "300", "--expert-capacity", "1000",
         "--batch-size", "64", "--eval-interval", "500", "--eval-episodes", "2", "--torch-threads", "1",
         "--stats-interval", "0.3", "--spi-tolerance", "300"]


def _silcr(*args: str, timeout: float = 180) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "silcr.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=timeout)


def _fingerprint(run_dir) -> dict[str, str]:
    """Every file of the run but the lock and the logs, by content."""
    out = {}
    for path in sorted(run_dir.rglob("*")):
        rel = path.relative_to(run_dir)
        if path.is_file() and rel.parts[0] not in (run_layout.LOGS, run_layout.LOCK):
            out[str(rel)] = hashlib.sha256(path.read_bytes()).hexdigest()
    return out


def _finished_at(run_dir) -> int:
    return json.loads((run_dir / "finished.json").read_text())["env_steps"]


@pytest.mark.parametrize("mode", ["single-process", "distributed"])
def test_resume_of_a_finished_run_changes_nothing_and_exits_0(tmp_path, mode):
    runs = tmp_path / "runs"
    args = ["--run", "done", "--runs-dir", str(runs), "--total-steps", "1500", *SMALL]
    args += ["--single-process"] if mode == "single-process" else ["--actors", "2", "--zenoh-listen",
                                                                   f"tcp/127.0.0.1:{free_port()}"]
    first = _silcr("train", *args)
    assert first.returncode == 0, first.stderr
    run_dir = runs / "done"
    before = _fingerprint(run_dir)
    assert {"progress.csv", "best.silcr", "checkpoints/learner.pt", "checkpoints/buffer.ckpt",
            "finished.json"} <= before.keys()

    again = _silcr("train", *args, "--resume")
    assert again.returncode == 0, again.stderr
    lines = again.stdout.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("silcr train: run done already finished at ") and \
        "raise --total-steps to go on" in lines[0], again.stdout
    assert _fingerprint(run_dir) == before  # no row, no checkpoint, no best.silcr, no config rewritten

    # The same command without --resume (run twice, or a --run name used again) is refused: it would train from
    # scratch over the run's checkpoints, progress.csv and best.silcr.
    twice = _silcr("train", *args)
    assert twice.returncode == 2 and "Traceback" not in twice.stderr, twice.stderr
    assert twice.stderr.strip().splitlines()[-1].endswith(
        f"--run: {run_dir} already holds a run that finished at {_finished_at(run_dir)} env steps; add --resume to go "
        f"on with it, or pick another --run name (or delete the directory to start that run again)"), twice.stderr
    assert _fingerprint(run_dir) == before

    # `--resume` alone goes on with the run's own options (its config.toml), the budget among them: before, what
    # was not given again took its default (Hopper-v5, 800-400 networks, a 2M budget that reopened this run).
    bare = _silcr("train", "--run", "done", "--runs-dir", str(runs), "--resume")
    assert bare.returncode == 0 and bare.stdout.startswith("silcr train: run done already finished at "), \
        (bare.stdout, bare.stderr)
    assert _fingerprint(run_dir) == before
    # An option given again that names another run (other env, other networks), with a budget still to spend, is
    # refused on the option that differs, before config.toml is rewritten (it was: then the buffer's checkpoint
    # refused to load, and the run's config said Hopper-v5).
    more = ["--run", "done", "--runs-dir", str(runs), "--total-steps", "3000", "--resume"]
    for extra, option, held in ((["--env", "Hopper-v5"], "--env", f"env = '{ENV}', not 'Hopper-v5'"),
                                (["--hidden", "32", "32"], "--hidden", "hidden = [16, 16], not [32, 32]")):
        other = _silcr("train", *more, *extra)
        assert other.returncode == 2 and "Traceback" not in other.stderr, other.stderr
        assert other.stderr.strip().splitlines()[-1] == (
            f"silcr train: error: {option}: {run_dir} holds a run with {held}; --resume goes on with the run's own "
            f"options ({run_dir / 'config.toml'}): leave {option} out, or pick another --run name")
        assert _fingerprint(run_dir) == before
    # What that line offers: the run's own config.toml names it.
    own = _silcr("train", "--config", str(run_dir / "config.toml"), "--resume")
    assert own.returncode == 0 and "already finished at " in own.stdout, (own.stdout, own.stderr)
    assert _fingerprint(run_dir) == before

    # Each component an orchestrator would start again says the same and writes nothing.
    for role, extra in (("learner", ["--hidden", "16", "16", "--learning-starts", "300", "--resume"]),
                        ("buffer", ["--expert-capacity", "1000", "--learning-starts", "300", "--resume"]),
                        ("actor", [])):
        r = _silcr(role, "--run", "done", "--runs-dir", str(runs), "--env", ENV, "--total-steps", "1500", *extra,
                   "--connect", f"tcp/127.0.0.1:{free_port()}", timeout=60)
        assert r.returncode == 0 and r.stdout.startswith(f"silcr {role}: run done already finished at "), \
            (role, r.stdout, r.stderr)
    assert _fingerprint(run_dir) == before
    for role in ("learner", "buffer"):  # started by hand without --resume: refused as the launcher refuses
        r = _silcr(role, "--run", "done", "--runs-dir", str(runs), "--env", ENV, "--total-steps", "1500",
                   "--connect", f"tcp/127.0.0.1:{free_port()}", timeout=60)
        assert r.returncode == 2 and "already holds a run that finished" in r.stderr, (role, r.stdout, r.stderr)
    assert _fingerprint(run_dir) == before

    # A larger budget goes on from there, and the run is finished again at the new budget.
    rows_before = len((run_dir / "progress.csv").read_text().splitlines())
    more = _silcr("train", *[a if a != "1500" else "2500" for a in args], "--resume")
    assert more.returncode == 0, more.stderr
    after = (run_dir / "progress.csv").read_text().splitlines()
    assert len(after) > rows_before
    assert int(after[-1].split(",")[1]) >= 2500
    assert '"total_steps": 2500' in (run_dir / "finished.json").read_text()


def test_a_run_finished_before_the_marker_existed_is_recognised_from_its_checkpoint(tmp_path):
    runs = tmp_path / "runs"
    args = ["--run", "old", "--runs-dir", str(runs), "--total-steps", "1200", "--single-process", *SMALL]
    assert _silcr("train", *args).returncode == 0
    run_dir = runs / "old"
    (run_dir / "finished.json").unlink()  # as a run written by silcr 0.5 left it
    before = _fingerprint(run_dir)
    again = _silcr("train", *args, "--resume")
    assert again.returncode == 0 and "already finished at " in again.stdout, again.stdout + again.stderr
    assert _fingerprint(run_dir) == before


def test_a_run_stopped_midway_is_not_finished(tmp_path):
    """The rule must not stop a run that has budget left: its learner drops a stale finished.json as it goes on."""
    runs = tmp_path / "runs"
    args = ["--run", "part", "--runs-dir", str(runs), "--single-process", *SMALL]
    assert _silcr("train", *args, "--total-steps", "1000").returncode == 0
    (runs / "part" / "finished.json").unlink()  # as a run stopped midway leaves it: checkpoints, no marker
    before = _fingerprint(runs / "part")
    fresh = _silcr("train", *args, "--total-steps", "1800")
    assert fresh.returncode == 2 and "already holds a run stopped midway (its checkpoints in " in fresh.stderr, \
        fresh.stderr
    assert _fingerprint(runs / "part") == before
    more = _silcr("train", *args, "--total-steps", "1800", "--resume")
    assert more.returncode == 0 and "already finished" not in more.stdout
    assert '"total_steps": 1800' in (runs / "part" / "finished.json").read_text()


def test_the_monitor_without_a_terminal_logs_plain_lines_and_ends_with_the_run(tmp_path):
    """`docker compose logs -f monitor` read nothing: the live table drew only on a terminal. Without one, the
    monitor prints a plain line per interval, and a closing line when the run finishes (then exits 0)."""
    port = free_port()
    runs = tmp_path / "runs"
    train = subprocess.Popen([sys.executable, "-m", "silcr.cli", "train", "--run", "watched", "--runs-dir", str(runs),
                              "--total-steps", "3000", "--actors", "2", "--zenoh-listen", f"tcp/127.0.0.1:{port}",
                              *SMALL], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for(lambda: port_in_use(f"tcp/127.0.0.1:{port}"), 60, "the run's router")
        monitor = subprocess.run([sys.executable, "-m", "silcr.cli", "monitor", "--run", "watched", "--connect",
                                  f"tcp/127.0.0.1:{port}", "--zenoh-mode", "client", "--interval", "0.5"],
                                 capture_output=True, text=True, cwd=REPO, timeout=240)
        assert train.wait(120) == 0
    finally:
        train.kill()
    assert monitor.returncode == 0, monitor.stderr
    lines = monitor.stdout.splitlines()
    figures = [line for line in lines if "learner: env_steps" in line and "buffer: transitions_received" in line]
    assert len(figures) >= 3, monitor.stdout
    assert "\x1b[" not in monitor.stdout  # no terminal codes in a log
    assert "run watched finished at " in lines[-1] and "updates" in lines[-1], lines[-1]


def test_the_python_api_refuses_a_run_name_whose_directory_holds_a_run(tmp_path):
    from silcr import SILCR

    opts = dict(hidden=(16, 16), learning_starts=300, expert_capacity=1000, batch_size=64, eval_interval=500,
                eval_episodes=1, torch_threads=1)
    with SILCR(ENV, run="named", runs_dir=str(tmp_path), **opts) as first:
        first.learn(600)
    before = _fingerprint(tmp_path / "named")
    # In the API's words: `resume` is not one of its options, so the refusal says what an API user can do.
    go_on = f"pick another run name .* silcr train --config {tmp_path / 'named' / 'config.toml'} --resume"
    again = SILCR(ENV, run="named", runs_dir=str(tmp_path), **opts)
    with pytest.raises(ValueError, match=f"^run: .*already holds a run that finished at .*{go_on}$"):
        again.learn(600)
    again.close()
    distributed = SILCR(ENV, run="named", runs_dir=str(tmp_path), actors=1, **opts)  # refused before a process starts
    with pytest.raises(ValueError, match=f"^run: .*already holds a run that finished at .*{go_on}$"):
        distributed.learn(600)
    distributed.close()
    assert _fingerprint(tmp_path / "named") == before
