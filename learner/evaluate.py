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
    """A policy over a few episodes: dense return (mean, std), mean length, the share of episodes that
    reached the task's goal (`None` for a task without one: `EnvSpec.reached_goal`), and the mean forward
    velocity over every step (`None` for an env whose steps do not report `info["x_velocity"]`)."""

    mean: float
    std: float
    length: float
    success: float | None
    x_velocity: float | None = None


#: The key MuJoCo's locomotion envs (Hopper, Walker2d, HalfCheetah, Swimmer, Ant, Humanoid) report their
#: torso's forward speed under, in m/s: what tells a walking robot from one that stands and earns the
#: healthy bonus (RESULTS.md, "What the returns are made of").
X_VELOCITY = "x_velocity"


def mean_x_velocity(step_infos: list[dict]) -> float | None:
    """The mean of `info["x_velocity"]` over the steps' info dicts (not the resets'); None if a step lacks it."""
    if not step_infos or any(X_VELOCITY not in i for i in step_infos):
        return None
    return float(np.mean([i[X_VELOCITY] for i in step_infos]))


def evaluate(weights: P.Weights, spec: EnvSpec, episodes: int, seed: int, video: Path | None = None,
             deterministic: bool = True) -> Evaluation:
    """The deterministic policy (tanh of the mean, or the most likely action), or with `deterministic` false
    the policy's sampled actions (seeded by `seed`), over `episodes` episodes.

    With `video`, the first episode is rendered off-screen and written as MP4.
    """
    step_infos: list[dict] = []
    eps = evaluation_episodes(weights, spec, episodes, seed, video, deterministic, step_infos)
    return summary(eps, spec, step_infos)


def summary(eps: list[P.Episode], spec: EnvSpec, step_infos: list[dict] | None = None) -> Evaluation:
    """Mean and std of the dense return, mean length and the goal's share over `eps`, and the mean forward
    velocity over `step_infos` (every step's info dict, as `evaluation_episodes` collects them)."""
    returns = [e.episode_return for e in eps]
    goals = [spec.reached_goal(e) for e in eps]
    success = None if None in goals else float(np.mean(goals))
    return Evaluation(float(np.mean(returns)), float(np.std(returns)), float(np.mean([e.length for e in eps])), success,
                      mean_x_velocity(step_infos or []))


def evaluation_episodes(weights: P.Weights, spec: EnvSpec, episodes: int, seed: int, video: Path | None = None,
                        deterministic: bool = True, step_infos: list[dict] | None = None) -> list[P.Episode]:
    """`evaluate`'s episodes, whole (episode i seeded `seed + i`); every step's info dict (not the resets')
    appended to `step_infos` if given."""
    policy = policy_for(weights, spec)
    frames: list[np.ndarray] = []
    env = _render_env(spec.env_id) if video else make_env(spec.env_id, "dense")
    eps = []
    try:
        for i in range(episodes):
            infos: list[dict] | None = [] if step_infos is not None else None
            eps.append(rollout(env, policy, spec, seed + i, deterministic, frames if video and i == 0 else None, infos))
            if step_infos is not None:
                step_infos.extend(infos[1:])  # infos[0] is the reset's
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
