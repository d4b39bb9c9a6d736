"""Demonstration files (`silcr demos` writes them): SQIL's fixed D_E, or a warm start of SILCR's
(`--expert-init`), where they compete with the agent's own episodes by return.

Format: one NumPy `.npz` archive (no pickled objects), version 1:

| array | shape, dtype | meaning |
|---|---|---|
| `format` | (), str | the constant `silcr-demos` |
| `version` | (), int64 | `DEMOS_VERSION` |
| `env` | (), str | gymnasium id the episodes come from, e.g. `Hopper-v5` |
| `episode_lengths` | (E,), int64 | transitions per episode, each >= 1 |
| `obs` | (sum(L_i + 1), obs_dim), float32 | each episode's s_0 .. s_L, episodes one after another |
| `actions` | (sum(L_i), act_dim), float32 | policy actions in [-1, 1] (before rescaling to the env's bounds) |
| `rewards` | (sum(L_i),), float32 | the env's dense rewards |
| `returns` | (E,), float64 | each episode's dense return (sum of its rewards) |
| `terminated`, `truncated` | (E,), bool | how each episode ended |

`load_demos` checks the file against the run's env, and each episode with the same
function that guards the network (`protocol.validate_episode`), and raises
`DemosError` with one line naming the problem.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np

from silcr.common.atomic_file import write_atomic
from silcr.common.envs import EnvSpec
from silcr.common.protocol import Episode, EpisodeLimits, ProtocolError, validate_episode

DEMOS_FORMAT = "silcr-demos"
DEMOS_VERSION = 1
#: The sender every loaded demonstration carries (actor 0 of this incarnation, which no
#: process draws: incarnations are random 56-bit ids), so that D_E can count them and a
#: buffer checkpoint keeps them as what they are.
DEMO_INCARNATION = 2**63 - 1


def is_demonstration(ep: Episode) -> bool:
    return ep.incarnation == DEMO_INCARNATION


_FIELDS = ("format", "version", "env", "episode_lengths", "obs", "actions", "rewards", "returns", "terminated", "truncated")


class DemosError(ValueError):
    """A demonstrations file that cannot be used for this run."""


def save_demos(path: Path, env_id: str, episodes: list[Episode]) -> None:
    """Write `episodes` (dense rewards, actions in [-1, 1]) atomically to `path`."""
    if not episodes:
        raise DemosError("no episodes to save")
    arrays = {
        "format": np.array(DEMOS_FORMAT),
        "version": np.array(DEMOS_VERSION, np.int64),
        "env": np.array(env_id),
        "episode_lengths": np.array([e.length for e in episodes], np.int64),
        "obs": np.concatenate([e.obs for e in episodes]).astype(np.float32),
        "actions": np.concatenate([e.actions for e in episodes]).astype(np.float32),
        "rewards": np.concatenate([e.rewards for e in episodes]).astype(np.float32),
        "returns": np.array([e.episode_return for e in episodes], np.float64),
        "terminated": np.array([e.terminated for e in episodes], bool),
        "truncated": np.array([e.truncated for e in episodes], bool),
    }
    write_atomic(path, lambda f: np.savez_compressed(f, **arrays))


def load_demos(path: Path, spec: EnvSpec) -> list[Episode]:
    """Read and validate a demonstrations file for the run's env; raise `DemosError` if unusable."""
    where = str(path)
    if not path.is_file():
        raise DemosError(f"{where}: no such demonstrations file")
    try:
        with np.load(path, allow_pickle=False) as z:
            missing = [k for k in _FIELDS if k not in z.files]
            if missing:
                raise DemosError(f"{where}: not a silcr demonstrations file (missing {', '.join(missing)})")
            a = {k: z[k] for k in _FIELDS}
    except DemosError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile) as e:
        raise DemosError(f"{where}: unreadable or corrupt ({type(e).__name__}: {e})") from None

    if str(a["format"]) != DEMOS_FORMAT:
        raise DemosError(f"{where}: format is {str(a['format'])!r}, expected {DEMOS_FORMAT!r}")
    if int(a["version"]) != DEMOS_VERSION:
        raise DemosError(f"{where}: version {int(a['version'])} is not supported (this silcr reads {DEMOS_VERSION})")
    if str(a["env"]) != spec.env_id:
        raise DemosError(f"{where}: demonstrations are for {str(a['env'])}, but this run's env is {spec.env_id}")
    lengths = a["episode_lengths"]
    if lengths.ndim != 1 or lengths.size == 0 or lengths.dtype.kind not in "iu" or (lengths < 1).any():
        raise DemosError(f"{where}: episode_lengths must be a non-empty list of positive integers")
    n_ep, n_tr = int(lengths.size), int(lengths.sum())
    expect = {
        "obs": (n_tr + n_ep, spec.obs_dim),
        "actions": (n_tr, spec.act_dim),
        "rewards": (n_tr,),
        "returns": (n_ep,),
        "terminated": (n_ep,),
        "truncated": (n_ep,),
    }
    for k, shape in expect.items():
        if a[k].shape != shape:
            raise DemosError(f"{where}: {k} has shape {a[k].shape}, expected {shape} for {n_ep} episodes on {spec.env_id}")
        if k in ("terminated", "truncated"):
            if a[k].dtype != bool:
                raise DemosError(f"{where}: {k} has dtype {a[k].dtype}, expected bool")
        elif a[k].dtype.kind != "f":
            raise DemosError(f"{where}: {k} has dtype {a[k].dtype}, expected floating point")

    limits = EpisodeLimits(spec.obs_dim, spec.act_dim, spec.max_episode_steps)
    episodes = []
    o = t = 0
    for i, n in enumerate(lengths.tolist()):
        ep = Episode(
            actor_id=0, seq=i, policy_version=-1, episode_return=float(a["returns"][i]),
            terminated=bool(a["terminated"][i]), truncated=bool(a["truncated"][i]),
            obs=a["obs"][o : o + n + 1].astype(np.float32), actions=a["actions"][t : t + n].astype(np.float32),
            rewards=a["rewards"][t : t + n].astype(np.float32), incarnation=DEMO_INCARNATION,
        )
        try:
            validate_episode(ep, limits)
        except ProtocolError as e:
            raise DemosError(f"{where}: episode {i}: {e}") from None
        episodes.append(ep)
        o += n + 1
        t += n
    return episodes
