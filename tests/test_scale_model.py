"""The many-actor model (`silcr bench model`, docs/scaling.md): its sums, its fit, and the check
against the committed 128-actor measurement."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from silcr.bench.scale_model import Calibration, Deployment, calibrate, predict, reproduce, top_m_recall
from tests.helpers import REPO

RECORDS = REPO / "results" / "bench-scale" / "scale-paced-after.json"
# The stated error of the model at the largest measured count (docs/scaling.md).
# Relative, but transitions per second: the rate limiter's slack, 2 x --spi-tolerance (2,000) / the 60 s window.
TOLERANCE = {"weights_fanout_mb_per_s": 0.1, "buffer_cpu_cores": 0.5, "router_cpu_cores": 0.25,
             "weights_latency_ms_p50": 0.25, "actor_rss_mb_median": 0.05}
TRANSITIONS_SLACK = 2 * 2_000 / 60

CALIB = Calibration(router_cpu_s_per_mb=0.002, buffer_cpu_base_cores=0.01, buffer_cpu_s_per_transition=2e-5, episode_bytes_per_transition=1500.0,
                    actor_rss_mb=90.0, latency_ms_base=20.0, latency_ms_per_mb_queued=3.0)


def _monte_carlo_recall(m: int, k: int, rounds: int = 3000) -> float:
    rng = np.random.default_rng(0)
    kept = 0
    for _ in range(rounds):
        counts = np.bincount(rng.integers(0, k, m), minlength=k)
        kept += np.minimum(counts, m // k).sum()
    return kept / rounds / m


@pytest.mark.parametrize("m,k", [(50, 2), (50, 8), (1000, 32)])
def test_top_m_recall_matches_a_simulation_of_random_shards(m, k):
    assert top_m_recall(m, k) == pytest.approx(_monte_carlo_recall(m, k), abs=0.01)
    assert top_m_recall(m, 1) == 1.0 and top_m_recall(m, 2 * k) < top_m_recall(m, k)


def test_the_budget_caps_the_fanout_and_relays_cut_the_learners_traffic():
    d = Deployment(actors=10_000, hosts=10_000 // 32, learner_updates_per_s=230, weights_mb=1.33)
    one_router = predict(d, CALIB)
    assert one_router["weights_fanout_mb_per_s"] == pytest.approx(100.0)  # the budget, counted over actors
    assert one_router["weights_interval_s"] == pytest.approx(10_000 * 1.33 / 100)
    hosts = predict(dataclasses.replace(d, topology="host-routers", budget_counts="copies"), CALIB)
    assert hosts["learner_out_mb_per_s"] == pytest.approx(d.hosts * 1.33 * hosts["weights_publications_per_s"])
    assert hosts["weights_interval_s"] == pytest.approx(d.hosts * 1.33 / 100)  # copies to hosts, not actors
    tree = predict(dataclasses.replace(d, topology="host-routers", budget_counts="copies", tree_fanout=32), CALIB)
    assert tree["relay_levels"] == 3 and tree["weights_interval_s"] == pytest.approx(32 * 1.33 / 100)
    assert tree["weights_latency_ms_p50"] < hosts["weights_latency_ms_p50"] < one_router["weights_latency_ms_p50"]
    small = predict(dataclasses.replace(d, actors=8, hosts=1), CALIB)
    assert small["weights_publications_per_s"] == pytest.approx(230 / 50)  # the learner's own pace
    peers = predict(dataclasses.replace(d, topology="peers"), CALIB)
    assert peers["zenoh_links"] > 4e7 and one_router["zenoh_links"] == 10_003
    sharded = predict(dataclasses.replace(d, buffer_shards=8, throttled=False), CALIB)
    assert sharded["buffer_cpu_cores"] == pytest.approx(0.01 + 10_000 * 1000 * 2e-5 / 8)


def test_the_fit_recovers_the_costs_that_made_the_measurements():
    rows = []
    for n in (8, 32, 128):
        p = predict(Deployment(actors=n, learner_updates_per_s=20 + n / 4, weights_mb=0.66), CALIB)
        rows.append(p | {"window_s": 60.0, "actor_rss_mb_median": 90.0})
    fitted = calibrate(rows, 0.66, buffer_s_per_transition=2e-5)
    for field in ("router_cpu_s_per_mb", "buffer_cpu_base_cores", "episode_bytes_per_transition",
                  "latency_ms_base", "latency_ms_per_mb_queued"):
        assert getattr(fitted, field) == pytest.approx(getattr(CALIB, field), rel=1e-6), field


def test_the_model_reproduces_the_128_actor_measurement():
    """Fitted on 8 and 32 actors, it predicts the measured 128 within the error docs/scaling.md states."""
    data = json.loads(RECORDS.read_text())
    weights_mb = data["results"][0]["weights_bytes"] / 1e6
    calib, pairs = reproduce(data["results"], weights_mb, data["train_args"])
    assert calib.fitted_on == (8, 32)
    for key, (measured, predicted) in pairs.items():
        bound = TRANSITIONS_SLACK if key == "transitions_per_s" else TOLERANCE[key] * measured
        assert abs(predicted - measured) <= bound, (key, measured, predicted)


def test_the_command_checks_and_refuses_unusable_records(tmp_path):
    ok = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "model", "--records", str(RECORDS),
                         "--out", str(tmp_path)], capture_output=True, text=True, cwd=REPO, timeout=120)
    assert ok.returncode == 0, ok.stderr
    out = json.loads((tmp_path / "model.json").read_text())
    assert {p["actors"] for p in out["predictions"]} == {1_000, 10_000}
    unthrottled = REPO / "results" / "bench-scale" / "scale.json"
    for bad, word in ((tmp_path / "missing.json", "cannot read"), (unthrottled, "unthrottled")):
        r = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "model", "--records", str(bad)],
                           capture_output=True, text=True, cwd=REPO, timeout=60)
        assert r.returncode == 2 and word in r.stderr and "Traceback" not in r.stderr
