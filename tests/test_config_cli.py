"""Options, TOML config files and the command line's handling of bad input."""

from __future__ import annotations

import subprocess
from pathlib import Path
import sys
import tomllib

import pytest

from silcr.cli import build_parser, command
from silcr.common.config import Config, ConfigError, resolve
from tests.helpers import REPO


def _resolve(argv: list[str], role: str = "train") -> Config:
    parser, _ = build_parser()
    return resolve(parser.parse_args([role, *argv]), role)


def test_defaults_are_table_one_except_tau():
    cfg = _resolve([])
    assert cfg.hidden == [800, 400] and cfg.lr == 3e-4 and cfg.gamma == 0.99
    assert cfg.tau == 0.005  # Table I's 0.05 diverged (docs/algorithm.md); configs/paper.toml keeps it
    assert _resolve(["--config", str(REPO / "configs" / "paper.toml")]).tau == 0.05
    assert cfg.batch_size == 128 and cfg.online_capacity == 1_000_000 and cfg.expert_capacity == 50_000
    assert cfg.learning_starts == 10_240 and cfg.samples_per_insert == 1.0
    assert cfg.run.startswith("Hopper-v5-silcr-")


def test_d_e_refills_only_with_better_episodes_by_default_and_older_records_read_as_any():
    from silcr.common.config import value_when_absent
    from silcr.common.run_records import load_run

    assert _resolve([]).expert_refill == "better" and _resolve(["--expert-refill", "any"]).expert_refill == "any"
    assert value_when_absent("expert_refill") == "any"  # what every run recorded before the option did
    old = REPO / "results" / "five-tasks" / "runs" / "silcr_Hopper-v5_s0"  # recorded before the option
    assert "expert_refill" not in tomllib.loads((old / "config.toml").read_text())
    assert load_run(old).config["expert_refill"] == "any"


def test_toml_then_command_line_precedence(tmp_path):
    f = tmp_path / "c.toml"
    f.write_text('env = "Walker2d-v5"\nactors = 3\nexpert-capacity = 20000\nhidden = [64, 64]\n')
    cfg = _resolve(["--config", str(f), "--actors", "5"])
    assert (cfg.env, cfg.actors, cfg.expert_capacity, cfg.hidden) == ("Walker2d-v5", 5, 20_000, [64, 64])


def test_saved_config_round_trips(tmp_path):
    cfg = _resolve(["--run", "r1", "--hidden", "32", "16", "--no-throttle"])
    cfg.save(tmp_path / "config.toml")
    data = tomllib.loads((tmp_path / "config.toml").read_text())
    assert Config(**data) == cfg


def test_resume_takes_what_is_not_given_again_from_the_runs_config(tmp_path):
    runs = tmp_path / "runs"
    (runs / "r1").mkdir(parents=True)
    _resolve(["--run", "r1", "--env", "Walker2d-v5", "--hidden", "32", "16", "--total-steps", "300000",
              "--seed", "4"]).save(runs / "r1" / "config.toml")
    # The run's own options, the budget among them; what is given again wins (a file's, the command line's).
    f = tmp_path / "more.toml"
    f.write_text("total-steps = 400000\n")
    cfg = _resolve(["--run", "r1", "--runs-dir", str(runs), "--resume", "--config", str(f), "--seed", "5"])
    assert (cfg.env, cfg.hidden, cfg.total_steps, cfg.seed, cfg.resume) == ("Walker2d-v5", [32, 16], 400_000, 5, True)
    # Without --resume, or for a component (it is given its options whole), the defaults as before.
    assert _resolve(["--run", "r1", "--runs-dir", str(runs)]).env == "Hopper-v5"
    assert _resolve(["--run", "r1", "--runs-dir", str(runs), "--resume"], role="learner").hidden == [800, 400]
    assert _resolve(["--run", "new", "--runs-dir", str(runs), "--resume"]).total_steps == 2_000_000  # nothing saved
    (runs / "r1" / "config.toml").write_text("env = = 'x'\n")
    with pytest.raises(ConfigError, match=r"--resume: .*r1/config.toml cannot be read"):
        _resolve(["--run", "r1", "--runs-dir", str(runs), "--resume"])


@pytest.mark.parametrize(
    "text, needle",
    [
        ("actorz = 3\n", "unknown option"),
        ("actors = 'three'\n", "expected int"),
        ("algo = 'ppo'\n", "invalid choice"),
        ("actors = = 3\n", "not valid TOML"),
    ],
)
def test_bad_toml_is_a_config_error(tmp_path, text, needle):
    f = tmp_path / "bad.toml"
    f.write_text(text)
    with pytest.raises(ConfigError, match=needle):
        _resolve(["--config", str(f)])


def _cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "silcr.cli", *args], capture_output=True, text=True, timeout=120,
                          cwd=cwd)


@pytest.mark.parametrize(
    "args, needle",
    [
        (["train", "--actors", "0"], "--actors"),
        (["train", "--device", "gpu"], "--device"),
        (["train", "--algo", "ppo"], "--algo"),
        (["train", "--env", "NoSuchEnv-v0"], "--env"),
        (["train", "--gamma", "1.5"], "--gamma"),
        (["train", "--run", "a/b"], "--run"),
        (["train", "--bogus"], "--bogus"),
        (["train", "--config", "/nonexistent.toml"], "--config"),
        (["buffer"], "--run"),
        (["actor", "--run", "x", "--connect", "nonsense"], "--connect"),
        (["learner", "--run", "x", "--batch-size", "1"], "--batch-size"),
        # D_E keeps whole episodes: an M below the task's longest episode would leave it empty (Swimmer: 1,000 steps)
        (["train", "--env", "Swimmer-v5", "--expert-capacity", "999"], "--expert-capacity"),
        (["buffer", "--run", "x", "--env", "HalfCheetah-v5", "--expert-capacity", "500"], "--expert-capacity"),
        # the registered episodic ids always pay the episodic reward: dense is asked for on the plain task
        (["train", "--env", "silcr/Hopper-v5", "--algo", "sac", "--reward", "dense"], "--reward"),
        (["train", "--algo", "sac", "--expert-admission", "recent"], "--expert-admission"),
        (["train", "--tanh-log-prob", "approx"], "--tanh-log-prob"),
        (["train", "--algo", "sac", "--expert-init", "x.npz"], "--expert-init: only --algo silcr"),
        (["train", "--expert-init", "nowhere.npz"], "--expert-init: no such file"),
        (["train", "--algo", "gasil", "--gasil-alpha", "-1"], "--gasil-alpha"),
        (["train", "--algo", "gasil", "--gasil-reward", "sigmoid"], "--gasil-reward"),
        (["train", "--algo", "gasil", "--disc-hidden", "0"], "--disc-hidden"),
        (["train", "--algo", "gasil", "--disc-batch-size", "0"], "--disc-batch-size"),
        (["train", "--algo", "gasil", "--recent-window", "0"], "--recent-window"),
        (["train", "--algo", "gasil", "--env", "silcr/Hopper-v5", "--reward", "dense"], "--reward"),
        # checked before anything starts (issue 18): these printed a traceback, forked, or died of MemoryError
        (["train", "--zenoh-listen", "garbage"], "--zenoh-listen: 'garbage' is not a Zenoh endpoint"),
        (["train", "--zenoh-listen", "tcp/127.0.0.1:99999"], "--zenoh-listen"),
        (["train", "--zenoh-listen", "tcp/:7447"], "--zenoh-listen"),
        (["router", "--listen", "garbage"], "--listen"),
        (["train", "--actors", "100000"], "--actors: 100000 is more than 1024"),
        (["train", "--online-capacity", "99999999999999999"], "--online-capacity"),
        (["buffer", "--run", "x", "--algo", "silcr", "--expert-capacity", "99999999999999999"], "--expert-capacity"),
    ],
)
def test_bad_options_exit_2_with_one_line_and_no_traceback(args, needle, tmp_path):
    r = _cli(*args, cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr
    err_lines = [l for l in r.stderr.splitlines() if "error" in l]
    assert len(err_lines) == 1 and needle in err_lines[0], r.stderr
    # no run directory, no config.toml, and no MUJOCO_LOG.TXT (MuJoCo's warnings go to the log): nothing written
    assert list(tmp_path.iterdir()) == []


def test_a_capacity_the_machine_cannot_hold_is_one_line_through_a_config_file(tmp_path):
    (tmp_path / "big.toml").write_text("online_capacity = 99999999999999999\n")
    r = _cli("train", "--run", "big", "--config", "big.toml", cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr and "would reserve" in r.stderr, r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["big.toml"]


@pytest.mark.parametrize("source", ["file", "environment"])
def test_a_bad_value_is_refused_even_where_the_command_line_overrides_it(tmp_path, source):
    """Issue 42, item 4: `total_steps = -100` in a --config file was accepted when --total-steps was also given."""
    env = None
    args = ["train", "--run", "over", "--total-steps", "1000"]
    if source == "file":
        (tmp_path / "run.toml").write_text("total_steps = -100\n")
        args += ["--config", "run.toml"]
        needle = "run.toml: total_steps: must be >= 1, got -100"
    else:
        import os

        env = os.environ | {"SILCR_TAU": "7"}
        args += ["--tau", "0.005"]
        needle = "SILCR_TAU: must be in (0, 1], got 7.0"
    r = subprocess.run(command(*args), capture_output=True, text=True, cwd=tmp_path, timeout=120, env=env)
    assert r.returncode == 2 and "Traceback" not in r.stderr and needle in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "runs").exists()
    # and without the override each is refused the same way, as before
    with pytest.raises(ConfigError, match="must be >= 1"):
        (tmp_path / "alone.toml").write_text("total_steps = -100\n")
        _resolve(["--config", str(tmp_path / "alone.toml")])


def test_every_subcommand_has_help():
    for cmd in ("train", "buffer", "learner", "actor", "router", "monitor"):
        r = _cli(cmd, "--help")
        assert r.returncode == 0 and "usage: silcr " + cmd in r.stdout


@pytest.mark.parametrize("name", ["paper.toml", "smoke.toml"])
def test_shipped_configs_load(name):
    cfg = _resolve(["--config", str(REPO / "configs" / name)])
    assert cfg.algo == "silcr"


@pytest.mark.parametrize("module", ["silcr.learner.sac", "silcr.actor.policy", "silcr.buffer_service.batches",
                                    "silcr.bench.reference_sac"])
def test_thread_pool_defaults_apply_to_library_use(module):
    """Importing any component as a library sets the defaults before numpy or torch loads."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "OPENBLAS_NUM_THREADS")}
    code = f"import {module}, os; print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('OPENBLAS_NUM_THREADS'))"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout.split()
    assert out == ["PASSIVE", "1"]


@pytest.mark.parametrize("preset, torch_first, expect", [
    ({}, False, ["None", "20000", "spin 20000 rounds, then sleep"]),  # silcr's PASSIVE swapped for a short spin
    ({"OMP_WAIT_POLICY": "PASSIVE"}, False, ["PASSIVE", "None", "sleep at once"]),  # a user's or a sweep's wins
    ({"GOMP_SPINCOUNT": "5"}, False, ["None", "5", "spin 5 rounds, then sleep"]),
    ({}, True, ["PASSIVE", "None", "sleep at once"]),  # torch loaded first: its pool has read the policy already
])
def test_single_process_threads_spin_briefly_unless_the_environment_says_otherwise(preset, torch_first, expect):
    """`silcr train --single-process` owns its cores: 2 spinning threads took 9.7 ms per 800-400 update, sleeping ones 15.5."""
    import os
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")} | preset
    code = ("import os, sys\n"
            + ("import silcr, torch\n" if torch_first else "import silcr\n")
            + "how = silcr.spin_in_single_process()\n"
            "print(os.environ.get('OMP_WAIT_POLICY'), os.environ.get('GOMP_SPINCOUNT'), how, sep='|')")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True).stdout
    assert out.strip().split("|") == expect


@pytest.mark.parametrize("policy, said", [(None, "idle threads spin 20000 rounds, then sleep"),
                                          ("PASSIVE", "idle threads sleep at once")])
def test_silcr_train_single_process_applies_the_spin_and_logs_it(tmp_path, policy, said):
    """The command itself, not only the function: from a user's shell it spins; under a sweep's PASSIVE it does not."""
    import os

    from silcr.learner.threads import usable_cores

    if usable_cores() < 2:
        pytest.skip("one core: no threads to time, so no log line of them")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    env |= {"OMP_WAIT_POLICY": policy} if policy else {}
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "train", "--single-process", "--run", "s", "--runs-dir",
                        str(tmp_path), "--env", "InvertedPendulum-v5", "--hidden", "16", "16", "--learning-starts",
                        "200", "--total-steps", "300", "--eval-episodes", "0"],
                       capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert r.returncode == 0, r.stdout + r.stderr
    log = (tmp_path / "s" / "logs" / "single-process.log").read_text()
    assert said in log, log


def test_output_cut_short_by_a_pipe_ends_quietly():
    """`silcr sweep ... --dry-run | head -1`: a closed pipe printed a BrokenPipeError traceback."""
    r = subprocess.run(f"{sys.executable} -m silcr.cli sweep experiments/paper.toml --seeds 0-999 --dry-run | head -1",
                       shell=True, capture_output=True, text=True, timeout=120, cwd=REPO)
    assert r.stdout.startswith("silcr sweep paper: 30000 cells") and r.stderr == "", r.stderr


def test_many_actors_join_as_clients_of_the_router():
    """`silcr train` makes its actors Zenoh clients above PEER_ACTORS_MAX: 128 peers meshed by gossip
    stalled a 2-core machine (docs/scaling.md)."""
    from silcr.common.config import PEER_ACTORS_MAX, actor_zenoh_mode

    assert actor_zenoh_mode(_resolve(["--actors", str(PEER_ACTORS_MAX)])) == "peer"
    assert actor_zenoh_mode(_resolve(["--actors", str(PEER_ACTORS_MAX + 1)])) == "client"
    assert actor_zenoh_mode(_resolve(["--actors", "128", "--actor-zenoh-mode", "peer"])) == "peer"
    assert actor_zenoh_mode(_resolve(["--actors", "2", "--actor-zenoh-mode", "client"])) == "client"
    assert actor_zenoh_mode(_resolve(["--actors", "2", "--zenoh-mode", "client"])) == "client"


def test_silcr_version_is_the_package_version():
    """`silcr --version` says the release pyproject.toml builds (the two once said 0.3.0 and 0.4.0)."""
    import silcr

    built = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]["version"]
    assert silcr.__version__ == built
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "--version"], capture_output=True, text=True, cwd=REPO,
                       timeout=60)
    assert r.returncode == 0 and r.stdout.strip() == f"silcr {built}"


def test_a_misspelt_option_is_named_by_its_subcommand_with_the_option_meant():
    r = _cli("train", "--hiden", "64")
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip() == "silcr train: error: unrecognized arguments: --hiden 64 (did you mean --hidden?)"


def test_help_groups_every_option():
    from silcr.common.config import FIELDS
    from silcr.common.option_parser import OPTION_GROUPS

    grouped = [name for names in OPTION_GROUPS.values() for name in names]
    assert sorted(grouped) == sorted(FIELDS)  # every option in exactly one group
    r = _cli("train", "--help")
    headings = [line for line in r.stdout.splitlines() if line.endswith(" options:")]
    assert headings == [f"{group} options:" for group in OPTION_GROUPS]
