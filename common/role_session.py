"""A role's process over Zenoh, set up in one place for the buffer, the learner and every actor.

`role_session` opens the session the options describe (`--connect`, `--listen`,
`--zenoh-mode`, `--zenoh-config`), stops the role when anyone announces the end of the
run, declares the role's liveliness token (`silcr/<run>/alive/<role>[/<id>]`) and its
stats publisher (every message carries `shutdown_rejections`: malformed shutdown
messages, ignored; with `--health-file`, each is followed by the heartbeat `silcr health`
reads: common/health.py), logs when the session loses its last link and regains one
(common/link_watch.py), and gives the role its stats schedule. On the way out it withdraws
the token, so the others see the role leave before its session closes.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import Iterator

import zenoh

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.control_channel import StatsPublisher, stop_on_shutdown
from silcr.common.envs import EnvSpec
from silcr.common.health import Heartbeat
from silcr.common.lifecycle import StopFlag
from silcr.common.link_watch import LinkWatch
from silcr.common.schedule import Every
from silcr.common.zenoh_session import open_session, session_config


@dataclass
class RoleSession:
    spec: EnvSpec
    keys: P.Keys
    session: zenoh.Session
    stats: StatsPublisher
    #: due every `--stats-interval` seconds, first at once
    stats_due: Every


@contextlib.contextmanager
def role_session(cfg: Config, stop: StopFlag, role: str, ident: int | None = None,
                 spec: EnvSpec | None = None) -> Iterator[RoleSession]:
    keys = P.Keys(cfg.run)
    spec = spec or EnvSpec.of(cfg.env)
    with open_session(session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)) as session:
        shutdown = stop_on_shutdown(session, keys, stop)
        token_key = keys.alive(role, ident)
        token = session.liveliness().declare_token(token_key)
        beat = Heartbeat(cfg.health_file, cfg.run, role, token_key).beat if cfg.health_file else None
        links = LinkWatch(session, stop, role if ident is None else f"{role} {ident}")
        try:
            yield RoleSession(spec, keys, session,
                              StatsPublisher(session, keys.stats(role, ident), shutdown.stats, on_put=beat),
                              Every(cfg.stats_interval))
        finally:
            links.close()
            token.undeclare()
