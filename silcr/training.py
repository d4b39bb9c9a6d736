"""How a Python API model trains: in this process (`actors=0`) or as the distributed system (`actors=N`).

Both are the command line's own launchers, driven from Python:

* `InProcessTraining` holds a `deploy.single_process.SingleProcessRun` from the model's first
  `learn` to its `close`, so a second `learn` goes on with the same tables and counters. It
  holds the run directory's lock meanwhile, writes the components' logs where `silcr train
  --single-process` does, and turns Ctrl-C into a clean stop followed by KeyboardInterrupt.
* `DistributedTraining` is `silcr train`'s path (`deploy.launch.train`: a router, the buffer
  service, the learner and the actors as processes, all stopped when it returns, on an
  exception and on Ctrl-C). A second `learn` resumes from the checkpoints the first left.
  The learner writes progress.csv in its own process; a callback reads its rows as they come.
"""

from __future__ import annotations

import contextlib
import io
import logging
from typing import Any, Callable

from silcr.common import protocol as P
from silcr.common import run_layout
from silcr.common.config import Config, ConfigError
from silcr.common.run_end import RunHeld

#: The components' loggers, written to <run dir>/logs/single-process.log while an actors=0 model learns.
COMPONENT_LOGGERS = ("train", "learner", "buffer", "actor", "clients", "protocol", "mujoco")

RowCallback = Callable[[dict[str, Any]], bool]


def _held_for_python(e: RunHeld) -> ValueError:
    """`run_end.RunHeld` as an API user acts on it: `resume` is not a Python option (the next `learn` of the same
    model goes on by itself), so a run held from before is either another name's or the command line's to go on."""
    return ValueError(f"run: {e.run_dir} already holds {e.held}; pick another run name (or delete the directory "
                      f"to start that run again), or go on with it from the command line: silcr train --config "
                      f"{run_layout.config(e.run_dir)} --resume")


class InProcessTraining:
    def __init__(self, cfg: Config) -> None:
        from silcr.common.run_lock import RunInUse
        from silcr.deploy.launch import run_directory
        from silcr.deploy.single_process import ResumeError, SingleProcessRun

        self.cfg = cfg
        self._held = contextlib.ExitStack()
        try:
            self._held.enter_context(run_directory(cfg))  # the launcher's, as `silcr train` holds it
        except RunInUse as e:
            raise RuntimeError(str(e)) from None
        except RunHeld as e:
            raise _held_for_python(e) from None
        try:
            with self.component_logs():
                self.run = SingleProcessRun(cfg)
        except ResumeError as e:
            self._held.close()
            raise ValueError(f"cannot resume: {e}") from None
        except BaseException:
            self._held.close()
            raise

    @property
    def env_steps(self) -> int:
        return self.run.replay.transitions_received

    def weights(self) -> P.Weights:
        return self.run.learner.books.weights()

    def learn(self, on_row: RowCallback | None, progress_bar: bool) -> None:
        """Train to `cfg.total_steps`; KeyboardInterrupt after a clean stop if Ctrl-C came."""
        from silcr.common.lifecycle import StopFlag, stop_on_signals
        from silcr.deploy.console import TrainingDisplay

        self.cfg.save(run_layout.config(self.cfg.run_dir))
        with stop_on_signals(StopFlag()) as stop:  # Ctrl-C or SIGTERM: a clean stop, then KeyboardInterrupt
            display = TrainingDisplay(self.cfg.total_steps) if progress_bar else contextlib.nullcontext()
            with self.component_logs(), display:
                self.run.run(stop, display if progress_bar else None, on_row)
        if stop.is_set():
            raise KeyboardInterrupt

    def checkpoint(self) -> None:
        """Both checkpoints, now (for a model file with its training state)."""
        from silcr.buffer_service import snapshot
        from silcr.buffer_service.replay import checkpoint_path

        with self.component_logs():
            if not self.run.learner.books.checkpoint():
                raise OSError(f"the learner checkpoint could not be written to {run_layout.checkpoints(self.cfg.run_dir)}")
            snapshot.write(checkpoint_path(self.cfg), snapshot.take(self.run.replay))

    def close(self) -> None:
        """The last checkpoints written, the records closed, the run directory released; OSError when a final
        checkpoint could not be written (`StaleCheckpoints`: the files on disk are stale)."""
        from silcr.deploy.console import StaleCheckpoints

        try:
            with self.component_logs():
                stale = self.run.close()
        finally:
            self._held.close()
        if stale:
            raise StaleCheckpoints(self.cfg.run_dir, stale)

    @contextlib.contextmanager
    def component_logs(self):
        """The components' INFO logs to <run dir>/logs/single-process.log, as `silcr train --single-process`
        writes them, without touching the caller's own logging."""
        handler = logging.FileHandler(run_layout.single_process_log(self.cfg.run_dir))
        handler.setFormatter(logging.Formatter("%(asctime)s %(name)s %(levelname)s %(message)s", "%H:%M:%S"))
        loggers = [logging.getLogger(name) for name in COMPONENT_LOGGERS]
        before = [(lg.level, lg.propagate) for lg in loggers]
        for lg in loggers:
            lg.addHandler(handler)
            lg.setLevel(logging.INFO)
            lg.propagate = False
        try:
            yield
        finally:
            for lg, (level, propagate) in zip(loggers, before):
                lg.removeHandler(handler)
                lg.setLevel(level)
                lg.propagate = propagate
            handler.close()


class DistributedTraining:
    """One `learn` of an `actors=N` model: `silcr train`'s launcher, its rows and its stop included. After `learn`
    returns or raises (Ctrl-C, a callback's exception), `weights` and `env_steps` hold what the run's last
    learner checkpoint holds, so the model keeps what was trained and a next `learn` resumes from it."""

    def __init__(self, cfg: Config, resume: bool = False, free_port: bool = False) -> None:
        """`resume`: go on from the run's checkpoints (a model's second `learn`); `free_port`: the router on a free
        port of this machine (two models training at once must not meet on one port)."""
        self.cfg = cfg
        cfg.resume = resume or cfg.resume
        if free_port:
            import socket

            with socket.socket() as s:
                s.bind(("127.0.0.1", 0))
                cfg.zenoh_listen = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        self.weights: P.Weights | None = None
        self.env_steps = 0

    def learn(self, on_row: RowCallback | None, progress_bar: bool) -> None:
        """Run `silcr train`'s path to `cfg.total_steps`. A callback's False stops the run cleanly (every component
        stops and checkpoints); its exception does too, and is raised; a real Ctrl-C raises KeyboardInterrupt
        once they have stopped."""
        from silcr.common.lifecycle import EXIT_STALE_CHECKPOINT
        from silcr.common.run_lock import RunInUse
        from silcr.deploy.console import StaleCheckpoints
        from silcr.deploy.launch import run_to_end

        stopped = False

        def told(row: dict[str, Any]) -> bool:
            nonlocal stopped
            stopped = on_row(row) is False
            return not stopped

        quiet = contextlib.nullcontext() if progress_bar else contextlib.redirect_stdout(io.StringIO())
        stale: list[str] = []
        try:
            with quiet:
                code, stale = run_to_end(self.cfg, told if on_row is not None else None, who="silcr learn")
        except RunHeld as e:
            raise _held_for_python(e) from None
        except (RunInUse, ConfigError) as e:
            raise RuntimeError(str(e)) from None
        except KeyboardInterrupt:  # Ctrl-C before the launcher took it over
            code = 130
        finally:
            self._take_checkpoint()
        if code == 130 and not stopped:
            raise KeyboardInterrupt
        if code == EXIT_STALE_CHECKPOINT:
            raise StaleCheckpoints(self.cfg.run_dir, stale)
        if code not in (0, 130):
            raise RuntimeError(f"the distributed run ended with exit code {code}; the components' logs are in "
                               f"{run_layout.logs(self.cfg.run_dir)} (the line above names the one that failed)")

    def _take_checkpoint(self) -> None:
        """What the run's learner checkpoint holds now: the weights and env steps the model keeps."""
        from silcr.learner.checkpoint import CheckpointError, load_checkpoint
        from silcr.learner.evaluate import weights_from_checkpoint

        path = run_layout.learner_checkpoint(self.cfg.run_dir)
        if not path.exists():
            return
        try:
            final = load_checkpoint(path)
        except CheckpointError:
            return
        self.weights, self.env_steps = weights_from_checkpoint(final)[0], int(final["counters"]["env_steps"])
