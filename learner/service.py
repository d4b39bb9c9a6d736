"""The learner: pull mixed batches, update SAC, push weights, evaluate, record, checkpoint.

Several sample queries stay in flight (each for `batches_per_request` batches),
so while one batch trains the next ones are already crossing the network. The
buffer's rate limiter decides when a batch may be taken; a `not_ready` reply
just means "wait a moment", never an error.
"""

from __future__ import annotations

import collections
import logging
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch
import zenoh

from silcr.common import protocol as P
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from silcr.common.lifecycle import StopFlag
from silcr.common.zenoh_session import open_session, session_config

from .checkpoint import load_checkpoint, save_checkpoint
from .evaluate import evaluate
from .progress import DIVERGENCE_COLUMNS, EXPERT_COLUMNS, ProgressLog
from .sac import Sac, SacHyper, as_floats

log = logging.getLogger("learner")

QUERY_TIMEOUT_S = 10.0


def pick_device(name: str) -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise ValueError("--device cuda: CUDA is not available on this machine")
    return torch.device(name)


class Learner:
    def __init__(self, cfg: Config, spec: EnvSpec) -> None:
        self.cfg, self.spec = cfg, spec
        self.device = pick_device(cfg.device)
        if cfg.torch_threads:
            torch.set_num_threads(cfg.torch_threads)
        torch.manual_seed(cfg.seed)
        hp = SacHyper(cfg.gamma, cfg.tau, cfg.lr, cfg.grad_clip, cfg.init_alpha, None, cfg.time_limit_terminal,
                      cfg.tanh_log_prob)
        self.sac = Sac(spec.obs_dim, spec.act_dim, cfg.hidden, hp, self.device)
        self.updates = 0
        self.policy_version = 0
        self.env_steps = 0
        self.next_eval = 0
        self.evals = 0
        self.last_eval_return: float | None = None
        self.checkpoint_path = cfg.run_dir / "checkpoints" / "learner.pt"
        # --resume continues from a checkpoint when there is one, so the same command
        # serves a first start and every restart (launcher, sweep, docker restart policy).
        self.resumed = cfg.resume and self.checkpoint_path.exists()
        if self.resumed:
            self._restore(load_checkpoint(self.checkpoint_path))
        elif cfg.resume:
            log.info("--resume: no checkpoint at %s yet; starting fresh", self.checkpoint_path)
        self._last_stats: dict[str, torch.Tensor] = {}

    # -- checkpoints -------------------------------------------------------------
    def counters(self) -> dict[str, Any]:
        return {
            "updates": self.updates,
            "policy_version": self.policy_version,
            "env_steps": self.env_steps,
            "next_eval": self.next_eval,
            "evals": self.evals,
            "last_eval_return": self.last_eval_return,
        }

    def _restore(self, payload: dict) -> None:
        if payload["sac"]["arch"] != self.sac.arch():
            raise ValueError(f"checkpoint networks {payload['sac']['arch']} do not match this run's {self.sac.arch()}")
        self.sac.load_state_dict(payload["sac"])
        c = payload["counters"]
        self.updates, self.policy_version, self.env_steps = c["updates"], c["policy_version"], c["env_steps"]
        self.next_eval, self.evals, self.last_eval_return = c["next_eval"], c["evals"], c["last_eval_return"]
        log.info("resumed from %s: %d updates, policy version %d", self.checkpoint_path, self.updates, self.policy_version)

    def checkpoint(self) -> None:
        t0 = time.monotonic()
        save_checkpoint(self.checkpoint_path, {"sac": self.sac.state_dict(), "counters": self.counters(), "config": self.cfg.to_dict()})
        log.info("checkpoint at %d updates written in %.2fs", self.updates, time.monotonic() - t0)

    # -- training ------------------------------------------------------------------
    def weights(self) -> P.Weights:
        return P.Weights(self.policy_version, self.sac.actor_arrays(), self.sac.arch(), sent_at=time.time())

    def train_on(self, arrays: dict[str, np.ndarray], batches: int, batch_size: int) -> None:
        dev = self.device
        t = {k: torch.from_numpy(np.ascontiguousarray(v)).to(dev, non_blocking=True) for k, v in arrays.items() if k != "policy_version"}
        term = t["terminated"].float()
        trunc = t["truncated"].float()
        for b in range(batches):
            s = slice(b * batch_size, (b + 1) * batch_size)
            self._last_stats = self.sac.update(t["obs"][s], t["actions"][s], t["rewards"][s], t["next_obs"][s], term[s], trunc[s])
            self.updates += 1

    @property
    def last_losses(self) -> dict[str, float]:
        """The last update's statistics and the divergence count; reading them waits for the device, so only when reporting."""
        out = as_floats(self._last_stats)
        out["q_bound_exceeded"] = int(self.sac.q_bound_exceeded)
        return out

    def target_updates(self) -> int:
        return int(max(0, self.cfg.total_steps - self.cfg.learning_starts) * self.cfg.samples_per_insert)


def run_learner(cfg: Config, stop: StopFlag) -> int:
    spec = EnvSpec.of(cfg.env)
    lrn = Learner(cfg, spec)
    keys = P.Keys(cfg.run)
    cfg.run_dir.mkdir(parents=True, exist_ok=True)
    progress = ProgressLog(cfg.run_dir, resume=lrn.resumed)
    log.info(
        "learner for run %s on %s: %s, networks %s, batch %d, %d env steps",
        cfg.run, lrn.device, cfg.algo, cfg.hidden, cfg.batch_size, cfg.total_steps,
    )
    request = P.SampleRequest(cfg.batches_per_request, cfg.batch_size).encode()
    conf = session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)
    finished = False
    start = time.monotonic()
    wait_times: collections.deque[float] = collections.deque(maxlen=2000)
    policy_lag: collections.deque[float] = collections.deque(maxlen=200)
    update_time = 0.0
    sample_errors = 0
    not_ready = 0
    buffer_meta: dict[str, Any] = {}  # the latest batch reply's description of the buffer (D_E's returns)
    with open_session(conf) as session:
        latest = {"payload": P.encode_weights(lrn.weights())}

        def answer_weights(query: zenoh.Query) -> None:
            with query:
                query.reply(keys.weights, latest["payload"])

        session.declare_queryable(keys.weights, answer_weights)
        session.declare_subscriber(keys.control_shutdown, lambda s: stop.set("shutdown message"))
        weights_pub = session.declare_publisher(
            keys.weights, congestion_control=zenoh.CongestionControl.BLOCK, priority=zenoh.Priority.DATA_HIGH
        )
        stats_pub = session.declare_publisher(
            keys.stats_learner,
            encoding=zenoh.Encoding.APPLICATION_JSON,
            congestion_control=zenoh.CongestionControl.DROP,
            priority=zenoh.Priority.DATA_LOW,
        )
        shutdown_pub = session.declare_publisher(keys.control_shutdown, congestion_control=zenoh.CongestionControl.BLOCK)
        token = session.liveliness().declare_token(keys.alive("learner"))
        querier = session.declare_querier(
            keys.sample, timeout=QUERY_TIMEOUT_S, consolidation=zenoh.ConsolidationMode.NONE
        )

        def publish_weights() -> None:
            latest["payload"] = P.encode_weights(lrn.weights())
            weights_pub.put(latest["payload"])

        def do_eval() -> None:
            if cfg.eval_episodes == 0:
                return
            t0 = time.monotonic()
            mean, std, length = evaluate(lrn.weights(), spec, cfg.eval_episodes, cfg.seed + 1_000_000 + 1_000 * lrn.evals)
            lrn.evals += 1
            lrn.last_eval_return = mean
            elapsed = time.monotonic() - start
            losses = lrn.last_losses
            progress.row(
                {
                    "time": round(elapsed, 3),
                    "env_steps": lrn.env_steps,
                    "updates": lrn.updates,
                    "policy_version": lrn.policy_version,
                    "eval_return": mean,
                    "eval_return_std": std,
                    "eval_length": length,
                    "alpha": lrn.sac.alpha,
                    "critic_loss": losses.get("critic_loss", float("nan")),
                    "actor_loss": losses.get("actor_loss", float("nan")),
                    "updates_per_s": lrn.updates / max(elapsed, 1e-9),
                    **{k: losses.get(k, float("nan")) for k in DIVERGENCE_COLUMNS},
                    **{k: buffer_meta.get(k) for k in EXPERT_COLUMNS},
                }
            )
            log.info(
                "eval at %d env steps, %d updates: return %.1f +- %.1f (length %.0f, %.1fs)",
                lrn.env_steps, lrn.updates, mean, std, length, time.monotonic() - t0,
            )

        publish_weights()
        if not lrn.resumed:
            do_eval()  # the untrained policy: the baseline every curve starts from
            lrn.next_eval = cfg.eval_interval

        waiting_logged = False
        while not querier.matching_status.matching and not stop.is_set():
            if not waiting_logged:
                log.info("waiting for the buffer service on %s", keys.sample)
                waiting_logged = True
            stop.wait(0.1)

        in_flight: collections.deque = collections.deque()
        next_stats = time.monotonic()
        next_checkpoint = (lrn.updates // cfg.checkpoint_interval + 1) * cfg.checkpoint_interval
        rate_limited_at_end = False
        last_buffer_steps, buffer_restarts, transitions_lost, last_error_log = 0, 0, 0, 0.0
        while not stop.is_set():
            while len(in_flight) < cfg.requests_in_flight:
                in_flight.append(querier.get(payload=request))
            t0 = time.monotonic()
            reply = next(iter(in_flight.popleft()), None)
            wait_times.append(time.monotonic() - t0)
            batch: P.BatchReply | None = None
            if reply is None or reply.ok is None:
                sample_errors += 1
                why = "no reply" if reply is None else reply.err.payload.to_string()
                if time.monotonic() - last_error_log > 10:  # the buffer may be down for a while: do not flood the log
                    log.warning("sample query failed (%s); retrying (%d failures so far)", why, sample_errors)
                    last_error_log = time.monotonic()
                stop.wait(0.5)
            else:
                try:
                    batch = P.BatchReply.decode(reply.ok.payload.to_bytes())
                except P.ProtocolError as e:
                    sample_errors += 1
                    log.warning("malformed batch reply: %s", e)
            if batch is not None:
                buffer_steps = int(batch.meta.get("env_steps", 0))
                if buffer_steps < last_buffer_steps:
                    # The buffer's counter never goes back unless it restarted from an older checkpoint.
                    buffer_restarts += 1
                    transitions_lost += last_buffer_steps - buffer_steps
                    log.warning("the buffer service restarted: %d transitions it had received since its last "
                                "checkpoint are lost (%d in all)", last_buffer_steps - buffer_steps, transitions_lost)
                last_buffer_steps = buffer_steps
                buffer_meta = batch.meta
                lrn.env_steps = max(lrn.env_steps, buffer_steps)
                if batch.status == "ok":
                    # Policy lag: how many weight versions behind the learner the sampled data is.
                    versions = batch.arrays["policy_version"]
                    policy_lag.append(float(lrn.policy_version - versions[versions >= 0].mean()) if (versions >= 0).any() else 0.0)
                    t1 = time.monotonic()
                    lrn.train_on(batch.arrays, int(batch.meta["batches"]), int(batch.meta["batch_size"]))
                    update_time += time.monotonic() - t1
                    rate_limited_at_end = False
                    if lrn.updates // cfg.weights_interval != (lrn.updates - int(batch.meta["batches"])) // cfg.weights_interval:
                        lrn.policy_version += 1
                        publish_weights()
                else:
                    not_ready += 1
                    rate_limited_at_end = batch.reason == "rate_limited" and lrn.env_steps >= cfg.total_steps
                    stop.wait(batch.retry_after_ms / 1000)
            if lrn.env_steps >= lrn.next_eval:
                do_eval()
                lrn.next_eval = (lrn.env_steps // cfg.eval_interval + 1) * cfg.eval_interval
            if lrn.updates >= next_checkpoint:
                lrn.checkpoint()
                next_checkpoint = (lrn.updates // cfg.checkpoint_interval + 1) * cfg.checkpoint_interval
            now = time.monotonic()
            if now >= next_stats:
                elapsed = now - start
                waits = np.asarray(wait_times) * 1000 if wait_times else np.zeros(1)
                stats = {
                    "time": time.time(),
                    "updates": lrn.updates,
                    "policy_version": lrn.policy_version,
                    "env_steps": lrn.env_steps,
                    "total_steps": cfg.total_steps,
                    "last_eval_return": lrn.last_eval_return,
                    "updates_per_s": lrn.updates / max(elapsed, 1e-9),
                    "duty_cycle": update_time / max(elapsed, 1e-9),
                    "batch_wait_ms_p50": float(np.percentile(waits, 50)),
                    "batch_wait_ms_p99": float(np.percentile(waits, 99)),
                    "not_ready_replies": not_ready,
                    "policy_lag_mean": float(np.mean(policy_lag)) if policy_lag else None,
                    "sample_errors": sample_errors,
                    "buffer_restarts": buffer_restarts,
                    "transitions_lost": transitions_lost,
                    "device": str(lrn.device),
                }
                losses = lrn.last_losses
                stats |= {k: P.finite_or_none(v) for k, v in losses.items()}
                stats["q_bound_exceeded"] = losses.get("q_bound_exceeded", 0)
                stats_pub.put(P.encode_stats(stats))
                if lrn.updates:
                    progress.scalars({f"train/{k}": v for k, v in losses.items()} | {"train/updates_per_s": stats["updates_per_s"]}, lrn.env_steps)
                next_stats = now + cfg.stats_interval
            if lrn.env_steps >= cfg.total_steps and (lrn.updates >= lrn.target_updates() or rate_limited_at_end):
                finished = True
                break

        if finished:
            lrn.policy_version += 1
            publish_weights()
            do_eval()
        lrn.checkpoint()
        stats_pub.put(P.encode_stats({"time": time.time(), "updates": lrn.updates, "policy_version": lrn.policy_version,
                                      "env_steps": lrn.env_steps, "last_eval_return": lrn.last_eval_return, "finished": finished}))
        if finished:
            log.info("finished: %d env steps, %d updates, last eval return %s", lrn.env_steps, lrn.updates, lrn.last_eval_return)
            shutdown_pub.put(P.encode_control("shutdown", reason="finished"))
        else:
            log.info("stopping (%s) at %d updates", stop.reason, lrn.updates)
        token.undeclare()
    progress.close()
    return 0
