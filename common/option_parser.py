"""The options as `silcr`'s subcommands take them: each role's parser built from the declarations in
`config.py`, grouped for `--help`."""

from __future__ import annotations

import argparse
import dataclasses
from typing import Any

from silcr.common.config import Config, option_name

#: How `--help` groups the options (every option is in one group; tests/test_config_cli.py keeps it so).
OPTION_GROUPS: dict[str, tuple[str, ...]] = {
    "run": ("run", "runs_dir", "env", "algo", "reward", "seed", "total_steps", "device", "torch_threads",
            "keep_denormals", "single_process", "max_restarts"),
    "algorithm": ("gamma", "lr", "tau", "grad_clip", "init_alpha", "time_limit_terminal", "absorbing_terminal",
                  "target_entropy_scale", "target_entropy_per_dim", "tanh_log_prob", "critic_norm", "q_target_clip", "bc_weight", "demos",
                  "expert_init", "gasil_alpha", "gasil_reward", "disc_hidden", "disc_lr", "disc_grad_penalty",
                  "disc_batch_size", "disc_interval", "disc_warmup", "recent_window"),
    "networks": ("hidden", "weights_interval", "weights_fanout_mb_s", "weights_dtype"),
    "buffers": ("online_capacity", "expert_capacity", "expert_admission", "expert_refill", "batch_size",
                "max_episode_bytes"),
    "rate control": ("learning_starts", "samples_per_insert", "spi_tolerance", "no_throttle", "batches_per_request",
                     "requests_in_flight"),
    "actors": ("actors", "actor_id", "envs_per_actor", "weights_poll_steps", "weights_wait", "actor_outbox_mb"),
    "evaluation": ("eval_interval", "eval_episodes", "final_eval_episodes", "eval_stochastic"),
    "Zenoh": ("connect", "listen", "zenoh_mode", "actor_zenoh_mode", "zenoh_config", "zenoh_listen"),
    "checkpoints": ("resume", "checkpoint_interval", "buffer_checkpoint_interval", "no_episode_log"),
    "stats and health": ("stats_interval", "health_file"),
}
_GROUP_OF = {name: group for group, names in OPTION_GROUPS.items() for name in names}


def add_options(parser: argparse.ArgumentParser, role: str) -> None:
    """Add every option of `role` to `parser`, in its `OPTION_GROUPS` group, with SUPPRESS defaults so only given
    options override."""
    parser.add_argument("--config", metavar="TOML", help="TOML file of options (keys as below, '-' or '_'); the command line wins")
    taken = [f for f in dataclasses.fields(Config) if role in f.metadata["roles"]]
    groups = {name: parser.add_argument_group(f"{name} options") for name in OPTION_GROUPS
              if any(_GROUP_OF[f.name] == name for f in taken)}
    for f in taken:
        meta = f.metadata
        group = groups[_GROUP_OF[f.name]]
        default = f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]
        kw: dict[str, Any] = {"default": argparse.SUPPRESS, "dest": f.name}
        if f.type in ("bool", bool):
            kw["action"] = "store_true"
            kw["help"] = meta["help"]
        else:
            elem = {"list[str]": str, "list[int]": int, "int": int, "float": float, "str": str}[str(f.type)]
            kw["type"] = elem
            if "nargs" in meta:
                kw["nargs"] = meta["nargs"]
            if "choices" in meta:
                kw["choices"] = meta["choices"]
            shown = " ".join(map(str, default)) if isinstance(default, list) else default
            kw["help"] = f"{meta['help']} (default: {shown})" if shown not in ("", []) else meta["help"]
            if "choices" in meta:
                kw["metavar"] = "{" + ",".join(meta["choices"]) + "}"
            else:
                kw["metavar"] = {int: "N", float: "X"}.get(elem, f.name.upper().split("_")[-1])
        group.add_argument(option_name(f.name), **kw)
