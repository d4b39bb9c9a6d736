"""A Zenoh router in a Python session: the rendezvous point of a run (no zenohd needed).

With `run`, it also follows that run: once the learner announces that the run finished, the router
waits `FINISHED_GRACE_S` for the other services to hear it and leave, then exits 0 (docker compose's
stack then ends by itself; a router shared by several runs is started without it).
"""

from __future__ import annotations

import logging

from silcr.common import protocol as P
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, router_config

log = logging.getLogger("router")

#: Seconds between a run's end and its router's: the announcement reaches every service through the router,
#: and the buffer writes its last checkpoint without it.
FINISHED_GRACE_S = 10.0


def run_router(listen: list[str], connect: list[str], zenoh_config: str, stop: StopFlag, run: str = "") -> int:
    with open_session(router_config(listen, connect, zenoh_config)) as session:
        log.info("zenoh router %s listening on %s%s", session.zid(), ", ".join(listen),
                 f"; following run {run}" if run else "")
        ended = StopFlag()
        if run:
            from silcr.common.control_channel import stop_on_shutdown

            stop_on_shutdown(session, P.Keys(run), ended)
        while not stop.wait(1.0):
            if ended.is_set():
                log.info("run %s ended (%s); stopping in %.0f s", run, ended.reason, FINISHED_GRACE_S)
                stop.wait(FINISHED_GRACE_S)
                break
        log.info("router stopping (%s)", stop.reason or ended.reason)
    return 0
