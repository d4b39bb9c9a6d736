"""What a new user hit with the Python API (issue 60), on real processes: Ctrl-C during a distributed `learn` keeps
the model and a second `learn` resumes; a callback's rows are typed alike in both modes and its exception stops
training and reaches the caller; a short run stops at its budget; a script without a `__main__` guard, or read
from standard input, trains with actors."""

from __future__ import annotations

import csv
import json
import os
import re
import signal
import subprocess
import sys
import textwrap

import pytest

from tests.helpers import REPO, wait_for

ENV = "InvertedPendulum-v5"
SMALL = dict(hidden=(16, 16), learning_starts=300, batch_size=64, eval_interval=500, eval_episodes=2, torch_threads=1,
             checkpoint_interval=200, stats_interval=0.3, spi_tolerance=300)



def _json_line(stream) -> dict:
    """The script's next JSON line, past any other (the launcher's own lines, and, before the launcher's session
    kept zenoh's logger off, a Zenoh ERROR such as "Received Data for unknown expr_id" at Ctrl-C)."""
    while (line := stream.readline()) and not line.startswith("{"):
        pass
    return json.loads(line)

def _script(body: str, runs_dir) -> str:
    """A user's script: no `if __name__ == "__main__":` guard, as a notebook cell or a quick script has none."""
    return textwrap.dedent(f"""
        import json, sys
        import silcr
        from silcr import SILCR
        SMALL = {SMALL!r}
        RUNS = {str(runs_dir)!r}
    """) + textwrap.dedent(body)


def _python(code: str, timeout: float = 300, stdin: bool = False) -> subprocess.CompletedProcess:
    args = [sys.executable, "-"] if stdin else [sys.executable, "-c", code]
    return subprocess.run(args, input=code if stdin else None, capture_output=True, text=True, cwd=REPO,
                          timeout=timeout)


def _rows(run_dir) -> list[dict[str, str]]:
    with open(run_dir / "progress.csv", newline="") as f:
        return list(csv.DictReader(f))


def test_ctrl_c_during_a_distributed_learn_keeps_the_model_and_the_next_learn_resumes(tmp_path):
    code = _script("""
        model = SILCR("InvertedPendulum-v5", actors=2, runs_dir=RUNS, run="interrupted", **SMALL)
        try:
            model.learn(10_000_000)
        except KeyboardInterrupt:
            print(json.dumps({"interrupted_at": model.num_timesteps,
                              "action": float(model.predict([0.0, 0.0, 0.0, 0.0])[0][0])}), flush=True)
        sys.stdin.readline()  # the test has counted the rows
        model.learn(600)
        print(json.dumps({"after": model.num_timesteps}), flush=True)
    """, tmp_path)
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO, start_new_session=True)
    run_dir = tmp_path / "interrupted"
    try:
        wait_for(lambda: (run_dir / "checkpoints" / "learner.pt").exists() and run_dir.joinpath("progress.csv").exists()
                 and len(_rows(run_dir)) >= 3, 240, "two evaluations and a learner checkpoint")
        os.killpg(proc.pid, signal.SIGINT)  # Ctrl-C reaches the whole foreground group, as in a terminal
        first = _json_line(proc.stdout)
        rows_before = len(_rows(run_dir))
        proc.stdin.write("\n")
        proc.stdin.flush()
        second = _json_line(proc.stdout)
        assert proc.wait(300) == 0, proc.stderr.read()
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    assert first["interrupted_at"] >= 1000, first  # what the run had trained, not 0
    assert second["after"] >= first["interrupted_at"] + 600
    rows = _rows(run_dir)
    assert len(rows) > rows_before  # went on: progress.csv kept its rows, none were overwritten
    steps = [int(r["env_steps"]) for r in rows]
    assert steps[0] == 0 and steps.count(0) == 1, steps


@pytest.mark.parametrize("actors", [0, 2])
def test_a_callbacks_rows_are_numbers_and_its_exception_stops_training_and_reaches_the_caller(tmp_path, actors):
    code = _script(f"""
        seen = []
        def callback(info):
            row = info["row"]
            seen.append(row)
            if row["env_steps"] >= 1000:  # a number in both modes
                raise ValueError("enough")
        model = SILCR("InvertedPendulum-v5", actors={actors}, runs_dir=RUNS, run="cb", **SMALL)
        try:
            model.learn(50_000, callback=callback)
        except ValueError as e:
            print(json.dumps({{"raised": str(e), "steps": model.num_timesteps,
                              "types": sorted({{type(v).__name__ for r in seen for v in r.values()}}),
                              "rows": len(seen)}}))
        model.close()
    """, tmp_path)
    r = _python(code)
    assert r.returncode == 0, r.stderr[-3000:]
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["raised"] == "enough" and out["rows"] >= 2
    assert set(out["types"]) <= {"int", "float", "str"} and {"int", "float"} <= set(out["types"])
    assert 1000 <= out["steps"] < 20_000  # stopped soon after, not at the budget
    assert (tmp_path / "cb" / "checkpoints" / "learner.pt").exists()  # a clean stop: checkpoints written


def test_a_run_shorter_than_learning_starts_stops_at_its_budget(tmp_path):
    """learn(4000) with 2 actors at the default --learning-starts (10,240) ended at 11,441 env steps: the actors
    ran unthrottled until the learner joined."""
    code = _script("""
        opts = dict(SMALL, learning_starts=10_240)
        model = SILCR("InvertedPendulum-v5", actors=2, runs_dir=RUNS, run="short", **opts)
        model.learn(3000)
        print(json.dumps({"steps": model.num_timesteps}))
    """, tmp_path)
    r = _python(code)
    assert r.returncode == 0, r.stderr[-3000:]
    steps = json.loads(r.stdout.strip().splitlines()[-1])["steps"]
    assert 3000 <= steps <= 3600, steps


def test_a_script_read_from_standard_input_trains_with_actors(tmp_path):
    """`python - <<EOF`: multiprocessing's spawn could not start the router (`FileNotFoundError: <stdin>`); with
    a restart, the whole script ran again in the child. The components are `silcr` processes of their own."""
    code = _script("""
        print("the script ran", flush=True)
        model = SILCR("InvertedPendulum-v5", actors=2, runs_dir=RUNS, run="stdin", **SMALL)
        model.learn(1200)
        print(json.dumps({"steps": model.num_timesteps}))
    """, tmp_path)
    r = _python(code, stdin=True)
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.count("the script ran") == 1
    assert json.loads(r.stdout.strip().splitlines()[-1])["steps"] >= 1200
    logs = "".join(p.read_text() for p in (tmp_path / "stdin" / "logs").glob("*.log"))
    assert "the script ran" not in logs and "Traceback" not in logs


def test_zenoh_writes_nothing_to_a_distributed_api_users_standard_output(tmp_path):
    """Zenoh's logger writes to file descriptor 1: the launcher's own session, in the user's process, put its lines
    (an ERROR at Ctrl-C; with RUST_LOG=info, every session's start and close) among the script's output."""
    code = _script("""
        model = SILCR("InvertedPendulum-v5", actors=1, runs_dir=RUNS, run="quiet", **SMALL)
        model.learn(800, progress_bar=False)
        print("the script's own line")
    """, tmp_path)
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=300,
                       env={**os.environ, "RUST_LOG": "info"})
    assert r.returncode == 0, r.stderr[-3000:]
    assert r.stdout.strip() == "the script's own line", r.stdout[-2000:]
    assert "zenoh" in (tmp_path / "quiet" / "logs" / "learner.log").read_text()  # the components still log theirs


def test_the_smaller_things_a_new_user_saw(tmp_path):
    """Issue 60, item 6: a model's observation space is the env's own; a loaded model reports the env steps it
    trained; a file that is not a model says so; `silcr plot` takes a run's progress.csv; the API names runs as the
    command line does."""
    import gymnasium as gym

    from silcr import SILCR
    from silcr.learner.model_file import ModelFileError

    model = SILCR("MountainCarContinuous-v0", runs_dir=tmp_path, hidden=(8, 8), learning_starts=100,
                  expert_capacity=1000, eval_interval=300, eval_episodes=1, torch_threads=1)
    space = gym.make("MountainCarContinuous-v0").observation_space
    assert model.observation_space == space  # Box([-1.2, -0.07], [0.6, 0.07]), not (-inf, inf)
    assert re.fullmatch(r"MountainCarContinuous-v0-silcr-\d{8}-\d{6}-[0-9a-f]{4}", model.run_dir.name)
    model.learn(400)
    model.save(tmp_path / "m.silcr")
    model.close()
    assert SILCR.load(tmp_path / "m.silcr").num_timesteps == model.num_timesteps >= 400
    (tmp_path / "junk.silcr").write_text("not a model")
    with pytest.raises(ModelFileError, match=r"is unreadable or corrupt \(not a torch file\)$"):
        SILCR.load(tmp_path / "junk.silcr")
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", str(model.run_dir / "progress.csv"), "-o",
                        str(tmp_path / "c.png")], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    assert "for the run (" in r.stdout  # not "for the 1 runs together"
