"""A component's health, as a scheduler's probes ask for it (`silcr health`, Kubernetes' exec probes).

With `--health-file PATH` a component's main loop writes a heartbeat there every `--stats-interval`
(with its stats, so it stops when the loop does): the run, the role, the component's liveliness
token and the time. `silcr health` reads it:

* alive (the liveness probe): the heartbeat is younger than `--stale-after` seconds. The loop
  writes it, not a background thread, so a component stuck in its loop (a deadlock, a hung
  device) stops it, while a slow one (a long evaluation, a checkpoint of a big buffer) only
  delays it by less than the threshold: Kubernetes restarts a stuck component, not a slow one.
* ready (`--ready`, the readiness probe): alive, and the component's Zenoh liveliness token
  (`silcr/<run>/alive/<role>[/<id>]`) is visible through the router: it has joined the run.

The file is written to a temporary name and renamed, so a probe never reads half of it.
"""

from __future__ import annotations

import json
import os
import time
from pathlib import Path
from typing import Any

#: Where a component's heartbeat goes when the option names no other file (the image's /tmp).
DEFAULT_HEALTH_FILE = "/tmp/silcr-health.json"


class Heartbeat:
    def __init__(self, path: str | Path, run: str, role: str, token: str) -> None:
        self.path = Path(path)
        self._fixed = {"run": run, "role": role, "token": token, "pid": os.getpid()}

    def beat(self) -> None:
        """Write the heartbeat now; a failed write is not the component's failure (the probe will say so)."""
        tmp = self.path.with_name(self.path.name + ".tmp")
        try:
            tmp.write_text(json.dumps(self._fixed | {"time": time.time()}))
            tmp.replace(self.path)
        except OSError:
            pass


def read(path: str | Path) -> dict[str, Any]:
    """The heartbeat at `path`; ValueError naming what is wrong."""
    try:
        beat = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"no heartbeat at {path} yet (the component has not started its loop)") from None
    except (OSError, ValueError) as e:
        raise ValueError(f"unreadable heartbeat at {path} ({e})") from None
    if not isinstance(beat, dict) or not {"run", "role", "token", "time"} <= set(beat):
        raise ValueError(f"{path} is not a silcr heartbeat")
    return beat


def alive(path: str | Path, stale_after: float, now: float | None = None) -> str:
    """One line about the component if its heartbeat is fresh; ValueError saying why not."""
    beat = read(path)
    age = (time.time() if now is None else now) - float(beat["time"])
    if age > stale_after:
        raise ValueError(f"{beat['role']} of run {beat['run']}: last heartbeat {age:.0f}s ago, more than "
                         f"--stale-after {stale_after:g}s (stuck)")
    return f"{beat['role']} of run {beat['run']}: heartbeat {age:.1f}s ago"


def token_visible(session, token: str, timeout: float) -> bool:
    """Whether the liveliness token `token` is declared by someone reachable through `session`."""
    replies = session.liveliness().get(token, timeout=timeout)
    return any(r.ok is not None for r in replies)
