"""The benchmark suite compares like with like: the plain reference does the same maths as `Sac`."""

from __future__ import annotations

import pytest
import torch

from silcr.bench.reference_sac import PlainSac, random_batch, update_flops
from silcr.learner.sac import Sac, SacHyper


def _copy_into_plain(sac: Sac, plain: PlainSac) -> None:
    plain.actor.load_state_dict(sac.actor.state_dict())
    with torch.no_grad():
        for j, (q, qt) in enumerate(((plain.q1, plain.q1_t), (plain.q2, plain.q2_t))):
            for twin, dst in ((sac.critic, q), (sac.critic_target, qt)):
                linears = [m for m in dst.net.modules() if isinstance(m, torch.nn.Linear)]
                for lin, w, b in zip(linears, twin.weights, twin.biases):
                    lin.weight.copy_(w[j].T)
                    lin.bias.copy_(b[j, 0])


@pytest.mark.parametrize("rewards_scale", [1.0, 1e4])  # 1e4 makes gradient clipping bite
def test_optimised_update_equals_the_plain_reference(rewards_scale):
    torch.manual_seed(0)
    sac = Sac(5, 2, [32, 16], SacHyper(), torch.device("cpu"))
    plain = PlainSac(5, 2, [32, 16], torch.device("cpu"))
    _copy_into_plain(sac, plain)
    obs, act, rew, nxt, term, trunc = random_batch(5, 2, 64, torch.device("cpu"))
    rew = rew * rewards_scale
    for step in range(3):
        torch.manual_seed(100 + step)
        sac.update(obs, act, rew, nxt, term, trunc)
        torch.manual_seed(100 + step)
        plain.update(obs, act, rew, nxt, term, trunc)
    for (name, p), q in zip(sac.actor.state_dict().items(), plain.actor.state_dict().values()):
        torch.testing.assert_close(p, q, rtol=1e-4, atol=1e-5, msg=name)
    lin = [m for m in plain.q2.net.modules() if isinstance(m, torch.nn.Linear)][0]
    torch.testing.assert_close(sac.critic.weights[0][1], lin.weight.T, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(sac.log_alpha, plain.log_alpha, rtol=1e-5, atol=1e-6)


def test_update_flops_counts_each_matmul():
    # obs 1, act 1, one hidden layer of 1, batch 1: every linear layer costs 2 FLOPs forward.
    # actor: trunk 1x1 + mean + log_std = 3 layers -> 6; critic: (2x1) + (1x1) = 4 + 2 = 6.
    # No first-layer input gradient in the critic step (2 critics x 4) nor the actor's (2).
    actor, critic = 6, 6
    expected = (actor + 2 * critic) + 2 * (3 * critic - 4) + (3 * actor - 2) + 2 * 2 * critic
    assert update_flops(1, 1, [1], 1) == expected


def test_actor_reference_replays_the_actors_own_actions():
    """The raw-rate reference steps the env with the untrained actor's actions, not uniform ones."""
    import numpy as np

    from silcr.actor.policy import NumpyPolicy, initial_weights
    from silcr.bench.actor import policy_actions
    from silcr.common.envs import EnvSpec

    spec = EnvSpec.of("Hopper-v5")
    actions = policy_actions("Hopper-v5", n=200, seed=0)
    assert len(actions) == 200
    a = np.stack(actions)
    assert (a >= spec.action_low).all() and (a <= spec.action_high).all()
    # the first action is the actor's first sample (same weights, rng and reset seed)
    import gymnasium as gym

    obs, _ = gym.make("Hopper-v5").reset(seed=0)
    policy = NumpyPolicy(initial_weights(spec.obs_dim, spec.act_dim, [800, 400], 0), spec.obs_dim, spec.act_dim)
    first = spec.to_env_action(policy.sample(np.asarray(obs, np.float32), np.random.default_rng(0)))
    np.testing.assert_allclose(a[0], first, rtol=1e-6)
    # squashed Gaussians crowd the bounds: more actions near them than uniform's 10% (seeded: 17%)
    near = np.abs(a) > 0.9 * spec.action_high
    assert near.mean() > 0.15


def test_recorded_matmuls_are_the_counted_flops():
    """The own-shape ceiling replays exactly the matmuls `update_flops` counts, and replays run."""
    from silcr.bench.reference_sac import matmul_only_rate, record_matmuls

    sac = Sac(5, 2, [16, 8], SacHyper(), torch.device("cpu"))
    batch = random_batch(5, 2, 32, torch.device("cpu"))
    calls = record_matmuls(lambda: sac.update(*batch))
    flops = 0
    for _, operands in calls:
        a, b = operands[-2][0], operands[-1][0]
        flops += 2 * a[-2] * a[-1] * b[-1] * (a[0] if len(a) == 3 else 1)
    assert flops == update_flops(5, 2, [16, 8], 32)
    assert matmul_only_rate(calls, torch.device("cpu"), 0.05) > 0


def test_a_process_cpu_time_is_read_finer_than_a_clock_tick():
    """The scale bench's CPU figures resolve less than /proc's 10 ms tick: a router relaying two
    actors uses about 15 ms in a 5 s window, which ticks could read as 0 (a CI run did). Another
    process burns 3 ms of CPU on cue; the bench's reading of it agrees with its own clock."""
    import subprocess
    import sys

    from silcr.bench.scale import _cpu_seconds

    burn = ("import sys, time\nprint('ready', flush=True)\nsys.stdin.readline()\nt = time.process_time()\n"
            "while time.process_time() - t < 0.003:\n    pass\nprint(time.process_time() - t, flush=True)\n"
            "sys.stdin.readline()\n")
    child = subprocess.Popen([sys.executable, "-c", burn], stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert child.stdout.readline().strip() == "ready"
        before = _cpu_seconds(child.pid)
        child.stdin.write("go\n")
        child.stdin.flush()
        burnt = float(child.stdout.readline())
        seen = _cpu_seconds(child.pid) - before
        child.stdin.write("end\n")
        child.stdin.flush()
    finally:
        child.wait(30)
    assert burnt >= 0.003 and abs(seen - burnt) < 0.002, (seen, burnt)
    assert _cpu_seconds(child.pid) is None  # gone


def test_the_scale_bench_measures_a_real_run_and_loses_nothing(tmp_path):
    """`silcr bench scale --quick` at 2 actors: every quantity issue 20 asks for is measured, and no
    episode is lost (no gap in any actor's sequence numbers, none left in the inbox)."""
    import json
    import subprocess
    import sys

    from tests.helpers import REPO

    # Paced by the learner with the actors as clients of the router, as a run with many actors is
    # (the unthrottled mode differs only in one `silcr train` option).
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "scale", "--quick", "--counts", "2",
                        # A small tolerance keeps the paced actors' pauses shorter than the 5 s window.
                        "--seconds", "5", "--paced", "--train-args=--actor-zenoh-mode client --spi-tolerance 100",
                        "--tag", "q",
                        "--out", str(tmp_path)], capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    records = json.loads((tmp_path / "scale-q.json").read_text())
    assert records["paced"] and records["train_args"] == ["--actor-zenoh-mode", "client", "--spi-tolerance", "100"]
    (res,) = records["results"]
    assert res["transitions_per_s"] > 0  # measured after the actors went on: the steady state
    assert res["router_cpu_cores"] > 0  # the router relays everything the client actors send and receive
    assert res["actors"] == 2 and res["actors_reporting"] == 2
    assert res["episodes_missing"] == 0 and res["episodes_dropped"] == 0 and res["episodes_rejected"] == 0
    assert res["episodes_received"] > 0 and res["episodes_received"] >= 0.8 * res["episodes_published"]
    for key in ("weights_latency_ms_p50", "weights_latency_ms_p99", "weights_fanout_mb_per_s", "episodes_mb_per_s",
                "router_cpu_cores", "buffer_cpu_cores", "learner_cpu_cores", "actor_rss_mb_median",
                "learner_duty_cycle"):
        assert isinstance(res[key], float) and res[key] >= 0, key
    assert 20 < res["actor_rss_mb_median"] < 1000 and res["weights_bytes"] > 1000
    assert (tmp_path / "scale-q.png").stat().st_size > 1000
    for args, option in ((["--counts", "8,x"], "--counts"), (["--train-args='unclosed"], "--train-args"),
                         (["--tag", "a/b"], "--tag")):
        bad = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "scale", *args, "--out", str(tmp_path / "no")],
                             capture_output=True, text=True, cwd=REPO, timeout=60)
        assert bad.returncode == 2 and option in bad.stderr and "Traceback" not in bad.stderr
        assert not (tmp_path / "no").exists()


def test_the_scale_bench_runs_actors_on_namespace_hosts_behind_routers_of_their_own(tmp_path):
    """`silcr bench scale --hosts 2 --counts 2`: four actors on two network-namespace hosts, each host
    with a Zenoh router linked to the hub's; the weights reach every actor through its host's router,
    nothing is lost, the host routers' CPU is measured, and the namespaces are gone afterwards."""
    import json
    import subprocess
    import sys

    from silcr.bench.netns import why_not_namespaces
    from tests.helpers import REPO

    if why := why_not_namespaces():
        pytest.skip(why)
    before = subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "bench", "scale", "--quick", "--hosts", "2", "--counts", "2",
                        "--seconds", "5", "--tag", "h", "--out", str(tmp_path)], capture_output=True, text=True,
                       cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stdout[-3000:] + r.stderr[-3000:]
    records = json.loads((tmp_path / "scale-h.json").read_text())
    (res,) = records["results"]
    assert records["hosts"] == 2 and res["actors"] == 4 and res["actors_reporting"] == 4, res
    assert res["episodes_missing"] == 0 and res["episodes_dropped"] == 0 and res["episodes_rejected"] == 0
    # Whole-run counts: a 5 s window may fall inside a pause (the default tolerance lets 4 fast
    # actors run 2,000 steps ahead, which the learner takes longer than the window to catch up).
    assert res["episodes_received"] > 0 and res["transitions_per_s"] >= 0
    assert res["weights_latency_ms_worst_actor_p50"] is not None  # the actors took weights through their hosts
    assert res["host_routers_cpu_cores"] is not None and res["host_routers_cpu_cores"] >= 0
    assert subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout == before
