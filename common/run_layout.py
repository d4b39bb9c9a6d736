"""Where each file of a run lives inside its run directory (`<runs dir>/<run>/`).

The launchers, the learner, the buffer service, `silcr sweep`, `silcr plot` and the
Python API all read or write these files; naming them here keeps the layout that the
README's run-directory table documents in one place, so that a writer and its readers
cannot drift apart.
"""

from __future__ import annotations

from pathlib import Path

CONFIG = "config.toml"            # the run's full config, written at launch; --resume and silcr plot read it
PROGRESS = "progress.csv"         # one row per evaluation
TENSORBOARD = "tb"
LOGS = "logs"                     # one <component>.log per process
SINGLE_PROCESS_LOG = "single-process.log"  # every component's log when they share one process
CHECKPOINTS = "checkpoints"
LEARNER_CHECKPOINT = "learner.pt"
BUFFER_CHECKPOINT = "buffer.ckpt"
BEST_MODEL = "best.silcr"         # the best evaluation's policy, as a model file
PIDS = "pids.json"                # which process is which component (multi-process launcher)
LOCK = ".lock"                    # held for the run's life (common/run_lock.py)
SWEEP_LOG = "sweep.log"           # a sweep cell's console output
SWEEP_DONE = "sweep-done.json"    # a sweep cell that finished: its exit status and minutes
FINISHED = "finished.json"        # the run's budget is spent: where it finished (common/run_end.py)


def config(run_dir: Path) -> Path:
    return Path(run_dir) / CONFIG


def progress(run_dir: Path) -> Path:
    return Path(run_dir) / PROGRESS


def tensorboard(run_dir: Path) -> Path:
    return Path(run_dir) / TENSORBOARD


def logs(run_dir: Path) -> Path:
    return Path(run_dir) / LOGS


def component_log(run_dir: Path, name: str) -> Path:
    """The log of one component's process (`router`, `buffer`, `learner`, `actor-0`, ...)."""
    return logs(run_dir) / f"{name}.log"


def single_process_log(run_dir: Path) -> Path:
    return logs(run_dir) / SINGLE_PROCESS_LOG


def checkpoints(run_dir: Path) -> Path:
    return Path(run_dir) / CHECKPOINTS


def learner_checkpoint(run_dir: Path) -> Path:
    return checkpoints(run_dir) / LEARNER_CHECKPOINT


def buffer_checkpoint(run_dir: Path) -> Path:
    return checkpoints(run_dir) / BUFFER_CHECKPOINT


def best_model(run_dir: Path) -> Path:
    return Path(run_dir) / BEST_MODEL


def pids(run_dir: Path) -> Path:
    return Path(run_dir) / PIDS


def lock(run_dir: Path) -> Path:
    return Path(run_dir) / LOCK


def sweep_log(run_dir: Path) -> Path:
    return Path(run_dir) / SWEEP_LOG


def sweep_done(run_dir: Path) -> Path:
    return Path(run_dir) / SWEEP_DONE


def finished(run_dir: Path) -> Path:
    return Path(run_dir) / FINISHED
