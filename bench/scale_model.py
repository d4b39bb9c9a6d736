"""`silcr bench model`: what a run needs at 1,000 and 10,000 actors, from costs measured by `silcr bench scale`.

An analytic model (issue 20, docs/scaling.md). `calibrate` fits a few unit costs on the
smaller counts of a `silcr bench scale --paced` record (the router's CPU per MB it relays,
the buffer's base load, bytes per transition, an actor's memory, the weights' latency as a
base plus a time per MB the relay sends ahead of the median actor; the buffer's CPU per
transition comes from the buffer benchmark instead);
`predict` combines them with a deployment (actors, hosts, topology, buffer shards, the
learner's update rate) into the quantities the bench measures. The largest measured count
is left out of the fit and reproduced, so the record itself says how far to trust the model;
`silcr bench model` prints that check and the predictions.

What the model leaves out, on purpose: the learner's update rate is an input (measured, or
what a GPU gives), not derived from the CPU left to it; the scheduler's sharing of one
machine's cores is not simulated, only each component's demand, which says where a machine
runs out. Known to be missing (docs/scaling.md): a cost per message (stats and liveliness
through the hub's router), which the 4-host measurement shows.
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from .timing import print_table

TOPOLOGIES = ("peers", "router", "host-routers")
# The buffer's CPU per transition it takes in: one buffer process inserted 486,000 Hopper
# transitions/s sent over Zenoh (docs/performance.md, "Buffer"). The paced runs of `bench
# scale` send the buffer a few dozen a second, too few to fit this cost on; they fit the
# buffer's base load (stats, liveliness, batches) instead.
BUFFER_S_PER_TRANSITION = 1 / 486_000


class RecordsError(ValueError):
    """Records the model cannot use (missing, not JSON, too few measured counts)."""


@dataclasses.dataclass(frozen=True)
class Calibration:
    """Unit costs, fitted on measured counts."""
    router_cpu_s_per_mb: float  # the router's CPU per MB it relays (weights out, episodes in)
    buffer_cpu_base_cores: float  # the buffer's load with few transitions (stats, liveliness, serving batches)
    buffer_cpu_s_per_transition: float  # decoding, storing and ranking, per transition received
    episode_bytes_per_transition: float
    actor_rss_mb: float
    latency_ms_base: float  # the weights' publication-to-use time with no relay queue (polling, decoding)
    latency_ms_per_mb_queued: float  # per MB the relay sends ahead of the median actor's copy
    fitted_on: tuple[int, ...] = ()


@dataclasses.dataclass(frozen=True)
class Deployment:
    actors: int
    learner_updates_per_s: float
    weights_mb: float  # one publication (Hopper 800-400: 1.33 float32, 0.66 float16)
    hosts: int = 1
    topology: str = "router"  # peers: every actor linked to every component; router: clients of one router;
    # host-routers: clients of a router on their host, which takes one copy of the weights per publication
    buffer_shards: int = 1
    weights_interval: int = 50
    fanout_budget_mb_s: float = 100.0  # --weights-fanout-mb-s; 0: none
    budget_counts: str = "actors"  # what the budget multiplies a publication by: "actors" (as built), or
    # "copies": the copies the learner's own router sends (hosts, or tree_fanout with a relay tree)
    tree_fanout: int = 0  # host-routers: 0 links every host's router to the hub; F > 0 relays through a tree
    # in which no router sends more than F copies (racks, then hosts)
    samples_per_insert: float = 1.0
    throttled: bool = True
    actor_steps_per_s: float = 1000.0  # one unthrottled actor (used when throttled is False)

    def __post_init__(self) -> None:
        if self.topology not in TOPOLOGIES:
            raise ValueError(f"topology must be one of {TOPOLOGIES}, got {self.topology!r}")


def calibrate(results: list[dict[str, Any]], weights_mb: float,
              buffer_s_per_transition: float = BUFFER_S_PER_TRANSITION) -> Calibration:
    """Unit costs from measured counts (records of `silcr bench scale --paced` with router-relayed actors)."""
    rows = [r for r in results if "window_s" in r]
    if not rows:
        raise RecordsError("no measured count in the records (every count refused or starved)")
    relayed_mb = np.array([r["weights_fanout_mb_per_s"] + r["episodes_mb_per_s"] for r in rows])
    router = np.array([r["router_cpu_cores"] for r in rows])
    transitions = np.array([r["transitions_per_s"] for r in rows])
    buffer = np.array([r["buffer_cpu_cores"] for r in rows])
    # Latency: the median actor gets its copy after the relay has sent half the actors theirs.
    queued_mb = np.array([r["actors"] / 2 * weights_mb for r in rows])
    latency = np.array([r["weights_latency_ms_p50"] for r in rows])
    if len(rows) >= 2 and np.ptp(queued_mb) > 0:
        slope, base = np.polyfit(queued_mb, latency, 1)
        slope, base = max(float(slope), 0.0), max(float(base), 0.0)
    else:
        slope, base = 0.0, float(latency.mean())
    return Calibration(
        router_cpu_s_per_mb=float(router.sum() / max(relayed_mb.sum(), 1e-9)),
        buffer_cpu_base_cores=max(0.0, float(np.mean(buffer - transitions * buffer_s_per_transition))),
        buffer_cpu_s_per_transition=buffer_s_per_transition,
        episode_bytes_per_transition=float(sum(r["episodes_mb_per_s"] for r in rows) * 1e6 / max(transitions.sum(), 1e-9)),
        actor_rss_mb=float(np.median([r["actor_rss_mb_median"] for r in rows])),
        latency_ms_base=base,
        latency_ms_per_mb_queued=slope,
        fitted_on=tuple(r["actors"] for r in rows),
    )


def predict(d: Deployment, c: Calibration) -> dict[str, Any]:
    """The quantities `silcr bench scale` measures, and what breaks, for one deployment."""
    per_host = math.ceil(d.actors / d.hosts)
    # Copies of each publication the hub (the learner's side) sends, and relay levels below it.
    if d.topology == "peers" or d.topology == "router":
        hub_copies, levels = (d.actors, 1) if d.topology == "peers" else (1, 1)
    elif d.tree_fanout and d.hosts > d.tree_fanout:
        hub_copies, levels = d.tree_fanout, 1 + math.ceil(math.log(d.hosts) / math.log(d.tree_fanout))
    else:
        hub_copies, levels = d.hosts, 2
    # Publications: the learner's cadence, paced by the fan-out budget.
    copies_counted = d.actors if d.budget_counts == "actors" else (d.actors if d.topology == "router" else hub_copies)
    pubs = d.learner_updates_per_s / d.weights_interval
    if d.fanout_budget_mb_s > 0:
        pubs = min(pubs, d.fanout_budget_mb_s / (copies_counted * d.weights_mb))
    to_actors_mb = d.actors * d.weights_mb * pubs  # every actor gets every publication
    # Data: paced by the learner (samples per insert), or what the actors make flat out.
    transitions = (d.learner_updates_per_s / d.samples_per_insert if d.throttled
                   else d.actors * d.actor_steps_per_s)
    episodes_mb = transitions * c.episode_bytes_per_transition / 1e6
    # Who sends the weights' copies: the learner itself (peers), the one router, or each host's router.
    learner_out_mb = {"peers": to_actors_mb, "router": d.weights_mb * pubs,
                      "host-routers": hub_copies * d.weights_mb * pubs}[d.topology]
    central_router_mb = {"peers": 0.0, "router": to_actors_mb + episodes_mb,
                         "host-routers": hub_copies * d.weights_mb * pubs + episodes_mb}[d.topology]
    host_router_mb = (per_host * d.weights_mb * pubs + episodes_mb / d.hosts) if d.topology == "host-routers" else 0.0
    # The median actor waits while each relay on its way sends half its copies ahead of it.
    if d.topology == "host-routers":
        queued = (hub_copies + (levels - 2) * (d.tree_fanout or 0) + per_host) / 2
    else:
        queued = d.actors / 2
    latency_ms = c.latency_ms_base + c.latency_ms_per_mb_queued * queued * d.weights_mb
    links = {"peers": d.actors * (d.actors - 1) // 2 + 3 * d.actors, "router": d.actors + 3,
             "host-routers": d.actors + 2 * d.hosts + 3}[d.topology]
    buffer_cores = c.buffer_cpu_base_cores + transitions * c.buffer_cpu_s_per_transition / d.buffer_shards
    return {
        "actors": d.actors, "hosts": d.hosts, "topology": d.topology, "buffer_shards": d.buffer_shards,
        "relay_levels": levels,
        "weights_publications_per_s": pubs,
        "weights_interval_s": 1 / pubs if pubs > 0 else math.inf,
        "weights_fanout_mb_per_s": to_actors_mb,
        "learner_out_mb_per_s": learner_out_mb,
        "weights_latency_ms_p50": latency_ms,
        "transitions_per_s": transitions,
        "episodes_mb_per_s": episodes_mb,
        "router_cpu_cores": central_router_mb * c.router_cpu_s_per_mb,
        "host_router_cpu_cores": host_router_mb * c.router_cpu_s_per_mb,
        "buffer_cpu_cores": buffer_cores,
        "actor_rss_gb_per_host": per_host * c.actor_rss_mb / 1024,
        "zenoh_links": links,
        # Only when paced: how busy the actors are (the learner's demand over what they could make).
        "actor_utilisation": (min(1.0, transitions / (d.actors * d.actor_steps_per_s)) if d.throttled else 1.0),
    }


def top_m_recall(expert_capacity_episodes: int, shards: int) -> float:
    """The share of the global top M episodes that K shards keep when each keeps its own top M/K,
    with episodes spread over shards at random: shard j holds X_j ~ Binomial(M, 1/K) of the global
    top M and keeps min(X_j, M/K) of them (its next best fill the rest of its share)."""
    m, k = expert_capacity_episodes, shards
    if k == 1:
        return 1.0
    share = m // k
    x = np.arange(m + 1)
    log_pmf = (math.lgamma(m + 1) - np.array([math.lgamma(i + 1) + math.lgamma(m - i + 1) for i in x])
               + x * math.log(1 / k) + (m - x) * math.log(1 - 1 / k))
    return float(k * (np.exp(log_pmf) * np.minimum(x, share)).sum() / m)


def reproduce(results: list[dict[str, Any]], weights_mb: float, train_args: list[str]) -> tuple[Calibration, dict[str, Any]]:
    """Fit on all counts but the largest, predict the largest: (calibration, {quantity: (measured, predicted)}).

    Paced, the buffer takes in the learner's updates / samples-per-insert in the long run; in a
    window the rate limiter lets the actors be up to --spi-tolerance updates ahead or behind, so
    a window's transitions per second may differ from it by 2 x tolerance / window."""
    rows = sorted((r for r in results if "window_s" in r), key=lambda r: r["actors"])
    if len(rows) < 3:
        raise RecordsError("the check needs three measured counts: two to fit, the largest to reproduce")
    calib = calibrate(rows[:-1], weights_mb)
    top = rows[-1]
    budget = _option(train_args, "--weights-fanout-mb-s", 100.0)
    pred = predict(Deployment(actors=top["actors"], learner_updates_per_s=top["learner_updates_per_s"],
                              weights_mb=weights_mb, fanout_budget_mb_s=budget), calib)
    keys = ["weights_fanout_mb_per_s", "weights_latency_ms_p50", "transitions_per_s", "router_cpu_cores",
            "buffer_cpu_cores"]
    pairs = {k: (top[k], pred[k]) for k in keys}
    pairs["actor_rss_mb_median"] = (top["actor_rss_mb_median"], calib.actor_rss_mb)
    return calib, pairs


def _option(args: list[str], name: str, default: float) -> float:
    for i, a in enumerate(args):
        if a == name and i + 1 < len(args):
            return float(args[i + 1])
    return default


def run(records: Path, out_dir: Path, learner_updates_per_s: float = 230.0) -> dict[str, Any]:
    """Check the model against the record's largest count, then predict 1,000 and 10,000 actors."""
    try:
        data = json.loads(records.read_text())
        train_args, results = data.get("train_args", []), data["results"]
        if not data.get("paced"):
            raise RecordsError(f"{records} was measured with the actors unthrottled; the model is calibrated "
                               "on `silcr bench scale --paced` records")
    except (OSError, ValueError, KeyError, AttributeError) as e:
        if isinstance(e, RecordsError):
            raise
        raise RecordsError(f"cannot read {records} as `silcr bench scale` records: {e}") from None
    measured = [r for r in results if "window_s" in r]
    if not measured:
        raise RecordsError(f"{records} holds no measured count (every count refused or starved)")
    weights_mb = measured[0]["weights_bytes"] / 1e6
    try:
        calib, pairs = reproduce(results, weights_mb, train_args)
    except KeyError as e:
        raise RecordsError(f"{records} lacks {e} (recorded by an older `silcr bench scale`)") from None
    print_table(f"model: fitted on {', '.join(map(str, calib.fitted_on))} actors, reproducing "
                f"{max(r['actors'] for r in results if 'window_s' in r)} ({records.name})",
                ["quantity", "measured", "predicted", "error"],
                [[k, m, p, f"{(p - m) / m:+.0%}" if m else "-"] for k, (m, p) in pairs.items()])
    slack = 2 * _option(train_args, "--spi-tolerance", 2_000.0) / data.get("window_s", 60.0)
    print(f"transitions_per_s: the model gives the long-run rate (updates / samples per insert); the rate "
          f"limiter lets a {data.get('window_s', 60.0):.0f} s window differ from it by up to {slack:.0f}/s "
          f"(2 x --spi-tolerance / window)")
    rows = []
    for actors in (1_000, 10_000):
        hosts = actors // 32
        for topology, shards, counts, fanout, paced in (
                ("router", 1, "actors", 0, True), ("host-routers", 1, "actors", 0, True),
                ("host-routers", 1, "copies", 0, True), ("host-routers", 1, "copies", 32, True),
                ("host-routers", 8, "copies", 32, False)):
            d = Deployment(actors=actors, hosts=hosts if topology == "host-routers" else 1, topology=topology,
                           buffer_shards=shards, budget_counts=counts, tree_fanout=fanout, weights_mb=weights_mb,
                           learner_updates_per_s=learner_updates_per_s, throttled=paced)
            rows.append(predict(d, calib) | {"budget_counts": counts, "tree_fanout": fanout, "paced": paced})
    shown = ["weights_interval_s", "learner_out_mb_per_s", "weights_latency_ms_p50", "router_cpu_cores",
             "host_router_cpu_cores", "transitions_per_s", "episodes_mb_per_s", "buffer_cpu_cores",
             "actor_utilisation", "zenoh_links"]
    layouts = ["1 router", "host routers (budget as built)", "host routers", "host + rack routers",
               "host + rack, unthrottled, 8 shards"]
    for actors in (1_000, 10_000):
        mine = [r for r in rows if r["actors"] == actors]
        print_table(f"model: {actors:,} actors, 32 per host; learner {learner_updates_per_s:.0f} updates/s, "
                    f"weights {weights_mb:.2f} MB, fan-out budget counting copies unless said",
                    ["quantity", *layouts],
                    [[k, *[f"{r[k]:.1e}" if k == "actor_utilisation" else r[k] for r in mine]] for k in shown])
    out = {"records": str(records), "calibration": dataclasses.asdict(calib),
           "check": {k: {"measured": m, "predicted": p} for k, (m, p) in pairs.items()}, "predictions": rows,
           "top_m_recall": {f"M={m} episodes, {k} shards": top_m_recall(m, k) for m in (50, 1000) for k in (2, 8, 32)}}
    print("D_E split over shards, each keeping its own best M/K: share of the global best M kept: "
          + ", ".join(f"{k}: {v:.3f}" for k, v in out["top_m_recall"].items()))
    out_dir.mkdir(parents=True, exist_ok=True)
    (out_dir / "model.json").write_text(json.dumps(out, indent=2))
    return out
