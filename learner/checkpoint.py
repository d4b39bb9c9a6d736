"""Learner checkpoints: written atomically, read without running code.

Writing: a temporary file in the same directory, fsync, rename, so a crash at any
moment leaves either the previous checkpoint or the new one, never a half-written file.

Reading: `torch.load(weights_only=True)`, which unpickles only tensors and plain
containers and numbers. A checkpoint is a pickle, and a full unpickler runs
whatever code the file names, so `silcr eval` on a file from elsewhere must not
use one. Every checkpoint silcr has written holds only such data and loads the same way.
"""

from __future__ import annotations

import pickle
from pathlib import Path
from typing import Any

import torch

from silcr.common import run_end, run_layout
from silcr.common.atomic_file import write_atomic
from silcr.common.config import Config


class CheckpointError(RuntimeError):
    pass


def save_checkpoint(path: Path, payload: dict[str, Any]) -> None:
    write_atomic(path, lambda f: torch.save(payload, f))


def load_plain(path: Path, error: type[Exception], what: str) -> Any:
    """`torch.load(weights_only=True)` of the `what` at `path`, or `error` with one line: missing, holding objects
    that would run code (refused), or unreadable. Learner checkpoints and the Python API's model files use it."""
    if not path.exists():
        raise error(f"no {what} at {path}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError as e:  # what weights_only refuses: objects that are not plain data
        # torch's message suggests loading with weights_only=False; keep only the line naming the object.
        named = [line.strip() for line in str(e).splitlines() if "GLOBAL" in line]
        if not named:  # no object named: not a pickle at all
            raise error(f"{what} {path} is unreadable or corrupt (not a torch file)") from None
        raise error(f"{what} {path} holds objects other than tensors and plain data, which could run code when "
                    f"loaded; refused ({named[0]})") from None
    except Exception as e:  # torch raises several types for truncated or foreign files
        if not _looks_like_torch(path):  # torch's own error for these says nothing useful ("KeyError: 101")
            raise error(f"{what} {path} is unreadable or corrupt (not a torch file)") from None
        raise error(f"{what} {path} is unreadable or corrupt ({type(e).__name__}: {e})") from None


def _looks_like_torch(path: Path) -> bool:
    """Whether the file starts as torch.save's files do: a zip archive (since torch 1.6) or a pickle."""
    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except OSError:
        return False
    return head.startswith(b"PK\x03\x04") or head[:1] == b"\x80"


def load_checkpoint(path: Path) -> dict[str, Any]:
    return checked_checkpoint(load_plain(path, CheckpointError, "checkpoint"), path)


def checked_checkpoint(payload: Any, path: Path) -> dict[str, Any]:
    """`payload`, loaded from `path`, if it is a learner checkpoint; CheckpointError with one line otherwise."""
    if not isinstance(payload, dict) or not isinstance(payload.get("sac"), dict) or "counters" not in payload:
        raise CheckpointError(f"{path} is not a silcr learner checkpoint")
    return payload


def finished_run(cfg: Config) -> run_end.Finished | None:
    """How `cfg`'s run finished if a budget of `cfg.total_steps` is already spent there (the finished-run rule,
    `common/run_end.py`): its finished.json, or for a run finished before that file existed, its learner
    checkpoint's counters (every env step of the budget collected, every update it is due made). None when
    the run can go on (or does not exist); an unreadable checkpoint is left to the learner to report."""
    if run_end.read(cfg.run_dir) is not None:
        return run_end.finished(cfg)
    path = run_layout.learner_checkpoint(cfg.run_dir)
    if not path.exists():
        return None
    try:
        counters = load_checkpoint(path)["counters"]
        env_steps, updates = int(counters["env_steps"]), int(counters["updates"])
    except (CheckpointError, KeyError, TypeError, ValueError):
        return None
    if env_steps >= cfg.total_steps and updates >= run_end.target_updates(cfg):
        return run_end.Finished(cfg.run, env_steps, updates, cfg.total_steps)
    return None


class LearnerCheckpoints:
    """The run's learner checkpoint (`<run dir>/checkpoints/learner.pt`): found and loaded on --resume,
    written when the schedule says, and a count of the writes that failed."""

    def __init__(self, run_dir: Path, resume: bool) -> None:
        self.path = run_layout.learner_checkpoint(run_dir)
        # --resume continues from a checkpoint when there is one, so the same command
        # serves a first start and every restart (launcher, sweep, docker restart policy).
        self.resumed = resume and self.path.exists()
        self.failed = 0

    def load(self) -> dict[str, Any] | None:
        """The checkpoint to resume from, or None for a fresh start."""
        return load_checkpoint(self.path) if self.resumed else None

    def write(self, payload: dict[str, Any]) -> None:
        """Write `payload`; a failure is counted, and raised as OSError or RuntimeError (torch.save's)."""
        try:
            save_checkpoint(self.path, payload)
        except (OSError, RuntimeError):
            self.failed += 1
            raise

    def state(self) -> dict[str, int]:
        return {"checkpoints_failed": self.failed}

    def restore(self, counters: dict[str, Any]) -> None:
        self.failed = int(counters.get("checkpoints_failed", 0))  # absent from checkpoints before 0.4
