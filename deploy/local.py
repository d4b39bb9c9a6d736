"""`silcr train`: the whole system on one machine, one process per component.

Starts a Zenoh router, the buffer service, the learner and N actors, each as a new
Python process running this module's `child_main` (given its role, and its configuration
on standard input): never a fork (a forked child of a process with a
Zenoh session hangs or talks to nobody), and never a re-import of the caller's script
(multiprocessing's `spawn` runs the `__main__` of a Python API user's script again in
every child, and cannot at all for a script read from standard input). It shows a
progress bar fed by the stats topics, restarts a
component that dies (actors fresh, buffer and learner from their checkpoints, up
to --max-restarts; the router too), and ends everything when the learner finishes, a component
dies for good, or on Ctrl-C. Each
child writes its log to `<run dir>/logs/<component>.log` and stops by itself
if this process disappears.
"""

from __future__ import annotations

import json
import logging
import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any, Callable

from silcr.common import protocol as P
from silcr.common import run_layout, seeds
from silcr.common.config import Config, actor_zenoh_mode
from silcr.common.control_channel import Shutdown
from silcr.common.lifecycle import (
    EXIT_CANNOT_START,
    EXIT_STALE_CHECKPOINT,
    StopFlag,
    caller_signal_handlers,
    ignore_stop_signals,
    setup_logging,
    stop_signals_interrupt,
)
from silcr.common.zenoh_session import open_session, session_config
from silcr.deploy.console import RunEnd, TrainingDisplay
from silcr.deploy.monitor import StatsSnapshot

log = logging.getLogger("train")

STOP_GRACE_S = 20.0


def component_main(role: str, cfg_dict: dict[str, Any], log_path: str) -> None:
    """What every child process runs (`child_main`, at the end of this file)."""
    fd = os.open(log_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    os.dup2(fd, 1)
    os.dup2(fd, 2)
    os.close(fd)
    sys.stdout = open(1, "w", buffering=1, closefd=False)
    sys.stderr = open(2, "w", buffering=1, closefd=False)
    name = role if role != "actor" else f"actor-{cfg_dict['actor_id']}"
    setup_logging(name)
    stop = StopFlag(watch_parent=True).install_signal_handlers()
    cfg = Config(**cfg_dict)
    try:
        if role == "router":
            from silcr.deploy.router import run_router

            code = run_router([cfg.zenoh_listen], [], cfg.zenoh_config, stop)
        elif role == "buffer":
            from silcr.buffer_service.service import run_buffer

            code = run_buffer(cfg, stop)
        elif role == "learner":
            from silcr.learner.service import run_learner

            code = run_learner(cfg, stop)
        else:
            from silcr.actor.service import run_actor

            code = run_actor(cfg, stop)
    except Exception:
        logging.getLogger(name).exception("%s failed", name)
        code = 1
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(code)


def _endpoint_host_port(endpoint: str) -> tuple[str, int] | None:
    try:
        proto, addr = endpoint.split("/", 1)
        host, port = addr.rsplit(":", 1)
        return host.strip("[]"), int(port.split("#")[0])
    except ValueError:
        return None


def port_in_use(endpoint: str) -> bool:
    hp = _endpoint_host_port(endpoint)
    if hp is None or not endpoint.startswith("tcp/"):
        return False
    with socket.socket(socket.AF_INET6 if ":" in hp[0] else socket.AF_INET) as s:
        s.settimeout(0.5)
        return s.connect_ex(hp) == 0


def _tail(path: Path, lines: int = 15) -> str:
    try:
        return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


class Component:
    """One child process, with the few calls the launcher makes of it."""

    def __init__(self, role: str, cfg: Config, log_path: Path) -> None:
        # The child reads its configuration from standard input (as JSON: exactly these values, not the
        # environment's SILCR_* again) before it sends its output to the log.
        # Not `python -m`: that puts the working directory first on sys.path (common/commands.py says why not).
        entry = "import sys; sys.path.pop(0); from silcr.deploy.local import child_main; child_main()"
        self._popen = subprocess.Popen([sys.executable, "-c", entry, role, str(log_path)],
                                       stdin=subprocess.PIPE, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        assert self._popen.stdin is not None
        try:
            self._popen.stdin.write(json.dumps(cfg.to_dict()).encode())
            self._popen.stdin.close()
        except BrokenPipeError:  # it died at once: its exit code says so
            pass
        self.pid = self._popen.pid

    @property
    def exitcode(self) -> int | None:
        return self._popen.poll()

    def is_alive(self) -> bool:
        return self._popen.poll() is None

    def terminate(self) -> None:
        self._popen.terminate()

    def kill(self) -> None:
        self._popen.kill()

    def join(self, timeout: float) -> None:
        try:
            self._popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pass


class LocalRun:
    def __init__(self, cfg: Config) -> None:
        self.cfg = cfg
        self.procs: dict[str, Component] = {}
        self.failed_log: Path | None = None  # the log of the component whose death ended the run
        self.specs: dict[str, tuple[str, Config]] = {}
        self.restarts: dict[str, int] = {}
        self.logs = run_layout.logs(cfg.run_dir)

    def log(self, name: str) -> Path:
        return run_layout.component_log(self.cfg.run_dir, name)

    def start(self, role: str, cfg: Config, name: str) -> None:
        self.specs[name] = (role, cfg)
        self.procs[name] = Component(role, cfg, self.log(name))
        # For operators and tests: which PID is which component. A full disk must not end the run here.
        pids = {n: proc.pid for n, proc in self.procs.items()} | {"train": os.getpid()}
        tmp = self.cfg.run_dir / ".pids.json.tmp"
        try:
            tmp.write_text(json.dumps(pids))
            tmp.replace(run_layout.pids(self.cfg.run_dir))
        except OSError as e:
            tmp.unlink(missing_ok=True)
            log.warning("%s could not be written (%s); the run goes on", run_layout.pids(self.cfg.run_dir), e)

    def stop_all(self, order: list[str]) -> None:
        for name in order:
            p = self.procs.get(name)
            if p is not None and p.is_alive():
                p.terminate()  # SIGTERM: the component's clean path
        deadline = time.monotonic() + STOP_GRACE_S
        for name in order:
            p = self.procs.get(name)
            if p is not None:
                p.join(max(0.1, deadline - time.monotonic()))
                if p.is_alive():
                    log.warning("%s did not stop within %.0fs; killing it", name, STOP_GRACE_S)
                    p.kill()
                    p.join(5)


RowCallback = Callable[[dict[str, Any]], bool]


class StoppedByCaller(Exception):
    """The caller's row callback said stop (returned False)."""


def run_train(cfg: Config, on_row: RowCallback | None = None, who: str = "silcr train") -> RunEnd:
    """The run to its end; how it ended (the launcher reports it: `console.report_end`). `on_row` gets every new
    progress.csv row (typed), from this thread: False stops the run cleanly (130), an exception stops it cleanly and
    is raised. `who` starts every line printed."""
    with caller_signal_handlers():  # the caller's (the Python API's caller's: a notebook's, say) come back after
        return _run_train(cfg, on_row, who)


def _run_train(cfg: Config, on_row: RowCallback | None, who: str) -> RunEnd:
    run_dir = cfg.run_dir  # held by the launcher (`launch.run_directory`), which checked the port
    child_cfg = Config(**cfg.to_dict())
    if not child_cfg.connect:
        child_cfg.connect = [cfg.zenoh_listen]
    run = LocalRun(cfg)
    actor_names = [f"actor-{i}" for i in range(cfg.actors)]
    order = [*actor_names, "learner", "buffer", "router"]
    print(f"{who}: run {cfg.run} in {run_dir} ({cfg.algo} on {cfg.env}, {cfg.actors} actor(s), {cfg.total_steps} env steps)")
    keys = P.Keys(cfg.run)
    stats = StatsSnapshot(keys)
    code = 0
    stop_signals_interrupt()  # `kill` of the launcher takes the same clean path as Ctrl-C
    try:
        run.start("router", cfg, "router")
        deadline = time.monotonic() + 15
        while not port_in_use(cfg.zenoh_listen):
            if not run.procs["router"].is_alive() or time.monotonic() > deadline:
                print(f"{who}: error: the Zenoh router did not start on {cfg.zenoh_listen} ({run.log('router')}):\n"
                      f"{_tail(run.log('router'))}", file=sys.stderr)
                run.stop_all(order)
                return RunEnd(1, [])
            time.sleep(0.1)
        # Stats in, the run's end out; its transport's errors (peers closing at the end) would only reach the
        # caller's standard output (a Python API user's): each component logs its own session's to its file.
        with open_session(session_config([cfg.zenoh_listen], [], "peer", cfg.zenoh_config), zenoh_log=False) as session:
            session.declare_subscriber(keys.stats_learner, stats.on_sample)
            session.declare_subscriber(keys.stats_buffer, stats.on_sample)
            # With --resume, one at a time: a checkpoint that cannot be read stops the run before the
            # others start, so none of them rewrites its own checkpoint meanwhile.
            for role in ("buffer", "learner"):
                run.start(role, child_cfg, role)
                if cfg.resume and (failed := _wait_started(run, role, stats)):
                    print(f"{who}: error: {failed}", file=sys.stderr)
                    return RunEnd(2, [])
            actor_mode = actor_zenoh_mode(cfg)
            if actor_mode != cfg.zenoh_mode:
                print(f"{who}: the {cfg.actors} actors join as Zenoh {actor_mode}s of the router "
                      f"(--actor-zenoh-mode {cfg.actor_zenoh_mode})")
            for i, name in enumerate(actor_names):
                acfg = Config(**child_cfg.to_dict())
                acfg.actor_id = i
                acfg.zenoh_mode = actor_mode
                run.start("actor", acfg, name)
            code = _watch(run, cfg, stats, who, RowFeed(run_dir, on_row) if on_row is not None else None)
            if code == 0:
                Shutdown(session, keys).announce(P.ShutdownNotice.FINISHED)
    except KeyboardInterrupt:
        print(f"\n{who}: interrupted; stopping all components (Ctrl-C again to force)", file=sys.stderr)
        code = 130
    except StoppedByCaller:
        print(f"{who}: the callback stopped training; stopping all components", file=sys.stderr)
        code = 130
    finally:
        ignore_stop_signals()  # let the children finish their clean exit
        run.stop_all(order)
    if code == 1:  # 2 (a component cannot start) has said its one line; 130 is Ctrl-C
        print(f"{who}: stopped with errors; the cause is in {run.failed_log or run.logs}", file=sys.stderr)
    return RunEnd(code, [name for name in ("learner", "buffer") if name in run.procs
                         and run.procs[name].exitcode == EXIT_STALE_CHECKPOINT])


class RowFeed:
    """Hands the caller each new progress.csv row, typed, from the launcher's own loop: the learner writes them in
    its process, and `learner.progress.ProgressFollower` reads each once, as it is written."""

    def __init__(self, run_dir: Path, on_row: RowCallback) -> None:
        from silcr.learner.progress import ProgressFollower

        self.on_row = on_row
        self.rows = ProgressFollower(run_dir)  # a resumed run's earlier rows were told before
        self._next = 0.0

    def poll(self, now: bool = False) -> None:
        """Feed the rows written since the last call (at most every half second unless `now`); StoppedByCaller
        when the callback returns False."""
        if not now and time.monotonic() < self._next:
            return
        self._next = time.monotonic() + 0.5
        from silcr.learner.progress import typed

        for row in self.rows.new_rows():
            if self.on_row(typed(row)) is False:
                raise StoppedByCaller


def _cannot_start(run: LocalRun, name: str) -> str:
    """The one line a component that could not start logged ("cannot start: ...")."""
    lines = [line for line in _tail(run.log(name), 50).splitlines() if "cannot start: " in line]
    why = lines[-1].split("cannot start: ", 1)[1] if lines else f"see {run.log(name)}"
    return f"{name} cannot start: {why}"


def _wait_started(run: LocalRun, name: str, stats: StatsSnapshot, timeout_s: float = 300.0) -> str | None:
    """Wait for `name`'s first stats message (it has restored its checkpoint); the reason if it could not start."""
    deadline = time.monotonic() + timeout_s
    while stats.as_dict()[name] is None:
        code = run.procs[name].exitcode
        if code == EXIT_CANNOT_START:
            return _cannot_start(run, name)
        if code is not None:  # died some other way: `_watch` restarts it as it would any time
            return None
        if time.monotonic() > deadline:
            log.warning("%s sent no stats within %.0f s; starting the others", name, timeout_s)
            return None
        time.sleep(0.1)
    return None


def _watch(run: LocalRun, cfg: Config, stats: StatsSnapshot, who: str, rows: RowFeed | None) -> int:
    """Follow the run until the learner finishes (0) or a component dies (1); feed `rows` on the way."""
    clean_exit_seen: dict[str, float] = {}
    with TrainingDisplay(cfg.total_steps) as display:
        while True:
            if rows is not None:
                rows.poll()
            snap = stats.as_dict()
            lr = snap["learner"] or {}
            display.show(max(int(lr.get("env_steps", 0)), int((snap["buffer"] or {}).get("transitions_received", 0))), lr)
            if run.procs["learner"].exitcode in (0, EXIT_STALE_CHECKPOINT):  # finished (stale: said at the end)
                if rows is not None:
                    rows.poll(now=True)  # the closing evaluation's row
                return 0
            for name, p in list(run.procs.items()):
                if p.exitcode is None:
                    continue
                if p.exitcode == EXIT_CANNOT_START:  # it would fail the same way again: no restart
                    display.stop()
                    print(f"{who}: error: {_cannot_start(run, name)}", file=sys.stderr)
                    return 2
                if p.exitcode not in (0, EXIT_STALE_CHECKPOINT) and run.restarts.get(name, 0) < cfg.max_restarts:
                    # Actors hold no state that matters: start a fresh one (new incarnation). The
                    # buffer and the learner come back from their latest checkpoints. The router
                    # holds none: it comes back on the same endpoint, and every session reconnects
                    # and declares its subscribers, queryables and tokens again by itself.
                    run.restarts[name] = run.restarts.get(name, 0) + 1
                    display.say(f"{who}: {name} exited with code {p.exitcode}; restarting it "
                                f"({run.restarts[name]}/{cfg.max_restarts})")
                    role, acfg = run.specs[name]
                    if role in ("buffer", "learner"):
                        acfg = Config(**acfg.to_dict() | {"resume": True})
                    else:  # a new seed, or the restarted actor replays its predecessor's episodes
                        acfg = Config(**acfg.to_dict() | {"seed": seeds.restarted(acfg.seed)})
                    run.start(role, acfg, name)
                    continue
                if p.exitcode == 0 and name != "learner":
                    # The learner's shutdown message ends the others first; give it time to exit too.
                    clean_exit_seen.setdefault(name, time.monotonic())
                    if time.monotonic() - clean_exit_seen[name] < STOP_GRACE_S:
                        continue
                display.stop()
                run.failed_log = run.log(name)
                print(f"{who}: {name} exited with code {p.exitcode}; last lines of {run.log(name)}:\n"
                      f"{_tail(run.log(name))}", file=sys.stderr)
                return 1
            time.sleep(0.25)


def child_main() -> None:
    """A child of `LocalRun`: `python -c ... ROLE LOG_PATH`, its configuration as JSON on standard input."""
    component_main(sys.argv[1], json.loads(sys.stdin.read()), sys.argv[2])
