"""The learner process over Zenoh: the transport loop around `Learner`.

A `ZenohBatchStream` keeps several sample queries in flight (not-ready replies,
retries and buffer restarts are handled there); each reply trains the learner,
whose weights go out through a `ZenohWeightsServer`; stats go on the learner's
stats key. The run ends when the budget is spent (the learner announces it) or on stop.
"""

from __future__ import annotations

import dataclasses
import logging
import time

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.control_channel import Shutdown
from silcr.common.lifecycle import EXIT_CANNOT_START, EXIT_STALE_CHECKPOINT, StopFlag, ignore_stop_signals
from silcr.common.role_session import role_session
from silcr.common.sample_channel import ZenohBatchStream
from silcr.common.weights_channel import ZenohWeightsServer

from .checkpoint import CheckpointError
from .learner import Learner

log = logging.getLogger("learner")


def run_learner(cfg: Config, stop: StopFlag) -> int:
    with role_session(cfg, stop, "learner") as role:
        shutdown = Shutdown(role.session, role.keys)
        try:
            lrn = Learner(cfg, role.spec, ZenohWeightsServer(role.session, role.keys, cfg.weights_fanout_mb_s * 1e6))
        except CheckpointError as e:
            log.error("cannot start: %s", e)
            return EXIT_CANNOT_START
        log.info("learner for run %s on %s: %s, networks %s, batch %d, %d env steps",
                 cfg.run, lrn.update.device, cfg.algo, cfg.hidden, cfg.batch_size, cfg.total_steps)
        # The requests name the learner's incarnation (as its weights do): the buffer serves only a live learner.
        request = dataclasses.replace(lrn.update.sample_request(), learner=lrn.books.incarnation)
        stream = ZenohBatchStream(role.session, role.keys, request, cfg.requests_in_flight, stop,
                                  updates_before=lrn.books.updates)
        lrn.books.start()
        stream.wait_for_buffer()
        finished = False
        mismatch: P.BufferMismatch | None = None
        for batch in stream:
            try:
                if batch is not None:
                    lrn.step(batch)
                else:
                    lrn.books.see(stream.last_reply)
            except P.BufferMismatch as e:
                log.error("%s", e)
                mismatch = e
                break
            lrn.books.poll()
            if role.stats_due.due():
                stats = lrn.books.stats() | stream.stats()
                role.stats.put(stats)
                lrn.books.record_scalars(stats)
            if lrn.books.done(starved=stream.rate_limited):
                finished = True
                break
        written = lrn.books.finish(finished)
        books = lrn.books
        role.stats.put({"time": time.time(), "updates": books.updates, "policy_version": books.policy_version,
                        "env_steps": books.env_steps, "last_eval_return": books.evaluations.last_eval_return, "finished": finished})
        if finished:
            # Everything is on disk: a stop signal now (compose's --abort-on-container-exit stops every container
            # once one ends) must not turn a completed run's exit 0 into a death by signal.
            ignore_stop_signals()
            shutdown.announce(P.ShutdownNotice.FINISHED)
        else:
            log.info("stopping (%s) at %d updates", stop.reason, books.updates)
    if mismatch:
        return 1
    return 0 if written else EXIT_STALE_CHECKPOINT
