"""The finished-run rule: a run whose budget is spent stays finished.

When the learner has spent a run's budget and written its last checkpoint, it writes
`<run dir>/finished.json` (the env steps and updates it finished at, and the budget).
From then on, starting the run again with `--resume` (a launcher, a component, a sweep, a
container that an orchestrator restarts) makes no update, writes no progress row and
rewrites no checkpoint: it says so in one line and exits 0. Raising the budget
(`--total-steps`, or the Python API's `learn(n)`) goes on as before, and the learner drops the
file as it goes on.

Runs finished before the file existed are recognised from the learner checkpoint's
counters (`silcr.learner.checkpoint.finished_run`): every env step of the budget collected
and every update it is due made.

Without `--resume`, a directory that holds a run (a learner checkpoint, or finished.json) is
refused before a file is written (`check_new`): starting the same command twice, or reusing a
`--run` name, would otherwise train from scratch over a run's checkpoints, progress.csv and
best.silcr. A directory with neither (a run stopped before its first learner checkpoint) holds
nothing `--resume` could go on from, and a new run starts there, as `silcr sweep` expects.

Why exit 0 rather than idle: a component that exits 0 is one that every orchestrator leaves
stopped (compose's `restart: on-failure`, a Kubernetes Job, Slurm), so nothing retrains the
run, and an exit code is what they read (docs/deployment.md, "When a run ends").
"""

from __future__ import annotations

import json
import logging
import tomllib
from dataclasses import asdict, dataclass
from pathlib import Path

from silcr.common import run_layout
from silcr.common.atomic_file import write_atomic
from silcr.common.config import Config, ConfigError, option_name, saved_options

log = logging.getLogger("run_end")


@dataclass(frozen=True)
class Finished:
    """Where a run's budget was spent."""

    run: str
    env_steps: int
    updates: int
    total_steps: int

    def message(self) -> str:
        return (f"run {self.run} already finished at {self.env_steps} env steps; raise --total-steps to go on "
                f"(it is {self.total_steps})")


def mark(run_dir: Path, finished: Finished) -> None:
    """Record that the run finished (atomically: a reader sees the whole file or none). A failed write (a full
    disk) is logged: a later --resume finds the budget spent from the learner checkpoint's counters instead."""
    try:
        write_atomic(run_layout.finished(run_dir), lambda f: f.write(json.dumps(asdict(finished)).encode()))
    except OSError as e:
        log.error("could not record that run %s finished in %s (%s)", finished.run, run_layout.finished(run_dir), e)


def unmark(run_dir: Path) -> None:
    """The run goes on past its old budget: it is no longer finished."""
    run_layout.finished(run_dir).unlink(missing_ok=True)


def read(run_dir: Path) -> Finished | None:
    """The run's finished.json, or None when there is none or it cannot be read as one."""
    try:
        data = json.loads(run_layout.finished(run_dir).read_text())
        return Finished(str(data["run"]), int(data["env_steps"]), int(data["updates"]), int(data["total_steps"]))
    except (OSError, ValueError, KeyError, TypeError):
        return None


class RunHeld(ConfigError):
    """A new run refused (on --run) because its directory holds one; `held` says what, in words. The message is the
    command line's; the Python API words its own, as `resume` is not one of its options."""

    def __init__(self, run_dir: Path, held: str) -> None:
        super().__init__("--run", f"{run_dir} already holds {held}; add --resume to go on with it, or pick another "
                                  f"--run name (or delete the directory to start that run again)")
        self.run_dir, self.held = run_dir, held


def check_new(cfg: Config) -> None:
    """Raise RunHeld when `cfg` starts a new run, without --resume, in a directory that holds one."""
    if cfg.resume:
        return
    run_dir, done = Path(cfg.run_dir), read(Path(cfg.run_dir))
    if done is not None:
        held = f"a run that finished at {done.env_steps} env steps"
    elif run_layout.learner_checkpoint(run_dir).exists():
        held = f"a run stopped midway (its checkpoints in {run_layout.checkpoints(run_dir)})"
    else:
        return
    raise RunHeld(run_dir, held)


#: What a run is of: its checkpoints hold these networks and episodes, and `silcr plot` labels its records by them.
#: A --resume that names other values (the command without the run's options, whose defaults are another run's) would
#: rewrite the run's config.toml before a checkpoint refused to load, or go on as another experiment under its name.
RUN_IDENTITY = ("env", "algo", "reward", "hidden", "critic_norm")


def check_same_run(cfg: Config) -> None:
    """Raise ConfigError (on the first option that differs) when a --resume names another run than the one its
    directory's config.toml says it holds; before anything is written. `silcr train` takes what is not given again
    from that file (`config.resumed_run_options`), so only an option given again can differ there; the Python API
    and a component started by hand give all of theirs."""
    if not cfg.resume:
        return
    path = run_layout.config(Path(cfg.run_dir))
    try:
        saved = saved_options(path)
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError):
        return  # none yet (a run stopped before its launcher wrote it), or unreadable: the resume writes the options given
    given = cfg.to_dict()  # checked options: a list option is a list here, as in the file
    for key in RUN_IDENTITY:
        if saved[key] != given[key]:
            raise ConfigError(option_name(key), f"{cfg.run_dir} holds a run with {key} = {saved[key]!r}, not "
                                                f"{given[key]!r}; --resume goes on with the run's own options "
                                                f"({path}): leave {option_name(key)} out, or pick another --run name")


def target_updates(cfg: Config) -> int:
    """The updates a budget of `cfg.total_steps` env steps is due: `--samples-per-insert` per step after
    `--learning-starts`."""
    return int(max(0, cfg.total_steps - cfg.learning_starts) * cfg.samples_per_insert)


def finished(cfg: Config) -> Finished | None:
    """How `cfg`'s run finished, if its finished.json says a budget of `cfg.total_steps` is spent; else None.
    (`silcr.learner.checkpoint.finished_run` also reads runs finished before the file existed.)"""
    marked = read(cfg.run_dir)
    return marked if marked is not None and marked.total_steps >= cfg.total_steps else None


#: How long a component that finds its run finished keeps announcing the end, so that the run's other processes
#: started beside it (a router that follows the run, actors and a buffer that cannot see this run directory)
#: hear it and exit too.
ANNOUNCE_S = 20.0


def announce(cfg: Config, seconds: float = ANNOUNCE_S) -> None:
    """Announce the run's end on its shutdown key every second for `seconds`, best effort (no router: nothing)."""
    import threading
    import time

    from silcr.common import protocol as P
    from silcr.common.control_channel import Shutdown
    from silcr.common.zenoh_session import open_session, session_config

    def repeat() -> None:
        try:
            with open_session(session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)) as session:
                shutdown, end = Shutdown(session, P.Keys(cfg.run)), time.monotonic() + seconds
                while time.monotonic() < end:
                    shutdown.announce(P.ShutdownNotice.FINISHED)
                    time.sleep(1.0)
        except Exception:  # no router, a bad endpoint: the others find out as they can (their own checks)
            pass

    worker = threading.Thread(target=repeat, daemon=True)
    worker.start()
    worker.join(seconds + 10.0)
