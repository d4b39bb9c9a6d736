"""A Zenoh router in a Python session: the rendezvous point of a run (no zenohd needed)."""

from __future__ import annotations

import logging

from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, router_config

log = logging.getLogger("router")


def run_router(listen: list[str], connect: list[str], zenoh_config: str, stop: StopFlag) -> int:
    with open_session(router_config(listen, connect, zenoh_config)) as session:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
        while not stop.wait(1.0):
            pass
        log.info("router stopping (%s)", stop.reason)
    return 0
