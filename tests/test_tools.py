"""`silcr plot` and `silcr eval` on small, real files."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch

from silcr.common.config import Config
from silcr.plot import plot, summary_markdown
from silcr.common.run_records import label_by_variant, load_run
from silcr.learner.checkpoint import save_checkpoint
from silcr.learner.sac import Sac, SacHyper
from tests.helpers import REPO


def _fake_run(root, env, algo, seed, steps, returns):
    d = root / f"{env}-{algo}-{seed}"
    d.mkdir()
    Config(run=d.name, env=env, algo=algo, seed=seed, reward="dense").save(d / "config.toml")
    rows = ["time,env_steps,updates,policy_version,eval_return"]
    rows += [f"0,{s},{s},0,{r}" for s, r in zip(steps, returns)]
    (d / "progress.csv").write_text("\n".join(rows) + "\n")
    return d


def test_plot_draws_one_panel_per_task_and_one_curve_per_algorithm(tmp_path):
    dirs = []
    for env in ("Hopper-v5", "Walker2d-v5"):
        for algo in ("silcr", "sac"):
            for seed in (0, 1):
                dirs.append(_fake_run(tmp_path, env, algo, seed, [0, 1000, 2000], [1, 10 + seed, 20 + 5 * seed]))
    runs = [load_run(d) for d in dirs]
    fig = plot(runs, tmp_path / "out" / "fig.png", expert=30.0)
    panels = [ax for ax in fig.axes if ax.get_visible()]
    assert [ax.get_title() for ax in panels] == ["Hopper-v5", "Walker2d-v5"]
    for ax in panels:
        solid = [l for l in ax.get_lines() if l.get_linestyle() == "-"]
        dashed = [l for l in ax.get_lines() if l.get_linestyle() == "--"]
        assert len(solid) == 2 and len(dashed) == 1
        mean_at_end = {l.get_label().split()[0]: l.get_ydata()[-1] for l in solid}
        assert mean_at_end["silcr"] == pytest.approx(22.5)  # mean of seeds 20 and 25
    assert (tmp_path / "out" / "fig.png").stat().st_size > 1000
    assert (tmp_path / "out" / "fig.svg").exists()
    table = summary_markdown(runs)
    assert table.count("\n") == 2 + 4 + 2  # head, 4 groups, a blank line and the wall time in all
    assert "| Hopper-v5 | silcr | 2 | 2,000 | 22.5 ± 2.5 | 22.5 ± 2.5 |" in table
    # --final-evals 2: the mean of the last two evaluations, (10 + 20) / 2 and (11 + 25) / 2
    assert "| Hopper-v5 | silcr | 2 | 2,000 | 16.5 ± 1.5 | 22.5 ± 2.5 |" in summary_markdown(runs, final_evals=2)


def test_a_group_keeps_its_colour_in_every_panel_and_steps_read_in_thousands(tmp_path):
    """ircr runs on Hopper only: without one colour per group, Walker2d's silcr would take
    the colour ircr has on Hopper."""
    from silcr.figures import steps_tick as _steps_tick

    runs = [load_run(_fake_run(tmp_path, env, algo, 0, [0, 100_000, 200_000], [0, 1, 2]))
            for env, algo in (("Hopper-v5", "ircr"), ("Hopper-v5", "silcr"), ("Walker2d-v5", "silcr"))]
    fig = plot(runs, tmp_path / "fig.png")
    colours = [{line.get_label().split()[0]: line.get_color() for line in ax.get_lines()} for ax in fig.axes]
    assert colours[0]["silcr"] == colours[1]["silcr"] != colours[0]["ircr"]
    assert [_steps_tick(v, 0) for v in (0, 500, 25_000, 200_000, 2_000_000)] == ["0", "500", "25k", "200k", "2M"]


def test_plot_rejects_a_directory_that_is_not_a_run(tmp_path):
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", str(tmp_path), "-o", str(tmp_path / "f.png")],
                       capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and "not a run directory" in r.stderr and "Traceback" not in r.stderr


@pytest.fixture
def checkpoint(tmp_path):
    torch.manual_seed(0)
    sac = Sac(4, 1, [16], SacHyper(), torch.device("cpu"))
    cfg = Config(run="ck", env="InvertedPendulum-v5", hidden=[16])
    path = tmp_path / "learner.pt"
    save_checkpoint(path, {"sac": sac.state_dict(), "counters": {"policy_version": 3}, "config": cfg.to_dict()})
    return path


def test_eval_reports_mean_and_std(checkpoint):
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(checkpoint), "--episodes", "3"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    assert "InvertedPendulum-v5, policy version 3: return" in r.stdout and "over 3 episodes" in r.stdout
    # --json: every episode, and a summary that is theirs (the same episodes as the text: same seeds)
    j = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(checkpoint), "--episodes", "3", "--json"],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert j.returncode == 0, j.stderr
    out = json.loads(j.stdout)
    eps = out["episodes"]
    assert [e["seed"] for e in eps] == [12345, 12346, 12347] and out["deterministic"] is True
    assert out["return_mean"] == pytest.approx(sum(e["return"] for e in eps) / 3)
    assert out["length_mean"] == pytest.approx(sum(e["length"] for e in eps) / 3)
    assert out["episodes_at_time_limit"] == sum(e["truncated"] for e in eps)
    # InvertedPendulum-v5 pays 1 a step, none for the step that falls; this untrained policy falls every time
    assert all(e["terminated"] and e["return"] == e["length"] - 1 for e in eps)
    assert f"return {out['return_mean']:.1f} ± {out['return_std']:.1f}" in r.stdout
    assert f"median {out['return_median']:.1f}" in r.stdout and "0 of 3 ran to the time limit" in r.stdout


def test_eval_writes_a_video_when_a_renderer_exists(checkpoint, tmp_path):
    from silcr.learner.evaluate import _render_env

    try:
        _render_env("InvertedPendulum-v5").close()
    except RuntimeError as e:
        pytest.skip(str(e))
    video = tmp_path / "ep.mp4"
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(checkpoint), "--episodes", "1", "--video", str(video)],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0, r.stderr
    import imageio.v2 as imageio

    frames = imageio.mimread(video)
    assert len(frames) >= 2 and np.asarray(frames[0]).ndim == 3


def test_eval_rejects_a_corrupt_checkpoint(tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint")
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(bad)], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and "corrupt" in r.stderr and "Traceback" not in r.stderr


def test_a_checkpoint_that_would_run_code_is_refused_without_running_it(tmp_path):
    """Checkpoints are pickles: `silcr eval` on a file from elsewhere must not execute what it names."""
    marker = tmp_path / "ran"
    evil = tmp_path / "evil.pt"
    code = (f"import os, torch\nclass Evil:\n    def __reduce__(self):\n        return (os.system, ('touch {marker}',))\n"
            f"torch.save({{'sac': Evil(), 'counters': {{}}, 'config': {{}}}}, {str(evil)!r})\n")
    subprocess.run([sys.executable, "-c", code], check=True, timeout=60)
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "eval", str(evil)], capture_output=True, text=True, cwd=REPO,
                       timeout=60)
    assert r.returncode == 2 and "could run code" in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not marker.exists()


def test_plot_labels_separate_algorithms_rewards_and_expert_sizes(tmp_path):
    from silcr.common.config import Config

    specs = [("silcr", "episodic", 50_000), ("silcr", "episodic", 10_000), ("sac", "dense", 50_000), ("sqil", "episodic", 50_000),
             ("gasil", "dense", 50_000), ("gasil", "episodic", 10_000)]
    labels = []
    for i, (algo, reward, m) in enumerate(specs):
        d = tmp_path / f"r{i}"
        d.mkdir()
        Config(run=d.name, env="Humanoid-v5", algo=algo, reward=reward, expert_capacity=m).save(d / "config.toml")
        (d / "progress.csv").write_text("time,env_steps,updates,policy_version,eval_return\n0,0,0,0,1\n")
        labels.append(load_run(d).algo)
    assert labels == ["silcr", "silcr (M=1e4)", "sac-dense", "sqil", "gasil-dense", "gasil-episodic (M=1e4)"]


def test_gasil_settings_label_only_gasil_runs(tmp_path):
    """A run of another algorithm is not labelled with GASIL's settings, and a run from before an option
    existed reads as its default (here tanh_log_prob and GASIL's options, added later)."""
    from silcr.common.run_records import distinguish

    dirs = []
    for i, (algo, alpha) in enumerate([("gasil", 0.1), ("gasil", 0.3), ("silcr", 0.1), ("sac", 0.1)]):
        d = tmp_path / f"r{i}"
        d.mkdir()
        cfg = Config(run=d.name, env="Hopper-v5", algo=algo, reward="dense", gasil_alpha=alpha).to_dict()
        if algo == "sac":  # an old run's config.toml: no GASIL keys at all
            cfg = {k: v for k, v in cfg.items() if not k.startswith(("gasil_", "disc_", "recent_", "tanh_log_prob"))}
        import tomli_w

        (d / "config.toml").write_text(tomli_w.dumps(cfg))
        (d / "progress.csv").write_text("time,env_steps,updates,policy_version,eval_return\n0,0,0,0,1\n")
        dirs.append(d)
    assert [r.algo for r in distinguish([load_run(d) for d in dirs])] == [
        "gasil-dense gasil_alpha=0.1", "gasil-dense gasil_alpha=0.3", "silcr", "sac-dense"]


def test_plot_keeps_runs_of_different_settings_apart_and_plots_other_columns(tmp_path):
    from silcr.common.config import Config
    from silcr.common.run_records import distinguish

    dirs = []
    for i, (tau, admission, seed) in enumerate([(0.05, "return", 0), (0.05, "return", 1), (0.005, "return", 0),
                                               (0.005, "recent", 0), (0.005, "return", 0)]):
        d = tmp_path / f"r{i}"
        d.mkdir()
        algo = "sac" if i == 4 else "silcr"  # SAC has no D_E: its label leaves expert_admission out
        Config(run=d.name, env="Hopper-v5", algo=algo, tau=tau, expert_admission=admission, seed=seed).save(d / "config.toml")
        (d / "progress.csv").write_text("env_steps,eval_return,expert_min_return,q_bound_exceeded\n"
                                        f"0,1,,0\n1000,{2 + i},{5 + i},{i}\n2000,{3 + i},{6 + i},{2 * i}\n")
        dirs.append(d)
    runs = distinguish([load_run(d) for d in dirs])
    assert [r.algo for r in runs] == ["silcr expert_admission=return tau=0.05"] * 2 + [
        "silcr expert_admission=return tau=0.005", "silcr expert_admission=recent tau=0.005", "sac-episodic tau=0.005"]
    table = summary_markdown(runs)
    assert "| silcr expert_admission=return tau=0.05 | 2 |" in table and "1/2 (1,000)" in table
    assert "| silcr expert_admission=recent tau=0.005 | 1 |" in table and "1/1 (1,000)" in table
    minimum = load_run(dirs[3], "expert_min_return")  # rows without a value yet are left out
    assert list(minimum.steps) == [1000, 2000] and list(minimum.returns) == [8, 9]
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "--metric", "q_max", "-o",
                        str(tmp_path / "q.png")], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert r.returncode == 2 and "no values of q_max" in r.stderr and "Traceback" not in r.stderr


def test_a_resumed_run_plots_the_rows_written_after_the_resume(tmp_path):
    """Rows to 3,000 steps were written, then the run resumed from a checkpoint taken at about 2,200 steps;
    the final evaluation shares the last scheduled one's step count and is kept."""
    d = _fake_run(tmp_path, "Hopper-v5", "silcr", 0, [0, 1000, 2000, 3000, 2500, 3000, 4000, 4000],
                  [1, 2, 3, 99, 4, 5, 6, 7])
    run = load_run(d)
    assert list(run.steps) == [0, 1000, 2000, 2500, 3000, 4000, 4000] and list(run.returns) == [1, 2, 3, 4, 5, 6, 7]


def test_a_metric_can_be_one_column_over_another(tmp_path):
    """`--metric q_max/q_bound`: the critics' distance to the soft-Q bound; rows missing either are left out."""
    d = _fake_run(tmp_path, "Humanoid-v5", "silcr", 0, [0, 1000, 2000], [1, 2, 3])
    text = (d / "progress.csv").read_text().splitlines()
    extra = [",q_max,q_bound", ",,", ",50,100", ",120,100"]
    (d / "progress.csv").write_text("\n".join(row + e for row, e in zip(text, extra)) + "\n")
    run = load_run(d, metric="q_max/q_bound")
    assert list(run.steps) == [1000, 2000] and list(run.returns) == [0.5, 1.2]
    with pytest.raises(ValueError, match="no values of q_max/alpha"):
        load_run(d, metric="q_max/alpha")


def test_the_table_adds_each_resumed_stretch_to_a_run_s_wall_time(tmp_path):
    """progress.csv's time restarts at zero when a run resumes: 1,800 s, then 900 s more after the
    resume (rows it wrote again included) is 0.75 h, not the last row's 0.25 h."""
    d = _fake_run(tmp_path, "Hopper-v5", "silcr", 0, [0, 1000, 2000, 1500, 3000], [1, 2, 3, 4, 5])
    text = (d / "progress.csv").read_text().splitlines()
    times = [600, 1200, 1800, 300, 900]
    (d / "progress.csv").write_text("\n".join([text[0]] + [f"{t}{row[1:]}" for t, row in zip(times, text[1:])]) + "\n")
    run = load_run(d)
    assert run.wall_s == 2700
    table = summary_markdown([run, load_run(_fake_run(tmp_path, "Hopper-v5", "silcr", 1, [0, 1000], [1, 2]))])
    assert "| 0.75 |" in table and "Wall time: 0.75 h for the 2 runs together" in table
    assert "distributed run's processes keep several cores busy" in table  # _fake_run's config is distributed
    single = _fake_run(tmp_path, "Hopper-v5", "silcr", 2, [0, 1000], [1, 2])
    Config(run=single.name, env="Hopper-v5", algo="silcr", seed=2, single_process=True).save(single / "config.toml")
    assert "one torch thread keeps about one core busy" in summary_markdown([load_run(single)])
    assert "1 of the runs are `--single-process`" in summary_markdown([run, load_run(single)])


def test_groups_are_listed_with_the_numbers_in_their_names_in_order(tmp_path):
    """An ablation's variants (silcr-M1000 ... silcr-M100000) read in the order of M, not of characters."""
    dirs = []
    for variant, m in [("silcr-M10000", 10000), ("silcr-M1000", 1000), ("silcr-M100000", 100000), ("silcr-M2000", 2000)]:
        d = tmp_path / f"{variant}_HalfCheetah-v5_s0"
        d.mkdir()
        Config(run=d.name, env="HalfCheetah-v5", algo="silcr", seed=0, expert_capacity=m).save(d / "config.toml")
        (d / "progress.csv").write_text(f"time,env_steps,updates,policy_version,eval_return\n0,0,0,0,0\n1,1000,1,0,{m}\n")
        dirs.append(d)
    runs = [load_run(d) for d in dirs]
    assert label_by_variant(runs)
    rows = [line.split(" | ")[1] for line in summary_markdown(runs).splitlines() if line.startswith("| HalfCheetah")]
    assert rows == ["silcr-M1000", "silcr-M2000", "silcr-M10000", "silcr-M100000"]


def test_the_interval_figure_colours_each_group_as_the_curves_do(tmp_path, monkeypatch):
    """The curves colour groups in sorted order over all of them; the interval figure (which shows only
    groups on every task) must give each the same colour, not rliable's palette in its own order.
    Its x label clears the tick labels, and a one-seed group's zero-width bar at the end of the
    axis is drawn whole."""
    pytest.importorskip("rliable")
    from rliable import plot_utils

    from silcr.figures import group_colours
    from silcr.stats import _interval_figure

    seen, drawn = {}, []
    real = plot_utils.plot_interval_estimates

    def spy(*args, **kwargs):
        seen.update(kwargs["colors"])
        drawn.append(real(*args, **kwargs))
        return drawn[-1]

    monkeypatch.setattr(plot_utils, "plot_interval_estimates", spy)
    three, one = (20.0, np.array([10.0, 30.0])), (5.0, np.array([5.0, 5.0]))
    per_task = {"A": {"ircr": three, "sac-dense": one, "silcr": three, "gasil": three},
                "B": {"ircr": three, "sac-dense": one, "silcr": three}}  # gasil on one task only: not in the figure
    seeds = {env: {label: 1 if label == "sac-dense" else 3 for label in groups} for env, groups in per_task.items()}
    _interval_figure(per_task, seeds, tmp_path / "f.png")
    colour = group_colours({"gasil", "ircr", "sac-dense", "silcr"})  # what the curves' figure uses
    assert seen == {"ircr": colour["ircr"], "sac-dense (one seed)": colour["sac-dense"], "silcr": colour["silcr"]}
    assert len(set(seen.values())) == 3 and (tmp_path / "f.png").stat().st_size > 1000
    fig, axes = drawn[0]
    renderer = fig.canvas.get_renderer()
    (xlabel,) = fig.texts
    label_box = xlabel.get_window_extent(renderer)
    for ax in axes:
        assert ax.get_xlim()[0] < 5.0  # sac-dense's 5.0 is the lowest value: inside the axis, not on its edge
        for tick in ax.get_xticklabels():
            if tick.get_visible() and tick.get_text():
                assert not label_box.overlaps(tick.get_window_extent(renderer)), tick.get_text()


def test_plot_stats_rliable_gives_iqm_intervals_normalised_aggregate_and_probability_of_improvement(tmp_path):
    """Three seeds of silcr and ircr and one of sac-dense on two tasks, with final returns chosen so the
    answers are known: the IQM of three values is their mean, silcr beats ircr in every pair."""
    dirs = []
    finals = {"silcr": [10.0, 20.0, 30.0], "ircr": [2.0, 4.0, 6.0], "sac": [40.0]}
    for env in ("Hopper-v5", "Swimmer-v5"):
        for algo, values in finals.items():
            for seed, final in enumerate(values):
                dirs.append(_fake_run(tmp_path, env, algo, seed, [0, 1000], [0.0, final]))
    out = tmp_path / "fig.png"
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "-o", str(out), "--stats", "rliable",
                        "--compare", "silcr", "--table", str(tmp_path / "t.md"), "--bootstrap-reps", "200"],
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    table = (tmp_path / "t.md").read_text()
    assert "| Hopper-v5 | silcr | 3 | 20.00 [" in table and "| Swimmer-v5 | ircr | 3 | 4.00 [" in table
    # normalised: 0 = the untrained policy (first evaluations, all 0), 1 = sac-dense's final return (40)
    assert "1 = sac-dense's final return" in table
    assert "| silcr | 3 | 0.50 [" in table
    # one seed has no interval: a bootstrap over one run only ever draws that run
    assert "| sac-dense | 1 | 1.00 (one seed: no interval) |" in table
    assert "| Hopper-v5 | sac-dense | 1 | 40.00 (one seed: no interval) |" in table
    assert "| Hopper-v5 | sac-dense | 0.00 [0.00, 0.00] (sac-dense: one seed; the interval resamples silcr's runs only) |" in table
    assert "FutureWarning" not in r.stderr  # arch's deprecation notice, once per estimate, is kept off the screen
    assert "| Hopper-v5 | ircr | 1.00 [1.00, 1.00] |" in table  # every silcr run beats every ircr run
    assert "| all 2 tasks | ircr | 1.00 [1.00, 1.00] |" in table
    assert (tmp_path / "fig-stats.png").stat().st_size > 1000
    # performance profiles: normalised finals silcr 0.25, 0.5, 0.75 on each task, ircr 0.05-0.15, sac-dense 1
    assert (tmp_path / "fig-profiles.png").stat().st_size > 1000
    assert "| silcr | 6 | 0.33 | 0.00 |" in table and "| ircr | 6 | 0.00 | 0.00 |" in table
    assert "| sac-dense | 2 | 1.00 | 0.00 |" in table
    from silcr.stats import figure_labels  # the figure names a one-seed group (its bar has no width)

    seeds = {"A": {"sac-dense": 1, "silcr": 3, "sac": 3}, "B": {"sac-dense": 1, "silcr": 3, "sac": 3}}
    assert figure_labels(seeds, ["sac", "sac-dense", "silcr"]) == {"sac": "sac", "sac-dense": "sac-dense (one seed)",
                                                                    "silcr": "silcr"}
    smoothed = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "-o", str(out), "--stats",
                               "rliable", "--final-evals", "2", "--bootstrap-reps", "200"],
                              capture_output=True, text=True, cwd=REPO, timeout=300)
    assert smoothed.returncode == 0, smoothed.stdout + smoothed.stderr
    assert "| Hopper-v5 | silcr | 3 | 10.00 [" in smoothed.stdout  # the mean of 0 and 10, 20, 30: 5, 10, 15
    assert "Final return (mean of the last 2 evaluations): interquartile mean" in smoothed.stdout
    for option, message in ((["--compare", "nope"], "--compare 'nope': no such group"),
                            (["--bootstrap-reps", "10"], "--bootstrap-reps must be >= 100"),
                            (["--final-evals", "0"], "--final-evals must be >= 1")):
        fresh = tmp_path / "bad" / "fig.png"
        bad = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "-o", str(fresh), "--stats",
                              "rliable", *option], capture_output=True, text=True, cwd=REPO, timeout=120)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr
        assert not (tmp_path / "bad").exists() or not any((tmp_path / "bad").iterdir())  # refused before any file


def test_the_closing_line_gives_the_final_evaluation_with_digits_that_matter(tmp_path):
    from silcr.deploy.console import done_message, format_return

    (tmp_path / "progress.csv").write_text("env_steps,eval_return\n6067,0.9549999999999998\n7150,0.0\n")
    assert "final evaluation 0.000 at 7150 env steps" in done_message(tmp_path)  # the last row, not the best
    assert "best" not in done_message(tmp_path)  # no best.silcr (a learner from before it): nothing to point to
    (tmp_path / "best.silcr").write_bytes(b"")  # unreadable: no best claimed for it
    assert "best" not in done_message(tmp_path)
    import torch

    def best_file(evaluation):
        torch.save({"format": "silcr-model", "version": 1, "evaluation": evaluation}, tmp_path / "best.silcr")

    best_file({"return_mean": 0.9549999999999998, "env_steps": 6067})
    assert f"best 0.955 at 6067 env steps, its policy in {tmp_path / 'best.silcr'};" in done_message(tmp_path)
    # The file's own evaluation, not progress.csv's highest row: writing a later best can fail (a full disk).
    best_file({"return_mean": 0.5, "env_steps": 3000})
    assert "best 0.500 at 3000 env steps" in done_message(tmp_path)
    assert format_return(0.9549999) == "0.955" and format_return(1234.56) == "1234.6"
    assert done_message(tmp_path / "missing").startswith("silcr train: done. progress:")


def test_sweep_cells_are_labelled_by_their_variants_unless_one_name_covers_two_settings(tmp_path):
    from silcr.common.config import Config
    from silcr.common.run_records import distinguish, label_by_variant

    def cell(root, variant, seed, **settings):
        d = root / f"{variant}_MiniGrid-Empty-8x8-v0_s{seed}"
        d.mkdir(parents=True)
        Config(run=d.name, env="MiniGrid-Empty-8x8-v0", seed=seed, **settings).save(d / "config.toml")
        (d / "progress.csv").write_text("env_steps,eval_return\n0,0\n1000,1\n")
        return d

    study = [cell(tmp_path / "a", "silcr", s, absorbing_terminal=True) for s in (0, 1)] + [
        cell(tmp_path / "a", "silcr-recent", 0, absorbing_terminal=True, expert_admission="recent"),
        cell(tmp_path / "a", "sac", 0, algo="sac")]
    runs = [load_run(d) for d in study]
    assert label_by_variant(runs) and [r.algo for r in runs] == ["silcr", "silcr", "silcr-recent", "sac"]
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, study), "-o", str(tmp_path / "f.png")],
                       capture_output=True, text=True, cwd=REPO, timeout=120)
    assert r.returncode == 0 and "| silcr-recent | 1 |" in r.stdout, r.stdout + r.stderr
    # a cell of another experiment whose variant has the same name but other settings: back to the settings
    other = cell(tmp_path / "b", "silcr", 0, absorbing_terminal=False)
    runs = [load_run(d) for d in [*study[:2], other]]
    assert not label_by_variant(runs)
    assert {r.algo for r in distinguish(runs)} == {"silcr absorbing_terminal=True", "silcr absorbing_terminal=False"}
    # and a run that is not a sweep cell
    plain = tmp_path / "mine"
    plain.mkdir()
    Config(run="mine", env="MiniGrid-Empty-8x8-v0").save(plain / "config.toml")
    (plain / "progress.csv").write_text("env_steps,eval_return\n0,0\n")
    assert not label_by_variant([load_run(study[0]), load_run(plain)])


def test_plot_against_a_setting_gives_the_final_return_at_each_value_one_line_per_family(tmp_path):
    """An ablation over M: the IQM at each M (three seeds whose IQM is their mean), the budget / M
    column, and a run with another tau on a line of its own rather than pooled into the M = 5,000 point."""
    pytest.importorskip("rliable")
    dirs = []
    for m, finals in ((1000, [10.0, 20.0, 30.0]), (5000, [40.0, 50.0, 60.0]), (100000, [1.0, 2.0, 3.0])):
        for seed, final in enumerate(finals):
            d = tmp_path / f"silcr-M{m}_HalfCheetah-v5_s{seed}"
            d.mkdir()
            Config(run=d.name, env="HalfCheetah-v5", algo="silcr", seed=seed, expert_capacity=m,
                   total_steps=200_000).save(d / "config.toml")
            (d / "progress.csv").write_text(f"time,env_steps,updates,policy_version,eval_return\n0,0,0,0,0\n1,1000,1,0,{final}\n")
            dirs.append(d)
    other = tmp_path / "silcr-tau_HalfCheetah-v5_s0"
    other.mkdir()
    Config(run=other.name, env="HalfCheetah-v5", algo="silcr", seed=0, expert_capacity=5000, total_steps=200_000,
           tau=0.01).save(other / "config.toml")
    (other / "progress.csv").write_text("time,env_steps,updates,policy_version,eval_return\n0,0,0,0,0\n1,1000,1,0,999\n")
    longer = tmp_path / "silcr-2M_HalfCheetah-v5_s0"  # another budget: another experiment, its own line and ratio
    longer.mkdir()
    Config(run=longer.name, env="HalfCheetah-v5", algo="silcr", seed=0, expert_capacity=5000,
           total_steps=2_000_000).save(longer / "config.toml")
    (longer / "progress.csv").write_text("time,env_steps,updates,policy_version,eval_return\n0,0,0,0,0\n1,1000,1,0,777\n")
    out = tmp_path / "fig.png"
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), str(other), str(longer), "-o", str(out),
                        "--stats", "rliable", "--against", "expert_capacity", "--bootstrap-reps", "200"],
                       capture_output=True, text=True, cwd=REPO, timeout=300)
    assert r.returncode == 0, r.stdout + r.stderr
    assert "| HalfCheetah-v5 | silcr tau=0.005 total_steps=200000 | 1000 | 200 | 3 | 20.00 [" in r.stdout
    # not pooled with tau=0.01's 999 nor with the 2M-step run's 777
    assert "| HalfCheetah-v5 | silcr tau=0.005 total_steps=200000 | 5000 | 40 | 3 | 50.00 [" in r.stdout
    assert "| HalfCheetah-v5 | silcr tau=0.005 total_steps=200000 | 100000 | 2 | 3 | 2.00 [" in r.stdout
    assert "| HalfCheetah-v5 | silcr tau=0.01 total_steps=200000 | 5000 | 40 | 1 | 999.00 (one seed: no interval) |" in r.stdout
    assert "| HalfCheetah-v5 | silcr tau=0.005 total_steps=2000000 | 5000 | 400 | 1 | 777.00 (one seed" in r.stdout
    assert (tmp_path / "fig-against-expert_capacity.png").stat().st_size > 1000
    for option, message in ((["--stats", "rliable", "--against", "reward"], "--against reward: "),
                            (["--stats", "rliable", "--against", "no_such"], "--against no_such: no such setting"),
                            (["--against", "expert_capacity"], "--against go with --stats rliable")):
        fresh = tmp_path / "bad" / "fig.png"
        bad = subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "-o", str(fresh), *option],
                             capture_output=True, text=True, cwd=REPO, timeout=120)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr, bad.stderr
        assert not (tmp_path / "bad").exists()  # refused before any file


def test_an_interval_does_not_depend_on_the_other_runs_plotted_with_it(tmp_path):
    """rliable's bootstrap draws from NumPy's global generator whatever random_state it is given, so
    one task's interval once changed with the tasks sorted before it; each estimate now has its own draws."""
    pytest.importorskip("rliable")
    from silcr.stats import rliable_report

    hopper = [load_run(_fake_run(tmp_path, "Hopper-v5", "silcr", s, [0, 1000], [0.0, v]))
              for s, v in enumerate([1183.0, 2108.0, 3160.0])]
    before = [load_run(_fake_run(tmp_path, "Ant-v5", "silcr", s, [0, 1000], [0.0, v])) for s, v in enumerate([5.0, 9.0, 1.0])]

    def hopper_line(runs):
        return next(line for line in rliable_report(runs, reps=200).splitlines() if line.startswith("| Hopper-v5 | silcr"))

    alone = hopper_line(hopper)
    assert hopper_line(before + hopper) == alone
    np.random.seed(123)  # nor on the caller's use of the global generator
    assert hopper_line(hopper) == alone


def test_plot_pools_one_configurations_cells_from_two_studies_and_refuses_when_settings_differ(tmp_path):
    """Ten seeds from two studies (issue 37): cells of one variant and task in two runs directories are
    seeds of one group when every setting matches (where and how they ran aside), and refused with one
    line naming the settings otherwise, or when a seed appears twice."""
    def cell(study, variant, seed, final, **settings):
        d = tmp_path / study / f"{variant}_Hopper-v5_s{seed}"
        d.mkdir(parents=True)
        Config(run=d.name, runs_dir=f"runs/{study}", env="Hopper-v5", seed=seed, torch_threads=1 + seed % 2,
               zenoh_listen=f"tcp/127.0.0.1:{17500 + seed}", **settings).save(d / "config.toml")
        (d / "progress.csv").write_text(f"env_steps,eval_return\n0,0\n1000,{final}\n")
        return d

    def plot_cli(*dirs):
        return subprocess.run([sys.executable, "-m", "silcr.cli", "plot", *map(str, dirs), "-o", str(tmp_path / "f.png")],
                              capture_output=True, text=True, cwd=REPO, timeout=120)

    first = [cell("five", "silcr", s, 10.0 * s) for s in range(3)]
    later = [cell("ten", "silcr", s, 10.0 * s) for s in range(3, 6)]
    r = plot_cli(*first, *later)
    assert r.returncode == 0, r.stderr
    assert "| Hopper-v5 | silcr | 6 | 1,000 | 25.0 ± 17.1 |" in r.stdout  # one group of six seeds: 0, 10, ... 50
    # one setting differs in the later study: refused, naming it, before any figure is written
    (tmp_path / "f.png").unlink()
    other = [cell("tau", "silcr", s, 1.0, tau=0.001) for s in (6, 7)]
    r = plot_cli(*first, *other)
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    assert "tau: 0.001 vs 0.005" in r.stderr and "not pooled" in r.stderr
    assert not (tmp_path / "f.png").exists()
    # the same seed in both studies is not two seeds
    again = cell("again", "silcr", 0, 5.0)
    r = plot_cli(*first, again)
    assert r.returncode == 2 and "seed 0 appears in more than one" in r.stderr


def test_a_record_without_a_newer_option_reads_as_what_it_ran(tmp_path, monkeypatch):
    """A config.toml written before --critic-norm existed ran plain critics, whatever today's default is."""
    import copy

    from silcr.common import config as C

    d = _fake_run(tmp_path, "Hopper-v5", "silcr", 0, [0, 1000], [1, 2])
    text = (d / "config.toml").read_text()
    (d / "config.toml").write_text("\n".join(line for line in text.splitlines() if not line.startswith("critic_norm")))
    # as if the default had since become LayerNorm critics
    changed = copy.copy(C.FIELDS["critic_norm"])
    changed.default = "layer"
    monkeypatch.setitem(C.FIELDS, "critic_norm", changed)
    assert C.default_of("critic_norm") == "layer"
    assert load_run(d).config["critic_norm"] == "none"


def _reward_terms_script():
    import importlib.util

    spec = importlib.util.spec_from_file_location("reward_terms", REPO / "experiments" / "humanoid-reward-terms.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_humanoid_reward_terms_add_up_to_the_return_and_bad_files_exit_2(tmp_path):
    import gymnasium as gym

    from silcr import SAC
    from silcr.actor.policy import policy_for
    from silcr.common.envs import EnvSpec
    from silcr.policy_commands import policy_weights

    SAC("Humanoid-v5", runs_dir=tmp_path / "runs", reward="dense", hidden=(8, 8)).save(tmp_path / "h.silcr")
    weights, env_id = policy_weights(tmp_path / "h.silcr")
    spec = EnvSpec.of(env_id)
    script = _reward_terms_script()
    ep = script.episode(gym.make(env_id), policy_for(weights, spec), spec, seed=3)
    # The split is only worth reading if no term is missing or counted twice.
    assert ep["return"] == pytest.approx(sum(ep[t] for t in script.TERMS), rel=1e-9)
    # Humanoid-v5 pays 5 a healthy step; the step on which it falls is not healthy.
    assert ep["reward_survive"] == pytest.approx(5.0 * (ep["length"] - (not ep["full_length"])))
    assert 1 <= ep["length"] <= 1000 and np.isfinite(ep["distance"])

    run = [sys.executable, str(REPO / "experiments" / "humanoid-reward-terms.py")]
    ok = subprocess.run(run + [str(tmp_path / "h.silcr"), "--episodes", "2"], capture_output=True, text=True, timeout=120)
    assert ok.returncode == 0, ok.stderr
    assert ok.stdout.splitlines()[-1].startswith(f"| {tmp_path / 'h.silcr'} |")
    SAC("Pendulum-v1", runs_dir=tmp_path / "runs", reward="dense", hidden=(8, 8)).save(tmp_path / "p.silcr")
    (tmp_path / "bad.pt").write_bytes(b"not a checkpoint")
    for bad, why in (("bad.pt", "unreadable or corrupt"), ("p.silcr", "a Pendulum-v1 policy")):
        r = subprocess.run(run + [str(tmp_path / "h.silcr"), str(tmp_path / bad)], capture_output=True, text=True,
                           timeout=120)
        assert r.returncode == 2 and why in r.stderr and "Traceback" not in r.stderr
        assert r.stdout == ""  # refused before any episode or table line


def test_humanoid_reward_terms_from_records_per_stretch_with_resumed_rows_superseded(tmp_path):
    d = tmp_path / "silcr_Humanoid-v5_s0"
    d.mkdir()
    Config(run=d.name, env="Humanoid-v5", algo="silcr", seed=0, total_steps=600_000).save(d / "config.toml")
    rows = ["time,env_steps,updates,policy_version,eval_return,eval_length",
            "0,100000,1,0,600,100", "0,150000,1,0,1800,300",  # stretch 1: (100 + 300) above the bonus over 400 steps
            "0,250000,1,0,99999,1000",  # lost with the run's last checkpoint: the resume writes 250k again
            "0,200000,1,0,900,100", "0,250000,1,0,5000,1000"]  # stretch 1 gains 400 over 100; stretch 2: 0
    (d / "progress.csv").write_text("\n".join(rows) + "\n")
    out = _reward_terms_script().record_stretches(d, 200_000)
    assert out[:2] == [(pytest.approx(500 / 3), pytest.approx(800 / 500)), (1000.0, 0.0)]
    assert len(out) == 3 and np.isnan(out[2]).all()  # 400k-600k: no evaluation yet
    r = subprocess.run([sys.executable, str(REPO / "experiments" / "humanoid-reward-terms.py"), "--records", str(d)],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.splitlines()[-1] == "| silcr_Humanoid-v5_s0 | 167, 1.60 | 1000, 0.00 | - |"
