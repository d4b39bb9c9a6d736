"""Running a checked configuration: the one launcher below `silcr train` and the Python API.

`train(cfg)` runs `cfg` to its end and returns the exit code `silcr train` ends with: in this
process with `--single-process`, else as a router, a buffer service, a learner and the actors
in processes of their own (`local.run_train`). Before anything starts it takes the run
directory (one run per directory: `run_lock`) and, for a distributed run, checks that the
router's port is free, and without `--resume` that the directory holds no run already
(`run_end.check_new`), with it that the options name the run it holds (`run_end.check_same_run`: env,
algorithm, reward, networks); each refusal raises before a file is written. With `--resume` on a run whose
budget is spent it writes nothing at all: one line, and exit code 0 (`common/run_end.py`).

`run_directory(cfg)` is what every way of training holds for a run's life (this `train`, and the
Python API's in-process model from its first `learn` to `close`): the lock, the logs folder, the
configuration saved. The options were checked before (`config`, `preflight`: the device too); how
Ctrl-C and SIGTERM stop a run is `common/lifecycle.py`'s (one clean stop; a second Ctrl-C forces).

How a run ended is reported here, once for both launchers (`console.report_end`): the closing
line, or the final checkpoints that could not be written named (`console.StaleCheckpoints`, exit
code 4); the Python API raises the same `StaleCheckpoints`.
"""

from __future__ import annotations

import contextlib
from typing import Any, Callable, Iterator

from silcr.common import run_layout
from silcr.common.config import Config, ConfigError
from silcr.common.run_end import check_new, check_same_run
from silcr.common.run_lock import check_free, hold
from silcr.deploy.console import RunEnd, report_end


def train(cfg: Config, on_row: Callable[[dict[str, Any]], bool] | None = None, who: str = "silcr train") -> int:
    """Run `cfg` (already checked: `config.resolve`/`from_options` and `preflight.check`); the exit code `silcr
    train` ends with. Raise RunInUse when another process holds its run directory, ConfigError when the router's
    port is taken. A distributed run gives `on_row` each new progress.csv row, typed, in this thread: False stops
    the run cleanly (exit code 130), an exception stops it cleanly and is raised. `who` starts the lines it prints."""
    return run_to_end(cfg, on_row, who).code


def run_to_end(cfg: Config, on_row: Callable[[dict[str, Any]], bool] | None = None, who: str = "silcr train") -> RunEnd:
    """`train`, with the components whose final checkpoint could not be written (the Python API raises
    `console.StaleCheckpoints` for them); the end already reported (`console.report_end`)."""
    check_free(cfg.run_dir)  # first: a live run of the same name is the likelier reason for a busy port
    if cfg.single_process:
        from silcr.common.process_env import spin_in_single_process

        spin_in_single_process()  # before torch loads (the finished-run check loads it): it owns the cores
    from silcr.learner.checkpoint import finished_run

    if cfg.resume and (done := finished_run(cfg)) is not None:  # the finished-run rule (common/run_end.py)
        print(f"{who}: {done.message()}", flush=True)
        return RunEnd(0, [])
    if not cfg.single_process:
        from silcr.deploy.local import port_in_use

        if port_in_use(cfg.zenoh_listen):
            raise ConfigError("--zenoh-listen", f"{cfg.zenoh_listen} is already in use (another run?); pick another port")
    with run_directory(cfg):
        if cfg.single_process:
            from silcr.deploy.single_process import run_single_process

            end = run_single_process(cfg)
        else:
            from silcr.deploy.local import run_train

            end = run_train(cfg, on_row, who)
    return RunEnd(report_end(cfg.run_dir, end, who), end.stale)


@contextlib.contextmanager
def run_directory(cfg: Config) -> Iterator[None]:
    """The run directory held for the run's life (RunInUse if another process holds it), with its logs folder
    and `cfg` saved as config.toml (saved again by a caller that raises the budget)."""
    check_free(cfg.run_dir)  # a live run is said first: it is the likelier reason
    check_new(cfg)  # without --resume, a run is never started over another (common/run_end.py)
    check_same_run(cfg)  # with it, the run the directory holds, not another under its name
    with hold(cfg.run_dir):  # one run directory, one run
        run_layout.logs(cfg.run_dir).mkdir(parents=True, exist_ok=True)
        cfg.save(run_layout.config(cfg.run_dir))
        yield
