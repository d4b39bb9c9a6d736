"""What `silcr train` shows while a run goes: a progress bar (or plain lines when not on a terminal),
one-off messages, and the divergence warning; and how a run ended (`report_end`, `StaleCheckpoints`). Both
launchers use it: `deploy.local` (processes) and `deploy.single_process`, through `deploy.launch`.
"""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any, NamedTuple

from silcr.common import run_layout
from silcr.common.lifecycle import EXIT_STALE_CHECKPOINT
from silcr.learner.progress import read_rows


def format_return(x: float) -> str:
    """A return as people read it: 1,234.5-style for MuJoCo, three digits for the returns below 10
    (MiniGrid pays at most 1; '1.0' would hide the difference between 0.955 and 0.973)."""
    return f"{x:.3f}" if abs(x) < 10 else f"{x:.1f}"


def done_message(run_dir: Path) -> str:
    """The closing line of a finished run: its last evaluation (the learner's final one), its best one when the
    learner kept that policy (best.silcr), and where the records are."""
    last = ""
    rows = read_rows(run_dir)
    try:
        if rows and rows[-1].get("eval_return"):
            last = f" final evaluation {format_return(float(rows[-1]['eval_return']))} at {rows[-1]['env_steps']} env steps;"
    except ValueError:
        pass  # the line still says where to look
    best = best_evaluation(run_dir)
    if best is not None:
        last += (f" best {format_return(float(best['return_mean']))} at {best['env_steps']} env steps, its policy in "
                 f"{run_layout.best_model(run_dir)};")
    return (f"silcr train: done.{last} progress: {run_layout.progress(run_dir)}; "
            f"TensorBoard: tensorboard --logdir {run_layout.tensorboard(run_dir)}")


def best_evaluation(run_dir: Path) -> dict[str, Any] | None:
    """The evaluation that chose the run's best.silcr, as the file records it (progress.csv's highest row can be
    newer than the file, when writing it failed), or None where there is no readable file."""
    path = run_layout.best_model(run_dir)
    if not path.exists():
        return None
    from silcr.learner.model_file import ModelFileError, read  # torch: loaded only once a run has ended

    try:
        evaluation = read(path).get("evaluation")
    except ModelFileError:
        return None
    return evaluation if isinstance(evaluation, dict) and {"return_mean", "env_steps"} <= set(evaluation) else None


CHECKPOINT_FILES = {"learner": run_layout.learner_checkpoint, "buffer": run_layout.buffer_checkpoint}


class StaleCheckpoints(OSError):
    """A run ended, but the final checkpoint of `components` ("learner", "buffer") could not be written: the files
    on disk are from before the end, and --resume would go on from there."""

    def __init__(self, run_dir: Path, components: list[str]) -> None:
        self.components = components
        files = ", ".join(str(CHECKPOINT_FILES[c](run_dir)) for c in components)
        super().__init__(f"the final checkpoint of the {' and the '.join(components)} could not be written (see "
                         f"{run_layout.logs(run_dir)}): {files} {'is' if len(components) == 1 else 'are'} stale, from "
                         f"before the end of the run, and --resume would continue from there; progress.csv holds the "
                         f"whole run")


class RunEnd(NamedTuple):
    """How a launcher's run ended: its exit code (0 finished, 130 stopped, 1 or 2 failed) and the components whose
    final checkpoint could not be written."""

    code: int
    stale: list[str]


def report_end(run_dir: Path, end: RunEnd, who: str = "silcr train") -> int:
    """The one report of a run's end, for every launcher: stale checkpoints named on stderr (a finished run then
    exits EXIT_STALE_CHECKPOINT, 4), a finished run's closing line; the exit code."""
    if end.stale:
        print(f"{who}: error: {StaleCheckpoints(run_dir, end.stale)}", file=sys.stderr)
        if end.code == 0:
            return EXIT_STALE_CHECKPOINT
    if end.code == 0:
        print(done_message(run_dir))
    return end.code


def divergence_warning(learner_stats: dict[str, Any]) -> str:
    """The one line `silcr train` prints when the critics first pass the soft-Q bound."""
    def num(key: str) -> str:
        v = learner_stats.get(key)
        return f"{v:.4g}" if isinstance(v, (int, float)) else "?"

    return (f"silcr train: warning: the critics are diverging: {learner_stats.get('q_bound_exceeded')} update(s) by "
            f"{learner_stats.get('env_steps', '?')} env steps had Q above the largest soft-Q value the rewards and alpha "
            f"allow (now: max Q {num('q_max')}, bound {num('q_bound')}); a smaller --tau helps (docs/algorithm.md, "
            f"'Divergence')")


class TrainingDisplay:
    """A rich progress bar over environment steps on a terminal; a line every 10 s otherwise (logs, CI)."""

    def __init__(self, total_steps: int) -> None:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

        self.total_steps = total_steps
        self.interactive = sys.stdout.isatty()
        self._bar = Progress(
            TextColumn("[bold]env steps"),
            BarColumn(),
            MofNCompleteColumn(),
            TextColumn("updates {task.fields[updates]}  version {task.fields[version]}  eval {task.fields[eval]}"),
            TimeElapsedColumn(),
            disable=not self.interactive,
        )
        self._task = self._bar.add_task("train", total=total_steps, updates=0, version=0, eval="-")
        self._last_print = 0.0
        self._warned_divergence = False

    def __enter__(self) -> "TrainingDisplay":
        self._bar.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        self._bar.__exit__(*exc)

    def stop(self) -> None:
        self._bar.stop()

    def say(self, message: str) -> None:
        if self.interactive:
            self._bar.console.print(message)
        else:
            print(message, flush=True)

    def show(self, env_steps: int, learner_stats: dict[str, Any]) -> None:
        """Advance the bar from the learner's stats; warn once if the critics passed the soft-Q bound."""
        if not self._warned_divergence and (learner_stats.get("q_bound_exceeded") or 0) > 0:
            self._warned_divergence = True
            self.say(divergence_warning(learner_stats))
        ev = learner_stats.get("last_eval_return")
        ev_s = format_return(ev) if isinstance(ev, (int, float)) else "-"
        updates, version = learner_stats.get("updates", 0), learner_stats.get("policy_version", 0)
        # The count as it is: the actors finish the episodes they are in, so a run ends a little past its budget.
        self._bar.update(self._task, completed=env_steps, updates=updates, version=version, eval=ev_s)
        if not self.interactive and time.monotonic() - self._last_print > 10:
            print(f"env steps {env_steps}/{self.total_steps}  updates {updates}  version {version}  eval {ev_s}",
                  flush=True)
            self._last_print = time.monotonic()
