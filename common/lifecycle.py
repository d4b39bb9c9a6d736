"""Process lifecycle: turn SIGINT/SIGTERM into a stop flag, and stop when the parent dies.

Every long-running loop polls `StopFlag.is_set()` (or waits on it), so Ctrl-C,
`kill`, a shutdown message or the death of the launching process all end the
component through the same clean path: close the Zenoh session, flush files.

This is the one module that installs signal handlers (tests/test_layout.py): a component's
(`StopFlag.install_signal_handlers`), a launcher's loop (`stop_signals_interrupt`), an in-process
run's (`stop_on_signals`), the quiet end of a run (`ignore_stop_signals`), each with the caller's
handlers back afterwards where a launcher runs inside another program (`caller_signal_handlers`).
"""

from __future__ import annotations

import contextlib
import faulthandler
import logging
import os
import signal
import sys
import threading
from typing import Iterator

#: A component exits with this when it cannot start from its inputs (a corrupt or foreign
#: checkpoint): restarting it would fail the same way, so `silcr train` does not, and exits 2.
EXIT_CANNOT_START = 3
#: A component, or `silcr train`, exits with this when the run ended (finished or stopped) but its last
#: checkpoint could not be written: the checkpoints on disk are older than the run, and a --resume would
#: go on from them. The launcher does not restart a component that exits with it (docs/reliability.md).
EXIT_STALE_CHECKPOINT = 4


class StopFlag:
    def __init__(self, watch_parent: bool = False) -> None:
        self._event = threading.Event()
        self.reason = ""
        self._parent = os.getppid() if watch_parent else None

    def install_signal_handlers(self) -> "StopFlag":
        def handler(signum: int, _frame: object) -> None:
            if self._event.is_set() and signum == signal.SIGINT:
                # A second Ctrl-C means "now": skip the clean path.
                os._exit(130)
            self.set(signal.Signals(signum).name)

        signal.signal(signal.SIGINT, handler)
        signal.signal(signal.SIGTERM, handler)
        # `kill -USR1 <pid>` prints where every thread of a component is to its stderr (its log), and it goes on:
        # what a component that stopped making progress is waiting on (docs/reliability.md).
        faulthandler.register(signal.SIGUSR1, all_threads=True)
        return self

    def set(self, reason: str = "stop requested") -> None:
        if not self._event.is_set():
            self.reason = reason
            self._event.set()

    def is_set(self) -> bool:
        if not self._event.is_set() and self._parent is not None and os.getppid() != self._parent:
            self.set("parent process died")
        return self._event.is_set()

    def wait(self, timeout: float) -> bool:
        """Sleep up to `timeout` seconds; return True as soon as stop is requested."""
        if self.is_set():
            return True
        step = 0.5 if self._parent is not None else timeout
        remaining = timeout
        while remaining > 0:
            if self._event.wait(min(step, remaining)):
                return True
            remaining -= step
            if self.is_set():
                return True
        return False


@contextlib.contextmanager
def caller_signal_handlers() -> Iterator[None]:
    """Whatever the block installs for SIGINT and SIGTERM (and SIGUSR1's stack dump), the caller's handlers come back
    after it.

    A launcher also runs inside other programs (the Python API's caller, a test): a handler it
    leaves behind, or a SIGINT left ignored while it closed, would be inherited by the caller's
    next child processes (an ignored signal survives exec) and change how they stop.
    """
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for signum, handler in previous.items():
            # None: installed outside Python; the default is the closest Python can put back.
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        faulthandler.unregister(signal.SIGUSR1)  # the stack dump `install_signal_handlers` set; the caller's action back


def ignore_stop_signals() -> None:
    """From now on SIGINT and SIGTERM change nothing (the work is done and on disk; the process is on its way
    out). Only the main thread can set handlers; elsewhere (a component run inside a test) this does nothing."""
    if threading.current_thread() is threading.main_thread():
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)


def _raise_interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def stop_signals_interrupt() -> None:
    """Ctrl-C and SIGTERM (`kill`, an orchestrator's stop) both raise KeyboardInterrupt here: a launcher's loop
    takes one clean path for either. Ctrl-C does so even where SIGINT came ignored from the parent (a shell's
    background job, `nohup`): the launchers' children stop on SIGINT whatever they inherited (`StopFlag`), so a
    launcher that ignored it would see them end and call the run finished."""
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _raise_interrupt)


@contextlib.contextmanager
def stop_on_signals(stop: StopFlag) -> Iterator[StopFlag]:
    """Within the block Ctrl-C and SIGTERM set `stop`: one clean stop, and a second Ctrl-C forces (exit 130).
    The caller's handlers come back after it. Off the main thread, where Python cannot set handlers, it
    installs nothing."""
    if threading.current_thread() is not threading.main_thread():
        yield stop
        return
    with caller_signal_handlers():
        yield stop.install_signal_handlers()


def setup_logging(component: str, level: int = logging.INFO) -> logging.Logger:
    logging.basicConfig(
        level=level,
        stream=sys.stderr,
        format=f"%(asctime)s {component} %(levelname)s %(message)s",
        datefmt="%H:%M:%S",
        force=True,
    )
    return logging.getLogger(component)
