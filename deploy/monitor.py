"""`silcr monitor`: read a running system's stats topics and show them.

On a terminal, a live table; without one (a container's log, a pipe), one plain line per
`--interval` seconds. Either way it ends with one line when the run finishes.

It uses nothing but Zenoh and JSON, so it doubles as an example of an outside
client of the stats contract (docs/protocol.md).
"""

from __future__ import annotations

import json
import os
import sys
import threading
import time
from typing import Any

from silcr.common import protocol as P
from silcr.common.control_channel import stop_on_shutdown
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, session_config


class StatsSnapshot:
    """Latest stats message per component, filled from a Zenoh callback."""

    def __init__(self, keys: P.Keys) -> None:
        self.keys = keys
        self._lock = threading.Lock()
        self.buffer: dict[str, Any] | None = None
        self.learner: dict[str, Any] | None = None
        self.actors: dict[str, dict[str, Any]] = {}
        self.malformed = 0

    def on_sample(self, sample: Any) -> None:
        key = str(sample.key_expr)
        try:
            data = P.Stats.decode(sample.payload.to_bytes()).values
        except P.ProtocolError:
            with self._lock:
                self.malformed += 1
            return
        with self._lock:
            if key == self.keys.stats_buffer:
                self.buffer = data
            elif key == self.keys.stats_learner:
                self.learner = data
            elif key.startswith(self.keys.prefix + "/stats/actor/"):
                self.actors[key.rsplit("/", 1)[-1]] = data

    def get(self, key: str) -> dict[str, Any]:
        """The latest message on one stats key (`keys.stats_buffer`, `keys.stats_actor(i)`, ...), or {}."""
        with self._lock:
            if key == self.keys.stats_buffer:
                return dict(self.buffer or {})
            if key == self.keys.stats_learner:
                return dict(self.learner or {})
            return dict(self.actors.get(key.rsplit("/", 1)[-1], {}))

    def as_dict(self) -> dict[str, Any]:
        with self._lock:
            return {"run": self.keys.run, "buffer": self.buffer, "learner": self.learner, "actors": dict(self.actors)}


def _table(snap: dict[str, Any]):
    from rich.table import Table

    t = Table(title=f"silcr run {snap['run']}", show_lines=False)
    t.add_column("component")
    t.add_column("field")
    t.add_column("value", justify="right")
    b = snap["buffer"] or {}
    for k in ("transitions_received", "episodes_received", "episodes_rejected", "online_transitions", "expert_transitions",
              "expert_episodes", "expert_min_return", "expert_max_return", "rollout_return", "rollout_length",
              "batches_served", "samples_per_insert",
              "actors_alive", "actors_paused"):
        if k in b:
            t.add_row("buffer", k, _fmt(b[k]))
    lr = snap["learner"] or {}
    for k in ("env_steps", "updates", "policy_version", "last_eval_return", "updates_per_s", "duty_cycle", "batch_wait_ms_p99", "alpha",
              "q_mean", "q_max", "q_bound", "q_bound_exceeded", "disc_loss", "disc_acc_expert", "disc_acc_policy",
              "gasil_reward_mean"):
        if k in lr:
            t.add_row("learner", k, _fmt(lr[k]))
    for aid, a in sorted(snap["actors"].items()):
        t.add_row(f"actor {aid}", "episodes / steps / version", f"{a.get('episodes')} / {a.get('steps')} / {a.get('policy_version')}")
        if a.get("waiting_for_buffer") or a.get("paused"):
            t.add_row(f"actor {aid}", "state", "waiting for the buffer" if a.get("waiting_for_buffer") else "paused")
    return t


def plain_line(snap: dict[str, Any]) -> str:
    """One line of the run's key figures: what `silcr monitor` prints per interval where there is no terminal
    (`docker compose logs -f monitor`, `kubectl logs`)."""
    b, lr, actors = snap["buffer"] or {}, snap["learner"] or {}, snap["actors"]
    parts = [f"run {snap['run']}"]
    if lr:
        total = lr.get("total_steps")
        parts.append(f"learner: env_steps {lr.get('env_steps')}" + (f"/{total}" if total else "")
                     + f" updates {lr.get('updates')} updates_per_s {_fmt(lr.get('updates_per_s'))}"
                     + f" last_eval_return {_fmt(lr.get('last_eval_return'))}")
    if b:
        parts.append(f"buffer: transitions_received {b.get('transitions_received')} episodes_received "
                     f"{b.get('episodes_received')} expert_transitions {b.get('expert_transitions')} expert_min_return "
                     f"{_fmt(b.get('expert_min_return'))} expert_max_return {_fmt(b.get('expert_max_return'))} "
                     f"actors_alive {b.get('actors_alive')} actors_paused {b.get('actors_paused')}")
    if actors:
        parts.append(f"actors: {len(actors)} reporting, steps {sum(int(a.get('steps') or 0) for a in actors.values())}, "
                     f"episodes {sum(int(a.get('episodes') or 0) for a in actors.values())}")
    if len(parts) == 1:
        parts.append("no stats yet")
    return " | ".join(parts)


def finished_line(snap: dict[str, Any]) -> str:
    lr = snap["learner"] or {}
    return (f"run {snap['run']} finished at {lr.get('env_steps')} env steps, {lr.get('updates')} updates; last "
            f"evaluation {_fmt(lr.get('last_eval_return'))}")


def _fmt(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:,.3f}" if abs(v) < 100 else f"{v:,.1f}"
    return str(v)


def run_monitor(run: str, connect: list[str], mode: str, zenoh_config: str, once: bool, as_json: bool, timeout: float,
                stop: StopFlag, interval: float = 10.0) -> int:
    """Show run `run`'s stats: once, as a live table on a terminal, or as one plain line every `interval` seconds
    elsewhere; a live monitor ends, with one closing line, when the run finishes."""
    keys = P.Keys(run)
    snap = StatsSnapshot(keys)
    out = sys.stdout
    if once and as_json:
        # Zenoh's own log lines (its Rust logger) go to file descriptor 1, and one printed while
        # the session runs would break the JSON: they go to stderr, the JSON alone to stdout.
        sys.stdout.flush()
        out = os.fdopen(os.dup(1), "w")
        os.dup2(2, 1)
    with open_session(session_config(connect, [], mode, zenoh_config)) as session:
        session.declare_subscriber(keys.stats_all, snap.on_sample)
        if once:
            deadline = time.monotonic() + timeout
            # Stats arrive about once a second; wait for the buffer and the learner, or the deadline.
            while time.monotonic() < deadline and not stop.is_set():
                s = snap.as_dict()
                if s["buffer"] is not None and s["learner"] is not None:
                    break
                stop.wait(0.1)
            s = snap.as_dict()
            if s["buffer"] is None and s["learner"] is None and not s["actors"]:
                print(f"silcr monitor: no stats from run {run!r} within {timeout:g}s (is it running, and is --connect right?)",
                      file=sys.stderr)
                return 1
            if as_json:
                print(json.dumps(s, indent=2), file=out, flush=True)
            else:
                from rich.console import Console

                Console().print(_table(s))
            return 0
        # The run's end: the learner's last stats say `finished`, and it announces the end on the shutdown key.
        ended = StopFlag()
        stop_on_shutdown(session, keys, ended)

        def over() -> bool:
            return ended.is_set() or bool((snap.as_dict()["learner"] or {}).get("finished"))

        if not out.isatty():  # a container's log: one plain line per interval, not a live table
            print(f"silcr monitor: run {run}, one line every {interval:g} s", file=out, flush=True)
            while not stop.is_set() and not over():
                if stop.wait(interval) or over():
                    break
                print(time.strftime("%H:%M:%S ") + plain_line(snap.as_dict()), file=out, flush=True)
        else:
            from rich.live import Live

            with Live(_table(snap.as_dict()), refresh_per_second=2) as live:
                while not stop.wait(1.0) and not over():
                    live.update(_table(snap.as_dict()))
        if over():
            stop.wait(1.5)  # the learner's last stats message may follow the announcement
            print(time.strftime("%H:%M:%S ") + finished_line(snap.as_dict()), file=out, flush=True)
    return 0
