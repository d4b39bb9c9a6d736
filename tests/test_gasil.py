"""GASIL: the discriminator, its reward, its checkpoint, the buffer's recent rows, and a whole run."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from silcr.buffer_service.replay import ReplayState
from silcr.common import protocol as P
from silcr.common.config import GASIL_REWARD_FORMS, Config
from silcr.common.envs import EnvSpec
from silcr.common.weights_channel import InProcessWeights
from silcr.learner.checkpoint import CheckpointError
from silcr.learner.gasil import Gasil, GasilHyper, reward_from_logit
from silcr.learner.learner import Learner
from tests.conftest import make_episode
from tests.helpers import free_port, train_to_the_end

ENV = "InvertedPendulum-v5"  # obs_dim 4, act_dim 1, as make_episode's defaults


def _two_sets(n: int, gen: torch.Generator) -> tuple[torch.Tensor, ...]:
    expert_obs = torch.randn(n, 4, generator=gen) + 2.0
    recent_obs = torch.randn(n, 4, generator=gen) - 2.0
    return expert_obs, torch.full((n, 1), 0.5), recent_obs, torch.full((n, 1), -0.5)


@pytest.mark.parametrize("form", GASIL_REWARD_FORMS)
def test_the_discriminator_separates_two_different_sets(form):
    torch.manual_seed(0)
    gasil = Gasil(4, 1, GasilHyper(reward_form=form), torch.device("cpu"))
    gen = torch.Generator().manual_seed(1)
    for _ in range(300):
        stats = gasil.update(*_two_sets(64, gen))
    assert stats["disc_acc_expert"] > 0.95 and stats["disc_acc_policy"] > 0.95
    expert_obs, expert_act, recent_obs, recent_act = _two_sets(256, gen)  # fresh samples
    r_expert, r_policy = gasil.reward(expert_obs, expert_act), gasil.reward(recent_obs, recent_act)
    assert r_expert.min() > r_policy.max()  # looking like D_E pays more, whatever the form
    if form == "logit":
        assert r_expert.min() > 0 > r_policy.max()
    elif form == "positive":
        assert r_policy.min() >= 0
    else:
        assert r_expert.max() <= 0


def test_reward_forms_are_the_documented_functions_of_d():
    logit = torch.linspace(-5, 5, 11)
    d = torch.sigmoid(logit)
    torch.testing.assert_close(reward_from_logit(logit, "logit"), torch.log(d) - torch.log(1 - d))
    torch.testing.assert_close(reward_from_logit(logit, "positive"), -torch.log(1 - d))
    torch.testing.assert_close(reward_from_logit(logit, "negative"), torch.log(d))


# -- the buffer: recent rows on request ---------------------------------------------

def _gasil_cfg(tmp_path, **over) -> Config:
    return Config(run="g", runs_dir=str(tmp_path), env=ENV, algo="gasil", reward="dense", hidden=[16], batch_size=8,
                  learning_starts=10, weights_interval=3, checkpoint_interval=1000, eval_interval=10_000,
                  eval_episodes=0, total_steps=10_000, disc_hidden=[16], disc_batch_size=8, recent_window=25, **over)


def _filled(cfg: Config, episodes: int = 10) -> ReplayState:
    """Episode i: 10 steps, observations from 100 * i, return i (D_E keeps the best by return)."""
    replay = ReplayState(cfg, EnvSpec.of(ENV))
    for i in range(episodes):
        replay.intake.store(make_episode(10, ret=float(i), seq=i, start=100.0 * i))
    return replay


def _episode_of(obs: np.ndarray) -> np.ndarray:
    return (obs[:, 0] // 100).astype(int)


def test_the_buffer_serves_recent_rows_only_when_asked(tmp_path):
    cfg = _gasil_cfg(tmp_path, expert_capacity=30)  # D_E: the best 3 episodes (returns 7, 8, 9)
    replay = _filled(cfg)
    req = P.SampleRequest(batches=2, batch_size=8, disc_batch_size=200, recent_window=25)
    reply = P.BatchReply.decode(replay.sampler.sample(P.SampleRequest.decode(req.encode())).encode())  # over the wire format
    assert reply.status == "ok" and reply.meta["online_rows"] == 8  # SAC's batch: all D_O, env rewards
    recent = _episode_of(reply.disc.recent_obs)
    assert recent.shape == (400,) and set(recent) == {7, 8, 9}  # the newest whole episodes holding >= 25 transitions
    assert set(_episode_of(reply.disc.expert_obs)) == {7, 8, 9}
    np.testing.assert_array_equal(reply.disc.recent_actions, np.full((400, 1), 0.5, np.float32))

    for ep in range(10, 13):  # worse episodes: D_E keeps 7-9, the recent window moves on
        replay.intake.store(make_episode(10, ret=-1.0, seq=ep, start=100.0 * ep))
    reply = replay.sampler.sample(req)
    assert set(_episode_of(reply.disc.recent_obs)) == {10, 11, 12}
    assert set(_episode_of(reply.disc.expert_obs)) == {7, 8, 9}

    old = P.BatchReply.decode(replay.sampler.sample(P.SampleRequest(2, 8)).encode())  # a learner from before GASIL
    assert old.status == "ok" and old.disc is None


def test_a_window_larger_than_d_o_uses_all_of_it(tmp_path):
    replay = _filled(_gasil_cfg(tmp_path), episodes=3)
    reply = replay.sampler.sample(P.SampleRequest(1, 8, disc_batch_size=300, recent_window=10**9))
    assert set(_episode_of(reply.disc.recent_obs)) == {0, 1, 2}


def test_sample_request_fields_round_trip_and_are_checked():
    assert P.SampleRequest.decode(P.SampleRequest(3, 64).encode()) == P.SampleRequest(3, 64, 0, 0)
    assert P.SampleRequest.decode(P.SampleRequest(3, 64, 32, 5000).encode()) == P.SampleRequest(3, 64, 32, 5000)
    import msgpack

    for bad in ({"disc_batch_size": -1, "recent_window": 10}, {"disc_batch_size": 8, "recent_window": 0},
                {"disc_batch_size": 8}):
        with pytest.raises(P.ProtocolError) as e:
            P.SampleRequest.decode(msgpack.packb({"v": 1, "kind": "sample", "batches": 1, "batch_size": 8, **bad}))
        assert e.value.reason in ("bad_request", "missing_field")


def test_a_buffer_without_d_e_refuses_discriminator_rows_and_counts_it(tmp_path):
    cfg = Config(run="s", runs_dir=str(tmp_path), env=ENV, algo="sac", batch_size=8, learning_starts=10)
    replay = ReplayState(cfg, EnvSpec.of(ENV))
    replay.intake.store(make_episode(20))
    with pytest.raises(P.ProtocolError, match="disc_batch_size"):
        replay.sampler.answer(P.SampleRequest(1, 8, 8, 100).encode())
    assert replay.sampler.sample_requests_rejected == 1


# -- the learner: r_D per batch, checkpoints ----------------------------------------

class SacSpy:
    """Records the rewards each SAC update was given."""

    def __init__(self, learner: Learner) -> None:
        self.rewards: list[torch.Tensor] = []
        update = learner.update.sac.update

        def spy(obs, actions, rewards, *rest):
            self.rewards.append(rewards.clone())
            return update(obs, actions, rewards, *rest)

        learner.update.sac.update = spy


def test_r_d_is_recomputed_for_every_batch_from_the_current_discriminator(tmp_path):
    cfg = _gasil_cfg(tmp_path, gasil_alpha=0.5, expert_capacity=30)
    replay = _filled(cfg)
    lrn = Learner(cfg, EnvSpec.of(ENV), InProcessWeights())
    spy = SacSpy(lrn)
    stored = replay.fifo.storage.rewards.copy()
    reply = replay.sampler.sample(P.SampleRequest(1, 8, 8, 25))
    obs = torch.from_numpy(np.array(reply.batch.obs))
    actions = torch.from_numpy(np.array(reply.batch.actions))
    r_env = torch.from_numpy(np.array(reply.batch.rewards))
    seen = []
    for _ in range(5):  # the same batch five times: the discriminator learns in between
        lrn.step(reply)
        expected = r_env + 0.5 * lrn.update.gasil.reward(obs, actions)  # the discriminator after this step's update
        torch.testing.assert_close(spy.rewards[-1], expected, rtol=0, atol=1e-6)
        seen.append(spy.rewards[-1])
    assert not torch.equal(seen[0], seen[-1])  # r_D followed the discriminator
    assert lrn.update.gasil.updates == 5
    np.testing.assert_array_equal(replay.fifo.storage.rewards, stored)  # never stored
    stats = lrn.books.stats()
    for k in ("disc_loss", "disc_acc_expert", "disc_acc_policy", "gasil_reward_mean"):
        assert isinstance(stats[k], float), k
    assert stats["gasil_reward_mean"] == pytest.approx(float(lrn.update.gasil.reward(obs, actions).mean()), abs=1e-6)


def test_the_warm_up_keeps_r_d_out_of_the_reward(tmp_path):
    cfg = _gasil_cfg(tmp_path, disc_warmup=3, expert_capacity=30)
    replay = _filled(cfg)
    lrn = Learner(cfg, EnvSpec.of(ENV), InProcessWeights())
    spy = SacSpy(lrn)
    reply = replay.sampler.sample(P.SampleRequest(1, 8, 8, 25))
    r_env = torch.from_numpy(np.array(reply.batch.rewards))
    for _ in range(4):
        lrn.step(reply)
    assert all(torch.equal(r, r_env) for r in spy.rewards[:2])  # 1 and 2 discriminator updates: r_env alone
    assert not torch.equal(spy.rewards[3], r_env)


def _all_state(lrn: Learner) -> list[torch.Tensor]:
    g = lrn.update.gasil
    tensors = [*lrn.update.sac.actor.parameters(), *lrn.update.sac.critic.parameters(), *lrn.update.sac.critic_target.parameters(),
               lrn.update.sac.log_alpha, *g.disc.parameters(), *g.disc.buffers()]
    for opt in (g.opt, lrn.update.sac.critic_opt, lrn.update.sac.actor_opt):
        for st in opt.state.values():
            tensors += [v for v in st.values() if torch.is_tensor(v)]
    return tensors


def test_a_resumed_gasil_learner_continues_bit_identically(tmp_path):
    cfg = _gasil_cfg(tmp_path, expert_capacity=30)
    replay = _filled(cfg)
    batches = [replay.sampler.sample(P.SampleRequest(2, 8, 8, 25)) for _ in range(6)]
    a = Learner(cfg, EnvSpec.of(ENV), InProcessWeights())
    for b in batches[:3]:
        a.step(b)
    a.books.checkpoint()
    b = Learner(Config(**cfg.to_dict() | {"resume": True}), EnvSpec.of(ENV), InProcessWeights())
    assert b.books.resumed and b.books.updates == a.books.updates == 6 and b.update.gasil.updates == 6
    for lrn in (a, b):
        torch.manual_seed(11)  # the policy's and the penalty's noise: the same draws for both
        for batch in batches[3:]:
            lrn.step(batch)
    assert a.books.updates == b.books.updates == 12
    for x, y in zip(_all_state(a), _all_state(b), strict=True):
        assert torch.equal(x, y)
    assert a.books.stats()["disc_loss"] == b.books.stats()["disc_loss"]


def test_a_checkpoint_without_a_discriminator_is_refused(tmp_path):
    sac_cfg = Config(**_gasil_cfg(tmp_path).to_dict() | {"algo": "sac"})
    Learner(sac_cfg, EnvSpec.of(ENV), InProcessWeights()).books.checkpoint()
    with pytest.raises(CheckpointError, match="does not fit this run: .*no GASIL discriminator"):
        Learner(Config(**_gasil_cfg(tmp_path).to_dict() | {"resume": True}), EnvSpec.of(ENV), InProcessWeights())


def test_a_learner_given_the_wrong_batches_says_why(tmp_path):
    cfg = _gasil_cfg(tmp_path, expert_capacity=30)
    lrn = Learner(cfg, EnvSpec.of(ENV), InProcessWeights())
    with pytest.raises(RuntimeError, match="no discriminator rows"):
        lrn.step(_filled(cfg).sampler.sample(P.SampleRequest(1, 8)))
    silcr_buffer = _filled(Config(**cfg.to_dict() | {"algo": "silcr"}))  # serves D_E rows too, but mixed in
    reply = silcr_buffer.sampler.sample(P.SampleRequest(1, 8, 8, 25))
    with pytest.raises(RuntimeError, match="the buffer service runs --algo silcr, this learner --algo gasil"):
        lrn.step(reply)
    # a buffer from before 0.4 does not name its algorithm: its batches tell
    unnamed = P.BatchReply(reply.status, {k: v for k, v in reply.meta.items() if k != "algo"}, reply.batch, reply.disc)
    with pytest.raises(RuntimeError, match="mixes D_E rows into its batches"):
        Learner(cfg, EnvSpec.of(ENV), InProcessWeights()).step(unnamed)


# -- the whole distributed system -------------------------------------------------

@pytest.mark.slow
def test_gasil_learns_inverted_pendulum_through_the_distributed_system(tmp_path):
    """Router, buffer, learner and two actors over Zenoh, --algo gasil with the dense reward (as the paper compares it)."""
    rows, procs = train_to_the_end(
        tmp_path, "gasil", "--zenoh-listen", f"tcp/127.0.0.1:{free_port()}", "--env", ENV, "--algo", "gasil",
        "--reward", "dense", "--expert-capacity", "5000", "--actors", "2", "--seed", "1", "--total-steps", "20000",
        "--learning-starts", "1000", "--hidden", "64", "64", "--eval-interval", "3000", "--eval-episodes", "5",
    )
    returns = [float(r["eval_return"]) for r in rows]
    assert returns[0] < 20, returns
    assert max(returns) >= 100, f"GASIL did not learn: eval returns {returns}"
    assert sum(returns[-2:]) / 2 >= 50, f"GASIL did not keep what it learned: eval returns {returns}"
    trained = [r for r in rows if r["disc_loss"]]
    assert trained and all(0 <= float(r["disc_acc_expert"]) <= 1 for r in trained)  # the discriminator ran
    assert rows[-1]["q_bound_exceeded"] == "0"
    assert procs.orphans == []
