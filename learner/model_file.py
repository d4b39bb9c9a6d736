"""The file `Model.save` writes and `Model.load` reads: one policy, its configuration and its spaces.

One `torch.save` archive of plain data and tensors, loaded with `weights_only=True` (it runs no
code, as learner checkpoints: `learner/checkpoint.py`), written atomically:

    format     "silcr-model"
    version    MODEL_VERSION; a file of a newer version is refused with one line
    silcr      the release that wrote it
    algo       the registry name of the algorithm (`silcr.common.algorithms`)
    config     the run's resolved options (config.toml's keys)
    policy     the actor network: version, arch, action_kind and params {name: tensor}
    spec       the env's shapes and bounds (`EnvSpec`): obs_dim, act_dim, n_actions, action_low/high,
               max_episode_steps, time_limit
    training   only with include_training_state: the learner checkpoint (networks, optimisers,
               counters) and the buffer checkpoint's bytes (D_O, D_E, counters), to go on training
    evaluation only in a run's best.silcr (`learner/evaluations.py`): the evaluation that chose this
               policy (return_mean, return_std, episodes, env_steps, updates, deterministic)
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import torch

from silcr.common import protocol as P
from silcr.common import run_layout
from silcr.common.atomic_file import write_atomic
from silcr.common.envs import EnvSpec

MODEL_FORMAT = "silcr-model"
MODEL_VERSION = 1


class ModelFileError(ValueError):
    """A file that is not a silcr model this release can read (the message says why)."""


def spec_dict(spec: EnvSpec) -> dict[str, Any]:
    return {"env_id": spec.env_id, "obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "n_actions": spec.n_actions,
            "action_low": torch.from_numpy(np.array(spec.action_low, np.float32)),
            "action_high": torch.from_numpy(np.array(spec.action_high, np.float32)),
            "max_episode_steps": spec.max_episode_steps, "time_limit": spec.time_limit} | (
        {} if spec.obs_low is None else {"obs_low": torch.from_numpy(np.array(spec.obs_low, np.float32)),
                                         "obs_high": torch.from_numpy(np.array(spec.obs_high, np.float32))})


def spec_of(d: dict[str, Any]) -> EnvSpec:
    bounds = (d["obs_low"].numpy(), d["obs_high"].numpy()) if "obs_low" in d else (None, None)  # absent before 0.6
    return EnvSpec(d["env_id"], int(d["obs_dim"]), int(d["act_dim"]), d["action_low"].numpy(), d["action_high"].numpy(),
                   int(d["max_episode_steps"]), d["time_limit"], int(d["n_actions"]), *bounds)


def policy_dict(w: P.Weights) -> dict[str, Any]:
    return {"version": w.version, "arch": dict(w.arch), "action_kind": w.action_kind,
            "params": {k: torch.from_numpy(np.array(v, np.float32)) for k, v in w.params.items()}}


def weights_of(d: dict[str, Any]) -> P.Weights:
    return P.Weights(int(d["version"]), {k: v.numpy() for k, v in d["params"].items()}, dict(d["arch"]),
                     action_kind=d["action_kind"])


def write(path: Path, algo: str, config: dict[str, Any], weights: P.Weights, spec: EnvSpec,
          training: dict[str, Any] | None = None, evaluation: dict[str, Any] | None = None,
          env_steps: int | None = None) -> None:
    """`env_steps`: how many env steps the policy trained on (a loaded model's `num_timesteps`)."""
    from silcr.common.version import __version__

    payload = {"format": MODEL_FORMAT, "version": MODEL_VERSION, "silcr": __version__, "algo": algo, "config": config,
               "policy": policy_dict(weights), "spec": spec_dict(spec)}
    if env_steps is not None:
        payload["env_steps"] = int(env_steps)
    if training is not None:
        payload["training"] = training
    if evaluation is not None:
        payload["evaluation"] = evaluation
    path.parent.mkdir(parents=True, exist_ok=True)
    write_atomic(path, lambda f: torch.save(payload, f))


def read(path: str | Path) -> dict[str, Any]:
    """The file's contents, checked to be a model this release reads; ModelFileError with one line otherwise."""
    from silcr.learner.checkpoint import load_plain

    path = Path(path)
    return checked(load_plain(path, ModelFileError, "model file"), path)


def is_model(payload: Any) -> bool:
    """Whether a loaded file is a model file (and not a learner checkpoint or anything else)."""
    return isinstance(payload, dict) and payload.get("format") == MODEL_FORMAT


def checked(payload: Any, path: Path) -> dict[str, Any]:
    """`payload`, loaded from `path`, if it is a model this release reads; ModelFileError with one line otherwise."""
    if not is_model(payload):
        what = "a learner checkpoint (load it with silcr eval, or train from it with --resume)" \
            if isinstance(payload, dict) and {"counters", "config"} <= set(payload) else "not a silcr model file"
        raise ModelFileError(f"{path} is {what}")
    version = payload.get("version")
    if not isinstance(version, int) or version > MODEL_VERSION:
        raise ModelFileError(f"{path} was written by a newer silcr ({payload.get('silcr', '?')}, model format "
                             f"{version}); this one ({_version()}) reads format {MODEL_VERSION}: upgrade silcr")
    return payload


def _version() -> str:
    from silcr.common.version import __version__

    return __version__


def training_state(run_dir: Path) -> dict[str, Any]:
    """A run's learner checkpoint and buffer checkpoint (`<run dir>/checkpoints/`), for `write`'s `training`."""
    from silcr.learner.checkpoint import load_checkpoint

    learner, buffer = run_layout.learner_checkpoint(run_dir), run_layout.buffer_checkpoint(run_dir)
    if not learner.exists() or not buffer.exists():
        raise ValueError("no training state to save: the model has not learned yet (or was loaded without it)")
    return {"learner": load_checkpoint(learner),
            "buffer": torch.frombuffer(bytearray(buffer.read_bytes()), dtype=torch.uint8)}


def restore_training(training: dict[str, Any], run_dir: Path) -> int:
    """Write a file's training state as `run_dir`'s checkpoints, for --resume to continue; the env steps it had."""
    from silcr.learner.checkpoint import save_checkpoint

    ckpts = run_layout.checkpoints(run_dir)
    if ckpts.exists() and any(ckpts.iterdir()):
        raise ValueError(f"run: {run_dir} already holds checkpoints; give another run name")
    save_checkpoint(run_layout.learner_checkpoint(run_dir), training["learner"])
    buffer = training["buffer"].numpy().tobytes()
    write_atomic(run_layout.buffer_checkpoint(run_dir), lambda f: f.write(buffer))
    return int(training["learner"]["counters"]["env_steps"])
