"""Training records: `progress.csv` (one row per evaluation) and TensorBoard events."""

from __future__ import annotations

import contextlib
import csv
import errno
import io
import logging
import math
import os
import threading
import time
from pathlib import Path
from typing import Any

from silcr.common import run_layout

log = logging.getLogger("learner")

#: The critics' health at the last update before the row (docs/algorithm.md, "Divergence"):
#: `q_bound_exceeded` counts every update so far whose largest Q passed the soft-Q bound.
DIVERGENCE_COLUMNS = ["q_mean", "q_max", "target_q_mean", "log_pi_mean", "q_bound", "q_bound_exceeded"]
#: GASIL's discriminator at the last update before the row (empty for other algorithms).
GASIL_COLUMNS = ["disc_loss", "disc_acc_expert", "disc_acc_policy", "gasil_reward_mean"]
#: D_E as the buffer service last described it (empty for plain SAC).
EXPERT_COLUMNS = ["expert_transitions", "expert_episodes", "expert_min_return", "expert_max_return"]
#: The mean return and length of the last 100 episodes the actors finished (their sampled actions; the
#: reward as the actors' env pays it), as the buffer service last described them.
ROLLOUT_COLUMNS = ["rollout_return", "rollout_length"]

PROGRESS_COLUMNS = [
    "time",
    "env_steps",
    "updates",
    "policy_version",
    "eval_return",
    "eval_return_std",
    "eval_length",
    "alpha",
    "critic_loss",
    "actor_loss",
    "updates_per_s",
    *DIVERGENCE_COLUMNS,
    *EXPERT_COLUMNS,
    *GASIL_COLUMNS,
    "checkpoints_failed",  # learner checkpoints that could not be written (silcr 0.4)
    "eval_success",  # share of evaluation episodes that reached the goal; empty for tasks without one (silcr 0.5)
    "q_target_clipped",  # share of the last update's TD targets cut at the soft-Q bound (--q-target-clip bound)
    *ROLLOUT_COLUMNS,
    # mean info["x_velocity"] over the evaluation's steps (m/s); empty for envs without it (silcr 0.6)
    "eval_x_velocity",
    # eval_return over D_E's lowest return, once D_E has filled (`evaluations.keep_ratio`; silcr 0.6)
    "keep_ratio",
    "bc_loss",  # the last update's behaviour-cloning loss on D_E rows (--bc-weight above 0)
    "wall_time",  # seconds since the run first started, every resumed stretch added (`time` restarts; silcr 0.6)
]


def read_rows(run_dir: Path) -> list[dict[str, str]]:
    """The rows of a run's progress.csv so far, as written (strings); none when it is missing or unreadable."""
    try:
        with open(run_layout.progress(run_dir), newline="") as f:
            return list(csv.DictReader(f))
    except (OSError, csv.Error):
        return []


class ProgressFollower:
    """A run's progress.csv followed as another process writes it (`tail -f`): `new_rows()` gives the whole rows
    written since the last call, read from where the last call stopped. Rows already there when it starts are
    skipped (a resumed run's earlier rows were told before); a row is taken once its line has ended, so a row
    half-written, or cut back after a failed write, is never read. A file replaced or shorter than what was
    read (rewritten) is read again from the start, skipping the rows already given."""

    def __init__(self, run_dir: Path) -> None:
        self.path = run_layout.progress(run_dir)
        self.header: list[str] | None = None
        self.offset = 0
        self.inode: int | None = None
        self.given = 0  # rows given, those skipped at the start counted in
        self.new_rows()

    def new_rows(self) -> list[dict[str, str]]:
        try:
            with open(self.path, "rb") as f:
                st = os.fstat(f.fileno())
                if st.st_ino != self.inode or st.st_size < self.offset:  # new or rewritten: from the start
                    self.header, self.offset, self.inode, skip = None, 0, st.st_ino, self.given
                else:
                    skip = 0
                f.seek(self.offset)
                chunk = f.read()
        except OSError:
            return []
        ended = chunk.rfind(b"\n") + 1  # only whole lines
        self.offset += ended
        lines = chunk[:ended].decode(errors="replace").splitlines()
        if self.header is None and lines:
            self.header = next(csv.reader([lines.pop(0)]))
        rows = [dict(zip(self.header, values)) for values in csv.reader(lines) if values]
        self.given += len(rows) - min(skip, len(rows))
        return rows[skip:]


def typed(row: dict[str, str]) -> dict[str, Any]:
    """A progress.csv row as the learner wrote it: numbers as numbers (int where whole), "" where empty."""
    out: dict[str, Any] = {}
    for key, text in row.items():
        try:
            out[key] = int(text)
        except (TypeError, ValueError):
            try:
                out[key] = float(text)
            except (TypeError, ValueError):
                out[key] = text
    return out


class ProgressLog:
    """progress.csv and TensorBoard, written so that a full disk (or a failing one) costs records, never the run.

    Every progress row is written whole or not at all: a write that fails (ENOSPC, EIO) is cut back to the
    row before it, the row waits (up to `MAX_PENDING_ROWS`, the oldest dropped beyond and counted), and the
    rows that waited are written, in order, before the next one once there is room again. A TensorBoard
    writer that fails is closed, its scalars dropped (counted) until it is reopened (a new event file, which
    TensorBoard reads beside the old ones) `TB_RETRY_S` later. Failures are logged once each time writing
    stops working and counted in `failed_writes` (the learner's stats: `records_failed`).
    """

    MAX_PENDING_ROWS = 10_000
    TB_RETRY_S = 30.0

    def __init__(self, run_dir: Path, resume: bool = False) -> None:
        run_dir.mkdir(parents=True, exist_ok=True)
        self.csv_path = run_layout.progress(run_dir)
        self.tb_dir = run_layout.tensorboard(run_dir)
        new = not (resume and self.csv_path.exists())
        if not new:
            _upgrade_header(self.csv_path)
        self._fd = os.open(self.csv_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND | (os.O_TRUNC if new else 0), 0o644)
        self._pending: list[bytes] = [_line(dict(zip(PROGRESS_COLUMNS, PROGRESS_COLUMNS)))] if new else []
        self.failed_writes = 0  # rows and scalars that could not be written when first tried
        self.rows_dropped = 0  # rows given up (more than MAX_PENDING_ROWS waiting)
        self.scalars_dropped = 0
        self._failing = False
        self._tb = None
        self._tb_retry_at = 0.0
        quiet_disk_errors_in_threads()
        self._flush_rows()
        self._open_tb()

    def row(self, values: dict[str, Any]) -> dict[str, Any]:
        """Write one row (or keep it until there is room); the row as written (a column of none, NaN or infinity
        is empty, ""), by column."""
        clean = {k: ("" if v is None or isinstance(v, float) and not math.isfinite(v) else v)
                 for k, v in values.items() if k in PROGRESS_COLUMNS}
        clean = {k: clean.get(k, "") for k in PROGRESS_COLUMNS}
        self._pending.append(_line(clean))
        if len(self._pending) > self.MAX_PENDING_ROWS:
            self._pending.pop(1 if self._pending[0].startswith(b"time,") else 0)
            self.rows_dropped += 1
        self._flush_rows()
        step = int(values["env_steps"])
        scalars = {f"eval/{k.removeprefix('eval_')}": values[k] for k in
                   ("eval_return", "eval_return_std", "eval_length", "eval_success", "eval_x_velocity")
                   if k in values and isinstance(values[k], (int, float))}
        if isinstance(values.get("keep_ratio"), (int, float)):
            scalars["eval/keep_ratio"] = values["keep_ratio"]
        self.scalars(scalars, step)
        return clean

    def scalars(self, values: dict[str, float], step: int) -> None:
        if not values:
            return
        if self._tb is None and not self._open_tb():
            self.scalars_dropped += len(values)
            return
        try:
            for k, v in values.items():
                self._tb.add_scalar(k, v, step)
        except OSError as e:  # the writer's thread failed (a full disk): it is broken for good
            self._failed("TensorBoard events", e)
            self.scalars_dropped += len(values)
            self._close_tb()
            self._tb_retry_at = time.monotonic() + self.TB_RETRY_S

    def stats(self) -> dict[str, int]:
        return {"records_failed": self.failed_writes, "records_waiting": len(self._pending),
                "records_dropped": self.rows_dropped + self.scalars_dropped}

    def close(self) -> None:
        self._flush_rows()
        if self._pending:
            log.error("%d progress.csv row(s) could not be written before the end (%s)", len(self._pending),
                      self.csv_path)
        os.close(self._fd)
        self._close_tb()

    # -- writing -----------------------------------------------------------------------------------------
    def _flush_rows(self) -> None:
        while self._pending:
            line = self._pending[0]
            try:
                end = os.fstat(self._fd).st_size
                written = os.write(self._fd, line)
                if written != len(line):
                    raise OSError(errno.ENOSPC, f"wrote {written} of {len(line)} bytes")
            except OSError as e:
                with contextlib.suppress(OSError):
                    os.ftruncate(self._fd, end)  # no half row: the file ends at the last whole one
                self._failed("progress.csv", e)
                return
            self._pending.pop(0)
            if self._failing:
                self._failing = False
                log.warning("progress.csv is written again (%d write(s) failed meanwhile)", self.failed_writes)

    def _failed(self, what: str, e: OSError) -> None:
        self.failed_writes += 1
        if not self._failing:
            self._failing = True
            log.error("%s could not be written (%s); training goes on, the rows wait and are written when there "
                      "is room, and failures are counted (records_failed)", what, e.strerror or e)

    def _open_tb(self) -> bool:
        if time.monotonic() < self._tb_retry_at:
            return False
        from torch.utils.tensorboard import SummaryWriter  # imported late: it is slow to import

        try:
            self._tb = SummaryWriter(log_dir=str(self.tb_dir))
        except OSError as e:
            self._failed("TensorBoard events", e)
            self._tb_retry_at = time.monotonic() + self.TB_RETRY_S
            return False
        return True

    def _close_tb(self) -> None:
        if self._tb is not None:
            with contextlib.suppress(Exception):  # a writer whose thread failed raises its error again here
                self._tb.close()
            self._tb = None


def _line(values: dict[str, Any]) -> bytes:
    out = io.StringIO()
    csv.DictWriter(out, fieldnames=PROGRESS_COLUMNS, extrasaction="ignore").writerow(values)
    return out.getvalue().encode()


def quiet_disk_errors_in_threads() -> None:
    """A writer thread that dies of a full or failing disk (TensorBoard's) logs one line, not a traceback: the
    failure is handled where it surfaces (`ProgressLog`)."""
    if getattr(threading.excepthook, "_silcr_quiet_disk", False):
        return
    previous = threading.excepthook

    def hook(args: threading.ExceptHookArgs) -> None:
        if isinstance(args.exc_value, OSError) and args.exc_value.errno in _DISK_ERRNOS:
            log.warning("thread %s: %s", args.thread.name if args.thread else "?", args.exc_value)
            return
        previous(args)

    hook._silcr_quiet_disk = True  # type: ignore[attr-defined]
    threading.excepthook = hook


_DISK_ERRNOS = {errno.ENOSPC, errno.EIO, errno.EDQUOT, errno.EROFS}


def _upgrade_header(path: Path) -> None:
    """Rewrite a progress.csv written with other columns (an older silcr) under today's, so resumed rows line up."""
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        if reader.fieldnames == PROGRESS_COLUMNS:
            return
        rows = list(reader)
    tmp = path.with_suffix(".csv.tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=PROGRESS_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    tmp.replace(path)
