"""The silcr wire protocol: Zenoh keys, QoS, message schemas and their codecs.

This is the only place where keys and message layouts are declared; every
component imports it. `docs/protocol.md` documents the same contract for people
and for tools written in other languages.

All binary messages are msgpack maps carrying `"v": SCHEMA_VERSION`. Arrays travel
as `[dtype, shape, raw_bytes]` (little-endian numpy dtype string, list of ints,
C-contiguous bytes) so that decoding is a zero-copy `np.frombuffer`. Stats are
JSON (UTF-8) so that any Zenoh client can read them without this package.
"""

from __future__ import annotations

import json
import math
import os
import re
from dataclasses import dataclass, field
from typing import Any, Mapping

import msgpack
import numpy as np

SCHEMA_VERSION = 1

#: Largest episode message the buffer accepts by default (bytes). A 1000-step
#: Humanoid episode is about 1.5 MB; 64 MB leaves room and still bounds memory.
DEFAULT_MAX_EPISODE_BYTES = 64 * 1024 * 1024
#: Hard bounds on what one sample query may ask for.
MAX_BATCHES_PER_REQUEST = 64
MAX_BATCH_SIZE = 65536

_RUN_NAME = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


class ProtocolError(ValueError):
    """A message that does not follow the schema.

    `reason` is a short stable slug used as a counter name in the stats
    (for example `bad_dtype`); `str(err)` is the one-line human explanation.
    """

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


def validate_run_name(run: str) -> str:
    """Run names become Zenoh key chunks, so they may not contain `/`, `*`, `?`, `$` or `#`."""
    if not _RUN_NAME.match(run):
        raise ValueError(
            f"invalid run name {run!r}: use 1-64 characters from letters, digits, '_', '.' and '-'"
        )
    return run


# ---------------------------------------------------------------------------
# Keys
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Keys:
    """Every Zenoh key expression of one run, `silcr/<run>/...`."""

    run: str

    def __post_init__(self) -> None:
        validate_run_name(self.run)

    @property
    def prefix(self) -> str:
        return f"silcr/{self.run}"

    @property
    def episodes(self) -> str:
        """actor -> buffer: one finished episode per put (BLOCK, DATA)."""
        return f"{self.prefix}/episodes"

    @property
    def weights(self) -> str:
        """learner -> actors: policy weights (BLOCK, DATA_HIGH); also a queryable for late joiners."""
        return f"{self.prefix}/weights"

    @property
    def sample(self) -> str:
        """learner -> buffer: queryable answering mixed-batch requests."""
        return f"{self.prefix}/sample"

    @property
    def stats_buffer(self) -> str:
        return f"{self.prefix}/stats/buffer"

    @property
    def stats_learner(self) -> str:
        return f"{self.prefix}/stats/learner"

    def stats_actor(self, actor_id: int) -> str:
        return f"{self.prefix}/stats/actor/{actor_id}"

    @property
    def stats_all(self) -> str:
        return f"{self.prefix}/stats/**"

    @property
    def control_throttle(self) -> str:
        """buffer -> actors: rate-limiter state, `{"paused": bool}` (BLOCK)."""
        return f"{self.prefix}/control/throttle"

    @property
    def control_shutdown(self) -> str:
        """launcher or learner -> everyone: the run is over (BLOCK)."""
        return f"{self.prefix}/control/shutdown"

    def alive(self, role: str, ident: int | str | None = None) -> str:
        """Liveliness token of one component."""
        return f"{self.prefix}/alive/{role}" + ("" if ident is None else f"/{ident}")

    @property
    def alive_actors(self) -> str:
        return f"{self.prefix}/alive/actor/*"

    @property
    def alive_all(self) -> str:
        return f"{self.prefix}/alive/**"


# ---------------------------------------------------------------------------
# Arrays
# ---------------------------------------------------------------------------


def pack_array(a: np.ndarray) -> list:
    a = np.ascontiguousarray(a)
    return [a.dtype.str, list(a.shape), a.tobytes()]


def unpack_array(obj: Any, name: str, dtype: str) -> np.ndarray:
    """Decode `[dtype, shape, bytes]`, insisting on `dtype` (for example `<f4`)."""
    if not (isinstance(obj, (list, tuple)) and len(obj) == 3):
        raise ProtocolError("bad_field", f"field {name!r} is not an array triple [dtype, shape, bytes]")
    dt, shape, raw = obj
    if dt != dtype:
        raise ProtocolError("bad_dtype", f"field {name!r} has dtype {dt!r}, expected {dtype!r}")
    if not (isinstance(shape, (list, tuple)) and all(isinstance(s, int) and s >= 0 for s in shape)):
        raise ProtocolError("bad_shape", f"field {name!r} has an invalid shape {shape!r}")
    if not isinstance(raw, (bytes, bytearray)):
        raise ProtocolError("bad_field", f"field {name!r} carries no raw bytes")
    expected = math.prod(shape) * np.dtype(dtype).itemsize
    if len(raw) != expected:
        raise ProtocolError(
            "bad_shape", f"field {name!r} has {len(raw)} bytes, shape {list(shape)} needs {expected}"
        )
    return np.frombuffer(raw, dtype=np.dtype(dtype)).reshape(shape)


def _unpack_map(payload: bytes, max_bytes: int | None = None) -> dict:
    if max_bytes is not None and len(payload) > max_bytes:
        raise ProtocolError("oversized", f"message of {len(payload)} bytes exceeds the limit of {max_bytes}")
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as e:  # msgpack raises several unrelated types
        raise ProtocolError("not_msgpack", f"payload is not valid msgpack ({type(e).__name__})") from None
    if not isinstance(msg, dict):
        raise ProtocolError("not_a_map", f"message is a msgpack {type(msg).__name__}, expected a map")
    v = msg.get("v")
    if v != SCHEMA_VERSION:
        raise ProtocolError("schema_version", f"schema version {v!r}, this build speaks {SCHEMA_VERSION}")
    return msg


def _get(msg: Mapping, name: str, types: type | tuple[type, ...]) -> Any:
    if name not in msg:
        raise ProtocolError("missing_field", f"field {name!r} is missing")
    value = msg[name]
    # bool is an int subclass: never accept it where a number is asked for.
    if isinstance(value, bool) and bool not in (types if isinstance(types, tuple) else (types,)):
        raise ProtocolError("bad_field", f"field {name!r} is a bool, expected {types}")
    if not isinstance(value, types):
        raise ProtocolError("bad_field", f"field {name!r} is {type(value).__name__}, expected {types}")
    return value


# ---------------------------------------------------------------------------
# Episodes (actor -> buffer)
# ---------------------------------------------------------------------------


@dataclass
class Episode:
    """One finished episode as it travels and as the buffer stores it.

    `obs` has `length + 1` rows: row t is s_t and row t+1 is s_{t+1}, so next
    observations are never stored twice. `actions` are the policy's squashed
    outputs in [-1, 1] (not rescaled to the env's bounds). `rewards` are the
    rewards the actor's env returned (episodic or dense); SILCR ignores them
    except through `episode_return`, the ranking key.
    """

    actor_id: int
    seq: int
    policy_version: int
    episode_return: float
    terminated: bool
    truncated: bool
    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    #: random id of the actor process that sent it: a restarted actor starts `seq` again
    incarnation: int = 0

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])


class EpisodeCodec:
    """Encodes episodes and validates every incoming one against the run's env."""

    def __init__(
        self,
        obs_dim: int,
        act_dim: int,
        max_steps: int = 100_000,
        max_bytes: int = DEFAULT_MAX_EPISODE_BYTES,
    ) -> None:
        self.obs_dim = obs_dim
        self.act_dim = act_dim
        self.max_steps = max_steps
        self.max_bytes = max_bytes

    @staticmethod
    def encode(ep: Episode) -> bytes:
        return msgpack.packb(
            {
                "v": SCHEMA_VERSION,
                "kind": "episode",
                "actor_id": int(ep.actor_id),
                "incarnation": int(ep.incarnation),
                "seq": int(ep.seq),
                "policy_version": int(ep.policy_version),
                "episode_return": float(ep.episode_return),
                "length": ep.length,
                "terminated": bool(ep.terminated),
                "truncated": bool(ep.truncated),
                "obs": pack_array(np.asarray(ep.obs, dtype="<f4")),
                "actions": pack_array(np.asarray(ep.actions, dtype="<f4")),
                "rewards": pack_array(np.asarray(ep.rewards, dtype="<f4")),
            },
            use_bin_type=True,
        )

    def decode(self, payload: bytes) -> Episode:
        """Return the episode or raise `ProtocolError` naming the first problem found."""
        msg = _unpack_map(payload, self.max_bytes)
        if msg.get("kind") != "episode":
            raise ProtocolError("bad_field", f"kind is {msg.get('kind')!r}, expected 'episode'")
        actor_id = _get(msg, "actor_id", int)
        seq = _get(msg, "seq", int)
        version = _get(msg, "policy_version", int)
        ret = _get(msg, "episode_return", (float, int))
        length = _get(msg, "length", int)
        terminated = _get(msg, "terminated", bool)
        truncated = _get(msg, "truncated", bool)
        if actor_id < 0 or seq < 0 or version < -1:
            raise ProtocolError("bad_field", "actor_id and seq must be >= 0 and policy_version >= -1")
        if length <= 0:
            raise ProtocolError("empty", f"episode has length {length}; an episode needs at least one step")
        if length > self.max_steps:
            raise ProtocolError("too_long", f"episode has {length} steps, the limit is {self.max_steps}")
        if not (terminated or truncated):
            raise ProtocolError("not_finished", "episode is neither terminated nor truncated")
        obs = unpack_array(_get(msg, "obs", (list, tuple)), "obs", "<f4")
        actions = unpack_array(_get(msg, "actions", (list, tuple)), "actions", "<f4")
        rewards = unpack_array(_get(msg, "rewards", (list, tuple)), "rewards", "<f4")
        if obs.ndim != 2 or actions.ndim != 2 or rewards.ndim != 1:
            raise ProtocolError("bad_shape", "obs and actions must be 2-D, rewards 1-D")
        if obs.shape[1] != self.obs_dim:
            raise ProtocolError("obs_dim", f"observation size {obs.shape[1]} does not match the run's env ({self.obs_dim})")
        if actions.shape[1] != self.act_dim:
            raise ProtocolError("act_dim", f"action size {actions.shape[1]} does not match the run's env ({self.act_dim})")
        if obs.shape[0] != length + 1 or actions.shape[0] != length or rewards.shape[0] != length:
            raise ProtocolError(
                "length_mismatch",
                f"length {length} needs {length + 1} observations and {length} actions and rewards, "
                f"got {obs.shape[0]}, {actions.shape[0]}, {rewards.shape[0]}",
            )
        if not (np.isfinite(obs).all() and np.isfinite(actions).all() and np.isfinite(rewards).all()):
            raise ProtocolError("non_finite", "episode contains NaN or infinite values")
        if not math.isfinite(ret):
            raise ProtocolError("non_finite", "episode_return is NaN or infinite")
        if np.abs(actions).max() > 1.0 + 1e-5:
            raise ProtocolError("action_range", "actions must be the policy's squashed outputs in [-1, 1]")
        total = float(rewards.sum(dtype=np.float64))
        if abs(total - ret) > 1e-3 * max(1.0, abs(ret)):
            raise ProtocolError("return_mismatch", f"episode_return {ret} differs from the sum of rewards {total}")
        incarnation = msg.get("incarnation", 0)
        if not isinstance(incarnation, int) or isinstance(incarnation, bool) or not 0 <= incarnation < 2**63:
            raise ProtocolError("bad_field", "field 'incarnation' must be an int in [0, 2**63)")
        return Episode(actor_id, seq, version, float(ret), terminated, truncated, obs, actions, rewards, incarnation)


# ---------------------------------------------------------------------------
# Weights (learner -> actors)
# ---------------------------------------------------------------------------


@dataclass
class Weights:
    version: int
    params: dict[str, np.ndarray]
    arch: dict[str, Any] = field(default_factory=dict)
    #: wall-clock time of publication (seconds since the epoch), for latency stats
    sent_at: float = 0.0
    #: random id of the learner process that published them: a learner restarted from an
    #: older checkpoint (or none) counts versions again from there, and actors must follow it
    incarnation: int = 0

    def supersedes(self, current: "Weights | None") -> bool:
        """The actors' rule: take weights that are newer than `current` or come from another learner incarnation."""
        return current is None or self.incarnation != current.incarnation or self.version > current.version


def new_incarnation() -> int:
    """A random id for a process whose counters start again when it restarts (actors, learners)."""
    return int.from_bytes(os.urandom(7), "little")


def encode_weights(w: Weights) -> bytes:
    return msgpack.packb(
        {
            "v": SCHEMA_VERSION,
            "kind": "weights",
            "version": int(w.version),
            "incarnation": int(w.incarnation),
            "sent_at": float(w.sent_at),
            "arch": dict(w.arch),
            "params": {k: pack_array(np.asarray(a, dtype="<f4")) for k, a in w.params.items()},
        },
        use_bin_type=True,
    )


def decode_weights(payload: bytes) -> Weights:
    msg = _unpack_map(payload)
    if msg.get("kind") != "weights":
        raise ProtocolError("bad_field", f"kind is {msg.get('kind')!r}, expected 'weights'")
    version = _get(msg, "version", int)
    arch = _get(msg, "arch", dict)
    raw = _get(msg, "params", dict)
    params = {str(k): unpack_array(v, f"params.{k}", "<f4") for k, v in raw.items()}
    for k, a in params.items():
        if not np.isfinite(a).all():
            raise ProtocolError("non_finite", f"weights {k!r} contain NaN or infinite values")
    sent_at = msg.get("sent_at", 0.0)
    incarnation = msg.get("incarnation", 0)  # absent from weights of learners before 0.2
    if not isinstance(incarnation, int) or isinstance(incarnation, bool) or not 0 <= incarnation < 2**63:
        raise ProtocolError("bad_field", "field 'incarnation' must be an int in [0, 2**63)")
    return Weights(version, params, arch, float(sent_at) if isinstance(sent_at, (int, float)) else 0.0, incarnation)


# ---------------------------------------------------------------------------
# Sampling (learner <-> buffer)
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class SampleRequest:
    """Ask for `batches` mixed batches of `batch_size` transitions each (one update each).

    GASIL's discriminator also needs, per batch, `disc_batch_size` D_E transitions and
    as many from the newest `recent_window` transitions of D_O (its positives and
    negatives). Both are 0 unless asked for, and then the request is the silcr 0.2
    message, so buffers and learners from before these fields still understand each other.
    """

    batches: int = 1
    batch_size: int = 128
    disc_batch_size: int = 0
    recent_window: int = 0

    def encode(self) -> bytes:
        msg: dict[str, Any] = {"v": SCHEMA_VERSION, "kind": "sample", "batches": self.batches, "batch_size": self.batch_size}
        if self.disc_batch_size:
            msg |= {"disc_batch_size": self.disc_batch_size, "recent_window": self.recent_window}
        return msgpack.packb(msg)

    @staticmethod
    def decode(payload: bytes) -> "SampleRequest":
        msg = _unpack_map(payload, max_bytes=4096)
        batches = _get(msg, "batches", int)
        batch_size = _get(msg, "batch_size", int)
        if not 1 <= batches <= MAX_BATCHES_PER_REQUEST:
            raise ProtocolError("bad_request", f"batches={batches} is outside [1, {MAX_BATCHES_PER_REQUEST}]")
        if not 2 <= batch_size <= MAX_BATCH_SIZE:
            raise ProtocolError("bad_request", f"batch_size={batch_size} is outside [2, {MAX_BATCH_SIZE}]")
        disc = _get(msg, "disc_batch_size", int) if "disc_batch_size" in msg else 0
        window = _get(msg, "recent_window", int) if disc else 0
        if not 0 <= disc <= MAX_BATCH_SIZE:
            raise ProtocolError("bad_request", f"disc_batch_size={disc} is outside [0, {MAX_BATCH_SIZE}]")
        if disc and window < 1:
            raise ProtocolError("bad_request", f"recent_window={window} must be >= 1 with disc_batch_size")
        return SampleRequest(batches, batch_size, disc, window)


BATCH_FIELDS = {
    "obs": "<f4",
    "actions": "<f4",
    "rewards": "<f4",
    "next_obs": "<f4",
    "terminated": "|u1",
    "truncated": "|u1",
    "policy_version": "<i8",
}
#: GASIL's discriminator rows, in a reply only when the request asked for them
#: (`disc_batch_size` rows per batch each): D_E transitions and recent D_O transitions.
DISC_FIELDS = {
    "disc_expert_obs": "<f4",
    "disc_expert_actions": "<f4",
    "disc_recent_obs": "<f4",
    "disc_recent_actions": "<f4",
}


@dataclass
class BatchReply:
    """`status` is `ok` (arrays hold batches*batch_size rows) or `not_ready` (see `reason`)."""

    status: str
    meta: dict[str, Any]
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    reason: str = ""
    retry_after_ms: int = 0

    def encode(self) -> bytes:
        msg: dict[str, Any] = {"v": SCHEMA_VERSION, "kind": "batch", "status": self.status, "meta": self.meta}
        if self.status == "ok":
            msg["arrays"] = {k: pack_array(np.asarray(self.arrays[k], dtype=dt)) for k, dt in BATCH_FIELDS.items()}
            msg["arrays"] |= {k: pack_array(np.asarray(self.arrays[k], dtype=dt))
                              for k, dt in DISC_FIELDS.items() if k in self.arrays}
        else:
            msg["reason"] = self.reason
            msg["retry_after_ms"] = int(self.retry_after_ms)
        return msgpack.packb(msg, use_bin_type=True)

    @staticmethod
    def decode(payload: bytes) -> "BatchReply":
        msg = _unpack_map(payload)
        status = _get(msg, "status", str)
        meta = _get(msg, "meta", dict)
        if status == "ok":
            raw = _get(msg, "arrays", dict)
            arrays = {k: unpack_array(raw.get(k), k, dt) for k, dt in BATCH_FIELDS.items()}
            arrays |= {k: unpack_array(raw[k], k, dt) for k, dt in DISC_FIELDS.items() if k in raw}
            return BatchReply("ok", meta, arrays)
        return BatchReply(status, meta, reason=str(msg.get("reason", "")), retry_after_ms=int(msg.get("retry_after_ms", 0)))


# ---------------------------------------------------------------------------
# Control and stats
# ---------------------------------------------------------------------------


def encode_control(kind: str, **fields: Any) -> bytes:
    return msgpack.packb({"v": SCHEMA_VERSION, "kind": kind, **fields})


def decode_control(payload: bytes, kind: str) -> dict:
    msg = _unpack_map(payload, max_bytes=65536)
    if msg.get("kind") != kind:
        raise ProtocolError("bad_field", f"kind is {msg.get('kind')!r}, expected {kind!r}")
    return msg


STATS_ENCODING = "application/json"


def encode_stats(stats: Mapping[str, Any]) -> bytes:
    return json.dumps(stats, separators=(",", ":"), allow_nan=False, default=_json_default).encode()


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def finite_or_none(x: float | None) -> float | None:
    """JSON has no NaN or infinity; stats use null for 'no value yet'."""
    return None if x is None or not math.isfinite(x) else float(x)
