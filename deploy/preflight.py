"""Checks of a run's options that need more than their values: the env (can it be made, what are its
actions), the machine (memory for the buffers and actors, a GPU for --device cuda), the Zenoh endpoints,
the files named.

`check(cfg, role)` raises ConfigError naming the option, as `config.validate` does, before anything
is started or written. The command line runs it after parsing, the Python API after its options.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

from silcr.common.algorithms import algorithm
from silcr.common.config import Config, ConfigError

if TYPE_CHECKING:
    from silcr.common.envs import EnvSpec


def check(cfg: Config, role: str) -> None:
    """Options that can only be checked by trying them: the env id and the Zenoh endpoints."""
    from silcr.common.zenoh_session import check_endpoint, session_config

    if role not in ("monitor", "health"):
        from silcr.common.envs import EnvSpec

        try:
            spec = EnvSpec.of(cfg.env)
        except ValueError as e:
            raise ConfigError("--env", str(e)) from None
        _check_action_kind(cfg, spec)
        if (algorithm(cfg.algo).ranks_own_episodes and role in ("train", "buffer") and spec.time_limit
                and cfg.expert_capacity < spec.time_limit):
            # D_E admits whole episodes: one that never fits leaves it empty, and the learner waits forever.
            raise ConfigError("--expert-capacity", f"{cfg.expert_capacity} transitions cannot hold one whole episode of "
                                                   f"{cfg.env}, which runs up to {spec.time_limit} steps; D_E would stay "
                                                   f"empty or stop admitting longer episodes. Use at least {spec.time_limit}")
        if role in ("train", "buffer"):
            _check_memory(cfg, role, spec)
            from silcr.common.demos import DemosError, load_demos

            for option, path in (("--demos", cfg.demos), ("--expert-init", cfg.expert_init)):
                try:
                    if path:
                        load_demos(Path(path), spec)
                except DemosError as e:
                    raise ConfigError(option, str(e)) from None
    if role in ("train", "learner") and cfg.device == "cuda":  # every way of training: CLI, API, a learner alone
        from silcr.learner.update import pick_device

        try:
            pick_device("cuda")
        except ValueError as e:
            raise ConfigError("--device", str(e).removeprefix("--device cuda: ")) from None
    for option, endpoints in (("--connect", cfg.connect), ("--listen", cfg.listen),
                              ("--zenoh-listen", [cfg.zenoh_listen] if role == "train" else [])):
        for endpoint in endpoints:
            try:
                check_endpoint(endpoint)
            except ValueError as e:
                raise ConfigError(option, str(e)) from None
    try:
        session_config(cfg.connect, cfg.listen, cfg.zenoh_mode, cfg.zenoh_config)
    except ValueError as e:
        raise ConfigError("--connect/--listen/--zenoh-config", str(e)) from None


def _check_action_kind(cfg: Config, spec: "EnvSpec") -> None:
    """What the env's kind of action rules out: algorithms and options made for the other kind."""
    from silcr.common.algorithms import ALGORITHMS
    from silcr.common.config import default_of, option_name

    algo = algorithm(cfg.algo)
    if spec.discrete:
        if not algo.discrete:
            runs = ", ".join(a.name for a in ALGORITHMS.values() if a.discrete)
            raise ConfigError("--algo", f"--algo {cfg.algo} does not run with discrete actions ({cfg.env} has "
                                        f"{spec.n_actions}); these do: {runs}")
        for name in ("expert_init", "tanh_log_prob"):
            if getattr(cfg, name) != default_of(name):
                raise ConfigError(option_name(name), f"applies to continuous actions only; {cfg.env} has "
                                                     f"{spec.n_actions} discrete actions")
        from silcr.common.minigrid_obs import is_minigrid

        if is_minigrid(cfg.env) and not algo.uses_env_reward and not cfg.absorbing_terminal:
            # Not an error (the paper's rule is a valid choice to study), but a trap for a new user.
            print(f"silcr: warning: {cfg.env}'s episodes end at the goal; with --algo {cfg.algo}'s labels and without "
                  f"--absorbing-terminal the agent learns to avoid it (docs/algorithm.md, 'Discrete actions')",
                  file=sys.stderr)
    elif cfg.target_entropy_scale != default_of("target_entropy_scale"):
        raise ConfigError("--target-entropy-scale", f"applies to discrete actions only; {cfg.env} has continuous ones "
                                                    f"(their target entropy is -{spec.act_dim}, minus the action size)")


def _check_memory(cfg: Config, role: str, spec: "EnvSpec") -> None:
    """Buffer capacities and actor processes that this machine's available memory cannot hold."""
    from silcr.buffer_service.replay import reserved_bytes
    from silcr.common.resources import ACTOR_RSS_BYTES, MAX_LOCAL_ACTORS, available_memory, gib

    if role == "train" and cfg.actors > MAX_LOCAL_ACTORS:
        raise ConfigError("--actors", f"{cfg.actors} is more than {MAX_LOCAL_ACTORS} actors on one machine; use "
                                      f"--envs-per-actor for more envs per process, or start actors on other "
                                      f"machines with `silcr actor` (docs/deployment.md)")
    available = available_memory()
    if available is None:
        return
    buffer = reserved_bytes(cfg, spec)
    if buffer > available:
        option = "--online-capacity" if cfg.online_capacity * 4 >= cfg.expert_capacity else "--expert-capacity"
        raise ConfigError(option, f"D_O of {cfg.online_capacity:,} and D_E of {cfg.expert_capacity:,} transitions of "
                                  f"{cfg.env} would reserve {gib(buffer)}; this machine has {gib(available)} available")
    actors = cfg.actors * ACTOR_RSS_BYTES if role == "train" and not cfg.single_process else 0
    if buffer + actors > available:
        raise ConfigError("--actors", f"{cfg.actors} actor processes (about {gib(actors)}) and the buffer's "
                                      f"{gib(buffer)} need more than the {gib(available)} this machine has available")
