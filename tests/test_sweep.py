"""`silcr sweep`: experiment files, seed ranges, and resuming a cell interrupted midway."""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time

import pytest

from silcr.deploy.sweep import ExperimentError, cell_state, cells_of, load_experiment, parse_seeds, selected_cells
from silcr.learner.checkpoint import load_checkpoint
from silcr.common.run_records import wall_seconds
from tests.helpers import REPO, Processes, free_port, wait_for

EXPERIMENTS = sorted((REPO / "experiments").glob("*.toml"))


def test_seed_ranges():
    assert parse_seeds("0-4") == [0, 1, 2, 3, 4]
    assert parse_seeds("0,3,7") == [0, 3, 7]
    assert parse_seeds("0-2,5,1") == [0, 1, 2, 5]
    for bad in ("a", "4-2", "1-"):
        with pytest.raises(ExperimentError):
            parse_seeds(bad)


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.stem for p in EXPERIMENTS])
def test_shipped_experiments_are_valid(path):
    exp = load_experiment(path)
    seeds = parse_seeds(exp["seeds"])
    cells = cells_of(exp, seeds)
    per_task = sum(len(set(seeds) & set(parse_seeds(v.get("seeds", exp["seeds"])))) for v in exp["variants"].values())
    assert len(cells) == len(exp["tasks"]) * per_task
    assert len({c.name for c in cells}) == len(cells)


@pytest.mark.parametrize("path", EXPERIMENTS, ids=[p.stem for p in EXPERIMENTS])
def test_shipped_experiments_are_listed_in_the_docs(path):
    # docs/experiments.md's table is where a user finds what each file is for and what it costs.
    assert f"`experiments/{path.name}`" in (REPO / "docs" / "experiments.md").read_text()


def test_a_variant_runs_only_its_own_seeds_and_only_takes_several_texts(tmp_path):
    path = tmp_path / "x.toml"
    path.write_text('tasks = ["Hopper-v5", "Swimmer-v5"]\nseeds = "0-2"\n[variants.silcr]\nalgo = "silcr"\n'
                    '[variants.sac-dense]\nalgo = "sac"\nreward = "dense"\nseeds = "0,5"\n')
    exp = load_experiment(path)
    names = [c.name for c in cells_of(exp, [0, 1, 2])]
    assert names == ["silcr_Hopper-v5_s0", "silcr_Hopper-v5_s1", "silcr_Hopper-v5_s2", "sac-dense_Hopper-v5_s0",
                     "silcr_Swimmer-v5_s0", "silcr_Swimmer-v5_s1", "silcr_Swimmer-v5_s2", "sac-dense_Swimmer-v5_s0"]
    assert all("seeds" not in c.options for c in cells_of(exp, [0]))  # not passed on to silcr train
    assert [c.name for c in selected_cells(exp, [0, 1], "sac-,silcr_Swim", (1, 1))] == [
        "sac-dense_Hopper-v5_s0", "silcr_Swimmer-v5_s0", "silcr_Swimmer-v5_s1", "sac-dense_Swimmer-v5_s0"]
    path.write_text('tasks = ["Hopper-v5"]\n[variants.a]\nseeds = "2-1"\n')
    with pytest.raises(ExperimentError, match="seeds '2-1'"):
        load_experiment(path)


def test_paper_experiments_cover_the_papers_grid():
    paper = load_experiment(REPO / "experiments" / "paper.toml")
    assert set(paper["tasks"]) == {"Swimmer-v5", "Hopper-v5", "HalfCheetah-v5", "Walker2d-v5", "Humanoid-v5"}
    assert {(v["algo"], v.get("reward", "episodic")) for v in paper["variants"].values()} == {
        ("silcr", "episodic"), ("sac", "episodic"), ("sac", "dense"), ("sqil", "episodic"), ("gasil", "dense"),
        ("gasil", "episodic")}
    ablation = load_experiment(REPO / "experiments" / "ablation-m.toml")
    assert sorted(v["expert_capacity"] for v in ablation["variants"].values()) == [10_000, 20_000, 50_000, 100_000, 1_000_000]
    assert ablation["tasks"] == ["Humanoid-v5"]


@pytest.mark.parametrize("text, message", [
    ('tasks = ["Hopper-v5"]\n[variants.a]\nalgo = "silcr"\nbogus = 1\n', "'bogus' is not a `silcr train` option"),
    ('tasks = ["Hopper-v5"]\n[variants.a]\nseed = 3\n', "may not set 'seed'"),
    ('tasks = []\n[variants.a]\n', "'tasks' must be a non-empty list"),
    ('tasks = ["Hopper-v5"]\n', "needs at least one [variants.<name>] table"),
    ('tasks = ["Hopper-v5"\n', "not valid TOML"),
])
def test_bad_experiment_files_are_one_line_errors(tmp_path, text, message):
    path = tmp_path / "x.toml"
    path.write_text(text)
    with pytest.raises(ExperimentError) as e:
        load_experiment(path)
    assert message in str(e.value)
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "sweep", str(path), "--dry-run"],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr


SMALL_EXPERIMENT = """
name = "tiny"
tasks = ["InvertedPendulum-v5"]
[common]
hidden = [32, 32]
learning_starts = 500
batch_size = 64
eval_episodes = 1
eval_interval = 1000
spi_tolerance = 500
total_steps = 4000
checkpoint_interval = 100
buffer_checkpoint_interval = 1
stats_interval = 0.3
[variants.silcr]
algo = "silcr"
"""


def test_a_dry_run_says_how_far_a_stopped_cell_got_and_which_cells_run_now(tmp_path):
    from silcr.common.run_lock import hold

    exp = tmp_path / "tiny.toml"
    exp.write_text(SMALL_EXPERIMENT.replace('[variants.silcr]', '[variants.sac]\nalgo = "sac"\n[variants.silcr]'))
    runs = tmp_path / "runs"
    stopped = runs / "silcr_InvertedPendulum-v5_s0"
    (stopped / "checkpoints").mkdir(parents=True)
    (stopped / "checkpoints" / "learner.pt").write_bytes(b"")  # what makes a cell "partial"
    (stopped / "progress.csv").write_text("time,env_steps,updates\n1.0,1000,500\n2.0,2500,2000\n")

    def dry_run() -> list[str]:
        r = subprocess.run([sys.executable, "-m", "silcr.cli", "sweep", str(exp), "--seeds", "0", "--runs-dir",
                            str(runs), "--dry-run"], capture_output=True, text=True, cwd=REPO, timeout=60)
        assert r.returncode == 0, r.stderr
        return r.stdout.splitlines()[1:]

    assert dry_run() == ["  new      sac_InvertedPendulum-v5_s0",
                         "  partial  silcr_InvertedPendulum-v5_s0  (2,500 of 4,000 env steps)"]
    with hold(runs / "sac_InvertedPendulum-v5_s0"), hold(stopped):  # as a live `silcr train` holds its run
        assert dry_run() == ["  new      sac_InvertedPendulum-v5_s0  (running now)",
                             "  partial  silcr_InvertedPendulum-v5_s0  (2,500 of 4,000 env steps; running now)"]


def test_an_interrupted_cell_resumes_from_its_checkpoint(tmp_path):
    exp = tmp_path / "tiny.toml"
    exp.write_text(SMALL_EXPERIMENT)
    runs = tmp_path / "runs"
    cell_dir = runs / "silcr_InvertedPendulum-v5_s0"
    procs = Processes(tmp_path)
    args = ["sweep", str(exp), "--seeds", "0", "--runs-dir", str(runs), "--port-base", str(free_port())]
    try:
        # Started as a script's background job starts it, with SIGINT ignored: its cells stop on SIGINT
        # whatever they inherit, so the sweep must too, or it records the stopped cell as done.
        sweep = procs.start("sweep1", *args, new_session=True, sigint_ignored=True)
        ckpt = cell_dir / "checkpoints" / "learner.pt"
        wait_for(lambda: ckpt.exists() and load_checkpoint(ckpt)["counters"]["updates"] >= 200, 240,
                 "the cell to write learner checkpoints")
        os.killpg(sweep.pid, signal.SIGINT)  # Ctrl-C in the sweep's terminal
        assert sweep.wait(90) == 130, procs.log("sweep1")
        assert cell_state(cell_dir) == "partial"
        stopped_at = load_checkpoint(ckpt)["counters"]["updates"]
        assert stopped_at < 3400  # really midway

        # Without --resume a half-done cell stops the sweep before anything starts.
        r = subprocess.run([sys.executable, "-m", "silcr.cli", *args], capture_output=True, text=True, cwd=REPO, timeout=120)
        assert r.returncode == 2 and "--resume" in r.stderr and "Traceback" not in r.stderr, r.stderr
        assert cell_state(cell_dir) == "partial"

        sweep = procs.start("sweep2", *args, "--resume")
        assert sweep.wait(400) == 0, procs.log("sweep2") + (cell_dir / "sweep.log").read_text()[-3000:]
    finally:
        procs.stop_all()
    assert "resume silcr_InvertedPendulum-v5_s0" in procs.log("sweep2")
    assert cell_state(cell_dir) == "done"
    learner_log = (cell_dir / "logs" / "learner.log").read_text()
    assert learner_log.count("resumed from") == 1
    assert "restored D_O" in (cell_dir / "logs" / "buffer.log").read_text()
    rows = list(csv.DictReader(open(cell_dir / "progress.csv")))
    updates = [int(r["updates"]) for r in rows]
    assert updates == sorted(updates) and updates[-1] > stopped_at
    assert int(rows[-1]["env_steps"]) >= 4000
    # The marker's compute is the whole run's, as `silcr plot` counts it (every stretch in progress.csv).
    marker = json.loads((cell_dir / "sweep-done.json").read_text())
    assert marker["minutes_all_stretches"] == pytest.approx(wall_seconds(rows) / 60), marker
    # The resumed run did not collect the first part again: about one update per env step overall.
    assert load_checkpoint(cell_dir / "checkpoints" / "learner.pt")["counters"]["updates"] < 4000 + 600

    # A third run finds the cell done and starts nothing.
    r = subprocess.run([sys.executable, "-m", "silcr.cli", *args], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0 and "1 done" in r.stdout and "start" not in r.stdout
    assert procs.orphans == []
def test_invalid_cells_are_reported_together_and_a_dry_run_still_shows_the_plan(tmp_path):
    path = tmp_path / "x.toml"
    path.write_text('tasks = ["Hopper-v5", "Swimmer-v5"]\n[variants.silcr]\nalgo = "silcr"\n'
                    '[variants.sqil]\nalgo = "sqil"\ndemos = "nowhere/{task}.npz"\n')

    def sweep(*extra):
        return subprocess.run([sys.executable, "-m", "silcr.cli", "sweep", str(path), "--seeds", "0-1",
                               "--runs-dir", str(tmp_path / "runs"), *extra],
                              capture_output=True, text=True, cwd=REPO, timeout=60)

    r = sweep("--dry-run")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stdout.count("  new ") == 8  # the whole plan, valid cells included
    errors = r.stderr.strip().splitlines()
    assert len(errors) == 2  # one line per distinct problem, not per cell
    assert "nowhere/Hopper-v5.npz (2 cells: sqil_Hopper-v5_s0, sqil_Hopper-v5_s1)" in errors[0]
    assert sweep("--dry-run", "--only", "silcr").returncode == 0  # cells not selected are not checked
    r = sweep()
    assert r.returncode == 2 and len(r.stderr.strip().splitlines()) == 2
    assert not (tmp_path / "runs").exists()  # nothing started


def test_a_second_interrupt_kills_the_cells_at_once_and_leaves_nothing_behind(tmp_path):
    """Ctrl-C twice (or `kill` twice): the sweep stops its cells without waiting for them, prints one line,
    exits 130 with no traceback, and no process of theirs is left; the cell stays resumable."""
    exp = tmp_path / "tiny.toml"
    exp.write_text(SMALL_EXPERIMENT)
    runs = tmp_path / "runs"
    cell_dir = runs / "silcr_InvertedPendulum-v5_s0"
    procs = Processes(tmp_path)
    try:
        sweep = procs.start("sweep", "sweep", str(exp), "--seeds", "0", "--runs-dir", str(runs), "--port-base",
                            str(free_port()), new_session=True)
        ckpt = cell_dir / "checkpoints" / "learner.pt"
        wait_for(lambda: ckpt.exists(), 240, "the cell to write a learner checkpoint")
        os.killpg(sweep.pid, signal.SIGINT)
        time.sleep(0.3)
        sweep.send_signal(signal.SIGTERM)  # the second, while the cells are stopping
        assert sweep.wait(60) == 130, procs.log("sweep")
    finally:
        procs.stop_all()
    assert procs.orphans == []
    log = procs.log("sweep")
    assert "Traceback" not in log and ("interrupted again" in log or "interrupted;" in log), log
    assert cell_state(cell_dir) == "partial"
