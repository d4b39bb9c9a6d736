"""The options that keep critics bounded (issue 36): `--critic-norm layer` and `--q-target-clip bound`,
for continuous and discrete SAC, through the update, checkpoints and the command line."""

from __future__ import annotations

import math
import tomllib

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from silcr.learner import sac_discrete as D
from silcr.learner.sac import LOG2, Sac, SacHyper, TwinCritic, as_floats, clip_target, soft_q_bound

GAMMA = 0.99


def _batch(n=16, obs_dim=3, act_dim=2, seed=1):
    g = torch.Generator().manual_seed(seed)
    rewards = torch.cat([torch.zeros(n // 2), torch.ones(n - n // 2)])  # SILCR's labels: half D_O, half D_E
    return (torch.randn(n, obs_dim, generator=g), torch.rand(n, act_dim, generator=g) * 2 - 1, rewards,
            torch.randn(n, obs_dim, generator=g), torch.zeros(n), torch.zeros(n))


def _runaway_target(critic: torch.nn.Module, value: float) -> None:
    """Make a target critic say `value` everywhere: a critic that has run away from the data."""
    with torch.no_grad():
        for p in critic.parameters():
            p.zero_()
        last = critic.biases[-1] if isinstance(critic, TwinCritic) else None
        if last is not None:
            last.fill_(value)
        else:  # discrete TwinQ: the output layers' biases
            critic.q1[-1].bias.fill_(value)
            critic.q2[-1].bias.fill_(value)


# -- --q-target-clip bound ---------------------------------------------------------------------------

@settings(max_examples=200, deadline=None)
@given(y=st.lists(st.floats(-1e6, 1e9, allow_nan=False, width=32), min_size=1, max_size=32),
       alpha=st.floats(1e-4, 10.0), entropy_max=st.floats(0.0, 50.0), gamma=st.floats(0.5, 0.999))
def test_a_clipped_target_never_exceeds_the_bound(y, alpha, entropy_max, gamma):
    target = torch.tensor(y)
    a = torch.tensor(alpha)
    clipped, share = clip_target(target, 1.0, a, entropy_max, gamma)
    bound = float(soft_q_bound(1.0, a, entropy_max, gamma))
    assert float(clipped.max()) <= bound
    kept = target <= bound
    assert torch.equal(clipped[kept], target[kept])  # a target within the bound is left alone
    assert math.isclose(float(share), float((~kept).float().mean()))


def test_the_update_trains_on_no_target_above_the_bound():
    """Target critics that say 1e6 everywhere: with the clip every target is the bound, without it 1e6."""
    hp = dict(gamma=GAMMA, init_alpha=0.2)
    torch.manual_seed(0)
    clipped = Sac(3, 2, [8], SacHyper(**hp, target_reward_max=1.0), torch.device("cpu"))
    torch.manual_seed(0)
    plain = Sac(3, 2, [8], SacHyper(**hp), torch.device("cpu"))
    for sac in (clipped, plain):
        _runaway_target(sac.critic_target, 1e6)
    bound = (1.0 + GAMMA * 0.2 * 2 * LOG2) / (1 - GAMMA)  # (r_max + gamma alpha H_max) / (1 - gamma), H_max = 2 log 2
    on = as_floats(clipped.update(*_batch()))
    off = as_floats(plain.update(*_batch()))
    assert on["target_q_mean"] == pytest.approx(bound, rel=1e-5)
    assert on["q_target_clipped"] == 1.0
    assert off["target_q_mean"] > 1e5 and "q_target_clipped" not in off


def test_the_discrete_update_clips_at_log_of_the_action_count():
    torch.manual_seed(0)
    sac = D.DiscreteSac(3, 4, [8], D.DiscreteSacHyper(gamma=GAMMA, init_alpha=0.5, target_reward_max=1.0),
                        torch.device("cpu"))
    _runaway_target(sac.critic_target, 1e6)
    obs, _, rewards, nxt, term, trunc = _batch()
    actions = torch.randint(0, 4, (16,))
    stats = as_floats(sac.update(obs, actions, rewards, nxt, term, trunc))
    assert stats["target_q_mean"] == pytest.approx((1.0 + GAMMA * 0.5 * math.log(4)) / (1 - GAMMA), rel=1e-5)
    assert stats["q_target_clipped"] == 1.0


# -- --critic-norm layer -------------------------------------------------------------------------------

def test_layer_norm_critics_normalise_each_hidden_layer():
    """A LayerNorm after a hidden layer makes the critic blind to that layer's scale: multiplying the first
    layer's weights and biases by 10 leaves Q as it was. A plain critic's Q changes."""
    obs, act = torch.randn(5, 3), torch.rand(5, 2) * 2 - 1
    for norm, unchanged in (("layer", True), ("none", False)):
        torch.manual_seed(0)
        critic = TwinCritic(3, 2, [16, 16], norm)
        before = critic(obs, act)
        with torch.no_grad():
            critic.weights[0].mul_(10.0)
            critic.biases[0].mul_(10.0)
        after = critic(obs, act)
        same = all(torch.allclose(b, a, atol=1e-4) for b, a in zip(before, after))
        assert same == unchanged, norm
    assert len(TwinCritic(3, 2, [16, 16], "layer").norm_gains) == 2
    assert len(TwinCritic(3, 2, [16, 16]).norm_gains) == 0
    twin_q = D.TwinQ(3, 4, [16, 16], "layer")
    assert sum(isinstance(m, torch.nn.LayerNorm) for m in twin_q.modules()) == 4  # two per critic


def test_the_norm_has_its_own_gain_per_critic():
    """Each critic learns its own LayerNorm gain and shift: the two stay independent networks."""
    torch.manual_seed(0)
    sac = Sac(3, 2, [8], SacHyper(critic_norm="layer"), torch.device("cpu"))
    for _ in range(3):
        sac.update(*_batch())
    gains = sac.critic.norm_gains[0]
    assert gains.shape == (2, 1, 8)
    assert not torch.allclose(gains[0], gains[1])


@pytest.mark.parametrize("discrete", [False, True])
def test_layer_norm_critics_are_saved_and_restored(tmp_path, discrete):
    from silcr.learner.checkpoint import load_checkpoint, save_checkpoint

    def build(norm):
        if discrete:
            return D.DiscreteSac(3, 4, [8], D.DiscreteSacHyper(critic_norm=norm, target_reward_max=1.0),
                                 torch.device("cpu"))
        return Sac(3, 2, [8], SacHyper(critic_norm=norm, target_reward_max=1.0), torch.device("cpu"))

    def batch():
        obs, act, r, nxt, term, trunc = _batch()
        return (obs, torch.randint(0, 4, (16,)) if discrete else act, r, nxt, term, trunc)

    torch.manual_seed(0)
    a = build("layer")
    for _ in range(3):
        a.update(*batch())
    save_checkpoint(tmp_path / "c.pt", {"sac": a.state_dict(), "counters": {}})
    saved = load_checkpoint(tmp_path / "c.pt")["sac"]
    assert saved["critic_norm"] == "layer"
    assert any("norm" in k or ".1." in k for k in saved["critic"])  # the norms' parameters are in the file
    torch.manual_seed(5)
    b = build("layer")
    b.load_state_dict(saved)
    torch.manual_seed(7)
    la = as_floats(a.update(*batch()))
    torch.manual_seed(7)
    lb = as_floats(b.update(*batch()))
    assert la == lb
    for pa, pb in zip(a.critic.parameters(), b.critic.parameters()):
        torch.testing.assert_close(pa, pb, rtol=0, atol=0)
    with pytest.raises(ValueError, match="--critic-norm layer"):
        build("none").load_state_dict(saved)  # a run with plain critics refuses the file, by name


def test_a_checkpoint_from_before_the_option_restores_into_plain_critics():
    torch.manual_seed(0)
    a = Sac(3, 2, [8], SacHyper(), torch.device("cpu"))
    old = a.state_dict()
    del old["critic_norm"]  # written before --critic-norm existed
    Sac(3, 2, [8], SacHyper(), torch.device("cpu")).load_state_dict(old)
    with pytest.raises(ValueError, match="--critic-norm none"):
        Sac(3, 2, [8], SacHyper(critic_norm="layer"), torch.device("cpu")).load_state_dict(old)


# -- the command line -----------------------------------------------------------------------------------

def test_the_options_reach_the_learner_and_resume(tmp_path):
    """A single-process run with both options: its checkpoint holds LayerNorm critics, its progress rows the
    clipped share, and --resume continues it; a resume with the other norm is refused with one line."""
    from silcr.cli import main
    from silcr.learner.checkpoint import load_checkpoint

    args = ["train", "--single-process", "--env", "InvertedPendulum-v5", "--hidden", "8", "8", "--learning-starts",
            "200", "--eval-interval", "300", "--eval-episodes", "1", "--expert-capacity", "1000", "--batch-size", "32",
            "--torch-threads", "1", "--runs-dir", str(tmp_path), "--run", "r", "--critic-norm", "layer",
            "--q-target-clip", "bound"]
    assert main([*args, "--total-steps", "600"]) == 0
    ckpt = load_checkpoint(tmp_path / "r" / "checkpoints" / "learner.pt")
    assert ckpt["sac"]["critic_norm"] == "layer"
    assert "norm_gains.0" in ckpt["sac"]["critic"]
    rows = (tmp_path / "r" / "progress.csv").read_text().splitlines()
    header = rows[0].split(",")
    clipped = [r.split(",")[header.index("q_target_clipped")] for r in rows[1:]]
    assert clipped[0] == "" and all(0.0 <= float(c) <= 1.0 for c in clipped[1:])
    assert main([*args, "--total-steps", "900", "--resume"]) == 0
    assert float((tmp_path / "r" / "progress.csv").read_text().splitlines()[-1].split(",")[1]) >= 900


@pytest.mark.parametrize("algo, ok", [("silcr", True), ("ircr", True), ("sac", False), ("gasil", False)])
def test_the_target_clip_is_refused_for_env_rewards(tmp_path, algo, ok):
    import subprocess

    from silcr.cli import command

    # --learning-starts at --online-capacity is refused by the last check, so a run that is refused for it
    # passed the clip's check
    args = command("train", "--algo", algo, "--q-target-clip", "bound", "--runs-dir", str(tmp_path), "--run", "x",
                   "--online-capacity", "5", "--learning-starts", "5")
    out = subprocess.run(args, capture_output=True, text=True, timeout=120)
    if ok:
        assert "--learning-starts" in out.stderr and "--q-target-clip" not in out.stderr
    else:
        assert out.returncode == 2 and "--q-target-clip" in out.stderr and "Traceback" not in out.stderr
        assert len(out.stderr.strip().splitlines()) == 1
    assert not (tmp_path / "x").exists()


# -- the defaults -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("algo, options, expected", [
    ("silcr", {}, ("layer", "bound")),             # the labelled algorithms: both options (the Humanoid study)
    ("ircr", {}, ("layer", "bound")),
    ("sqil", {"demos": __file__}, ("layer", "bound")),
    ("sac", {}, ("none", "none")),                 # an env reward: plain critics, nothing to clip at
    ("gasil", {}, ("none", "none")),
    ("silcr", {"gamma": 1.0}, ("layer", "none")),  # no bound without discounting
    ("silcr", {"critic_norm": "none", "q_target_clip": "none"}, ("none", "none")),  # a choice stays as made
    ("silcr", {"critic_norm": "auto", "q_target_clip": "auto"}, ("layer", "bound")),
])
def test_auto_resolves_to_the_critics_measured_for_the_algorithm(tmp_path, algo, options, expected):
    from silcr.common.config import Config, critics_of, default_of, from_options

    assert (default_of("critic_norm"), default_of("q_target_clip")) == ("auto", "auto")
    cfg = from_options({"algo": algo, "run": "r", "runs_dir": str(tmp_path)} | options, "train")
    assert (cfg.critic_norm, cfg.q_target_clip) == expected  # what config.toml records: never "auto"
    cfg.save(tmp_path / "config.toml")
    saved = tomllib.loads((tmp_path / "config.toml").read_text())
    assert (saved["critic_norm"], saved["q_target_clip"]) == expected
    # a Config built directly keeps "auto"; the learner resolves it the same way
    raw = Config(run="r", algo=algo, **{k: v for k, v in options.items() if k != "demos"})
    assert critics_of(raw) == expected


def test_a_run_without_the_options_in_its_record_reads_as_plain_critics():
    """config.toml files written before the options existed ran with plain critics, whatever the defaults are now."""
    from silcr.common.config import value_when_absent

    assert (value_when_absent("critic_norm"), value_when_absent("q_target_clip")) == ("none", "none")
