"""Deterministic evaluation of a policy, from live weights or a checkpoint, with an optional video."""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from silcr.actor.policy import Policy, policy_for
from silcr.common import protocol as P
from silcr.common.envs import EnvSpec, make_env
from silcr.common.minigrid_obs import is_minigrid


def rollout(env, policy: Policy, spec: EnvSpec, seed: int, deterministic: bool = True,
            frames: list[np.ndarray] | None = None, infos: list[dict] | None = None) -> P.Episode:
    """One episode of `policy` on a dense-reward `env`, recorded whole (rendered into `frames` if given; the
    env's info dicts, the reset's first and then one a step, appended to `infos` if given)."""
    obs, info = env.reset(seed=seed)
    if infos is not None:
        infos.append(info)
    rng = np.random.default_rng(seed)
    observations, actions, rewards = [np.asarray(obs, np.float32)], [], []
    terminated = truncated = False
    while not (terminated or truncated):
        a = policy.deterministic(obs) if deterministic else policy.sample(obs, rng)
        obs, r, terminated, truncated, info = env.step(spec.to_env_action(a))
        if infos is not None:
            infos.append(info)
        observations.append(np.asarray(obs, np.float32))
        actions.append(np.asarray(a, spec.action_dtype))
        rewards.append(float(r))
        if frames is not None:
            frames.append(env.render())
    rew = np.asarray(rewards, np.float32)
    return P.Episode(actor_id=-1, seq=seed, policy_version=policy.version, episode_return=float(np.sum(rewards)),
                     terminated=bool(terminated), truncated=bool(truncated) and not terminated,
                     obs=np.stack(observations), actions=np.stack(actions), rewards=rew)


class Evaluation(NamedTuple):
    """A policy over a few episodes: dense return (mean, std), mean length, and the share of
    episodes that reached the task's goal (`None` for a task without one: `EnvSpec.reached_goal`)."""

    mean: float
    std: float
    length: float
    success: float | None


def evaluate(weights: P.Weights, spec: EnvSpec, episodes: int, seed: int, video: Path | None = None,
             deterministic: bool = True) -> Evaluation:
    """The deterministic policy (tanh of the mean, or the most likely action), or with `deterministic` false
    the policy's sampled actions (seeded by `seed`), over `episodes` episodes.

    With `video`, the first episode is rendered off-screen and written as MP4.
    """
    return summary(evaluation_episodes(weights, spec, episodes, seed, video, deterministic), spec)


def summary(eps: list[P.Episode], spec: EnvSpec) -> Evaluation:
    """Mean and std of the dense return, mean length and the goal's share over `eps`."""
    returns = [e.episode_return for e in eps]
    goals = [spec.reached_goal(e) for e in eps]
    success = None if None in goals else float(np.mean(goals))
    return Evaluation(float(np.mean(returns)), float(np.std(returns)), float(np.mean([e.length for e in eps])), success)


def evaluation_episodes(weights: P.Weights, spec: EnvSpec, episodes: int, seed: int, video: Path | None = None,
                        deterministic: bool = True) -> list[P.Episode]:
    """`evaluate`'s episodes, whole (episode i seeded `seed + i`)."""
    policy = policy_for(weights, spec)
    frames: list[np.ndarray] = []
    env = _render_env(spec.env_id) if video else make_env(spec.env_id, "dense")
    try:
        eps = [rollout(env, policy, spec, seed + i, deterministic, frames if video and i == 0 else None) for i in range(episodes)]
    finally:
        env.close()
    if video:
        import imageio.v2 as imageio

        video.parent.mkdir(parents=True, exist_ok=True)
        fps = int(env.metadata.get("render_fps", 30))
        imageio.mimwrite(video, frames, fps=fps, macro_block_size=1)
    return eps


def record_demos(weights: P.Weights, spec: EnvSpec, episodes: int, seed: int, deterministic: bool = True,
                 progress=None) -> list[P.Episode]:
    """Roll out `episodes` episodes of the policy for a demonstrations file (dense rewards kept)."""
    policy = policy_for(weights, spec)
    env = make_env(spec.env_id, "dense")
    out = []
    try:
        for i in range(episodes):
            out.append(rollout(env, policy, spec, seed + i, deterministic))
            if progress is not None:
                progress(out[-1])
    finally:
        env.close()
    return out


def _render_env(env_id: str):
    if is_minigrid(env_id):  # MiniGrid draws its frames itself (pygame surfaces, no OpenGL)
        return make_env(env_id, "dense", render_mode="rgb_array")
    # Headless: EGL (GPU or Mesa) first, then OSMesa (software); say clearly when neither works.
    tried = []
    for backend in ([os.environ["MUJOCO_GL"]] if "MUJOCO_GL" in os.environ else ["egl", "osmesa"]):
        os.environ["MUJOCO_GL"] = backend
        try:
            env = make_env(env_id, "dense", render_mode="rgb_array")
            env.reset(seed=0)
            env.render()
            return env
        except Exception as e:  # each backend fails in its own way (ImportError, AttributeError, GL errors)
            tried.append(f"{backend}: {type(e).__name__}: {e}")
    raise RuntimeError("no off-screen renderer for MuJoCo works here (" + "; ".join(tried) + "); install EGL or OSMesa (libegl1 or libosmesa6)")


def weights_from_checkpoint(payload: dict) -> tuple[P.Weights, str]:
    sd = payload["sac"]["actor"]
    params = {k: v.detach().cpu().numpy().astype(np.float32) for k, v in sd.items()}
    arch = payload["sac"]["arch"]
    return (P.Weights(int(payload["counters"]["policy_version"]), params, arch,
                      action_kind=arch.get("action_kind", "continuous")), str(payload["config"]["env"]))
