"""The silcr wire protocol: Zenoh keys, QoS, message schemas and their codecs.

This is the only place where keys and message layouts are declared; every
component imports it. `docs/protocol.md` documents the same contract for people
and for tools written in other languages.

Every message kind is a dataclass with `encode()` and a `decode(payload)` class
method that returns it or raises `ProtocolError` naming the problem: `Episode`,
`EpisodeAck`, `Weights`, `SampleRequest`, `BatchReply`, `ThrottleNotice`, `ShutdownNotice`
and `Stats`. All binary messages are msgpack maps carrying `"v": SCHEMA_VERSION` and a
`kind`. Arrays travel as `[dtype, shape, raw_bytes]` (little-endian numpy dtype
string, list of ints, C-contiguous bytes) so that decoding is a zero-copy
`np.frombuffer`. Stats are JSON (UTF-8) so that any Zenoh client can read them
without this package. What makes an episode valid is stated once, in
`validate_episode`, which the demonstrations loader uses too.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
from dataclasses import dataclass, field, fields
from functools import cached_property
from typing import Any, Callable, Generic, Mapping, TypeVar

import msgpack
import numpy as np

#: Version 2 added the kind of action an episode, a set of weights and a batch carry
#: (`action_kind`: discrete actions travel as int64 indices). Version 1 messages, which
#: carry continuous actions only, are still read: a missing `action_kind` is "continuous".
#: Version 3 added `param_dtype` to weights: their arrays may travel as float16, half the
#: bytes of every publication's fan-out to the actors; a missing `param_dtype` is "<f4".
SCHEMA_VERSION = 3
READABLE_VERSIONS = (1, 2, 3)
#: What an env's actions are: float32 vectors in [-1, 1] (continuous) or int64 indices in [0, n) (discrete).
ACTION_KINDS = ("continuous", "discrete")
ACTION_WIRE = {"continuous": "<f4", "discrete": "<i8"}
#: How a set of weights' arrays travel (`--weights-dtype`); actors compute in float32 either way.
WEIGHTS_WIRE = {"float32": "<f4", "float16": "<f2"}

#: Largest episode message the buffer accepts by default (bytes). A 1000-step
#: Humanoid episode is about 1.5 MB; 64 MB leaves room and still bounds memory.
DEFAULT_MAX_EPISODE_BYTES = 64 * 1024 * 1024
#: Hard bounds on what one sample query may ask for: batches, rows per batch, rows in all
#: (a GPU learner's 16 batches of 4,096 fit). The buffer also refuses a request whose reply
#: would pass MAX_REPLY_BYTES for its env's observation and action sizes.
MAX_BATCHES_PER_REQUEST = 64
MAX_BATCH_SIZE = 65536
MAX_ROWS_PER_REQUEST = 65536
MAX_REPLY_BYTES = 64 * 1024 * 1024

log = logging.getLogger("protocol")

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

    def episode_acks(self, actor_id: int) -> str:
        """buffer -> one actor: which of its episodes the buffer holds durably (`EpisodeAck`, BLOCK)."""
        return f"{self.prefix}/episodes/ack/{actor_id}"

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

    def stats(self, role: str, ident: int | str | None = None) -> str:
        """The stats key of one component: `stats/buffer`, `stats/learner`, `stats/actor/<id>`."""
        return f"{self.prefix}/stats/{role}" + ("" if ident is None else f"/{ident}")

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
    def alive_learners(self) -> str:
        """The sampling learners' tokens, `alive/learner/<incarnation>`: the buffer serves only these."""
        return f"{self.prefix}/alive/learner/*"


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
    if isinstance(v, bool) or v not in READABLE_VERSIONS:
        raise ProtocolError("schema_version", f"schema version {v!r}, this build reads {list(READABLE_VERSIONS)}")
    return msg


def _unpack_kind(payload: bytes, kind: str, max_bytes: int | None = None) -> dict:
    msg = _unpack_map(payload, max_bytes)
    if msg.get("kind") != kind:
        raise ProtocolError("bad_field", f"kind is {msg.get('kind')!r}, expected {kind!r}")
    return msg


def _pack(msg: dict) -> bytes:
    return msgpack.packb({"v": SCHEMA_VERSION, **msg}, use_bin_type=True)


#: Integers are stored in int64 columns: anything outside cannot be stored or used.
INT64_MAX = 2**63 - 1


def _int(msg: Mapping, name: str, low: int, high: int = INT64_MAX, default: int | None = None) -> int:
    """An integer field within [low, high] (what it is stored in), or `default` when absent and allowed."""
    if default is not None and name not in msg:
        return default
    value = _get(msg, name, int)
    if not low <= value <= high:
        raise ProtocolError("out_of_range", f"field {name!r} is {value}, outside [{low}, {high}]")
    return value


def _finite(msg: Mapping, name: str, default: float | None = None) -> float:
    """A finite number field (an int is taken as a float), or `default` when absent and allowed."""
    if default is not None and name not in msg:
        return default
    value = float(_get(msg, name, (float, int)))
    if not math.isfinite(value):
        raise ProtocolError("non_finite", f"field {name!r} is {value}")
    return value


def _action_kind(msg: Mapping) -> str:
    """The message's `action_kind` (absent from version 1 messages: "continuous")."""
    kind = msg.get("action_kind", "continuous")
    if kind not in ACTION_KINDS:
        raise ProtocolError("bad_field", f"action_kind is {kind!r}, expected one of {list(ACTION_KINDS)}")
    return kind


def action_kind_of(actions: np.ndarray) -> str:
    """Integer actions are action indices (discrete); anything else is a continuous action."""
    return "discrete" if np.asarray(actions).dtype.kind in "iu" else "continuous"


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


@dataclass(frozen=True)
class EpisodeLimits:
    """What the run's env allows an episode to be: its sizes, its longest length, its largest message."""

    obs_dim: int
    act_dim: int
    max_steps: int = 100_000
    max_bytes: int = DEFAULT_MAX_EPISODE_BYTES
    #: discrete actions: how many (an episode's actions are indices in [0, n_actions)); 0: continuous
    n_actions: int = 0

    @property
    def action_kind(self) -> str:
        return "discrete" if self.n_actions else "continuous"


@dataclass
class Episode:
    """One finished episode as it travels and as the buffer stores it.

    `obs` has `length + 1` rows: row t is s_t and row t+1 is s_{t+1}, so next
    observations are never stored twice. `actions` are the policy's squashed
    outputs in [-1, 1] (not rescaled to the env's bounds), float32, or for a
    discrete env one int64 action index per row (shape (length, 1)). `rewards` are the
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
    #: the oldest of its episodes the actor still holds unconfirmed (it can send any from there on again);
    #: None from actors before 0.9, which hold nothing: the buffer takes it as `seq`
    resend_from: int | None = None

    @property
    def length(self) -> int:
        return int(self.actions.shape[0])

    @property
    def action_kind(self) -> str:
        return action_kind_of(self.actions)

    def encode(self) -> bytes:
        kind = self.action_kind
        return _pack({
            "kind": "episode",
            "action_kind": kind,
            "actor_id": int(self.actor_id),
            "incarnation": int(self.incarnation),
            "seq": int(self.seq),
            "policy_version": int(self.policy_version),
            "episode_return": float(self.episode_return),
            "length": self.length,
            "terminated": bool(self.terminated),
            "truncated": bool(self.truncated),
            "obs": pack_array(np.asarray(self.obs, dtype="<f4")),
            "actions": pack_array(np.asarray(self.actions, dtype=ACTION_WIRE[kind])),
            "rewards": pack_array(np.asarray(self.rewards, dtype="<f4")),
        } | ({} if self.resend_from is None else {"resend_from": int(self.resend_from)}))

    @classmethod
    def decode(cls, payload: bytes, limits: EpisodeLimits) -> "Episode":
        """The episode, valid for `limits` (`validate_episode`), or `ProtocolError` naming the first problem."""
        msg = _unpack_kind(payload, "episode", limits.max_bytes)
        length = _get(msg, "length", int)  # what the message claims, checked before its arrays are read
        if length <= 0:
            raise ProtocolError("empty", f"episode has length {length}; an episode needs at least one step")
        if length > limits.max_steps:
            raise ProtocolError("too_long", f"episode has {length} steps, the limit is {limits.max_steps}")
        incarnation = msg.get("incarnation", 0)  # absent from episodes of actors before 0.2
        if not isinstance(incarnation, int) or isinstance(incarnation, bool):
            raise ProtocolError("bad_field", "field 'incarnation' must be an int")
        kind = _action_kind(msg)
        if kind != limits.action_kind:
            raise ProtocolError("action_kind", f"episode carries {kind} actions, the run's env has {limits.action_kind} ones")
        ep = cls(
            _get(msg, "actor_id", int), _get(msg, "seq", int), _get(msg, "policy_version", int),
            float(_get(msg, "episode_return", (float, int))), _get(msg, "terminated", bool),
            _get(msg, "truncated", bool),
            unpack_array(_get(msg, "obs", (list, tuple)), "obs", "<f4"),
            unpack_array(_get(msg, "actions", (list, tuple)), "actions", ACTION_WIRE[kind]),
            unpack_array(_get(msg, "rewards", (list, tuple)), "rewards", "<f4"),
            incarnation,
            _int(msg, "resend_from", 0) if "resend_from" in msg else None,
        )
        if ep.resend_from is not None and ep.resend_from > ep.seq:
            raise ProtocolError("out_of_range", f"resend_from {ep.resend_from} is after the episode's own seq {ep.seq}")
        if ep.actions.ndim == 2 and ep.actions.shape[0] != length:
            raise ProtocolError("length_mismatch", f"length {length} but {ep.actions.shape[0]} actions")
        validate_episode(ep, limits)
        return ep


def validate_episode(ep: Episode, limits: EpisodeLimits) -> None:
    """What a valid episode is, for the network and for demonstration files alike.

    Raise `ProtocolError` with the first problem: every number storable (ids and
    versions in int64) and finite, the arrays shaped for the run's env and for each
    other, at least one and at most `limits.max_steps` steps, actions of the run's
    kind (continuous in [-1, 1], or action indices in [0, n_actions)),
    a return equal to the sum of the rewards, and an end (terminated or truncated).
    """
    for name, value, low in (("actor_id", ep.actor_id, 0), ("seq", ep.seq, 0), ("policy_version", ep.policy_version, -1),
                             ("incarnation", ep.incarnation, 0)):
        if not low <= value <= INT64_MAX:
            raise ProtocolError("out_of_range", f"field {name!r} is {value}, outside [{low}, {INT64_MAX}]")
    obs, actions, rewards = ep.obs, ep.actions, ep.rewards
    if obs.ndim != 2 or actions.ndim != 2 or rewards.ndim != 1:
        raise ProtocolError("bad_shape", "obs and actions must be 2-D, rewards 1-D")
    if obs.shape[1] != limits.obs_dim:
        raise ProtocolError("obs_dim", f"observation size {obs.shape[1]} does not match the run's env ({limits.obs_dim})")
    if actions.shape[1] != limits.act_dim:
        raise ProtocolError("act_dim", f"action size {actions.shape[1]} does not match the run's env ({limits.act_dim})")
    length = ep.length
    if length <= 0:
        raise ProtocolError("empty", f"episode has length {length}; an episode needs at least one step")
    if length > limits.max_steps:
        raise ProtocolError("too_long", f"episode has {length} steps, the limit is {limits.max_steps}")
    if obs.shape[0] != length + 1 or rewards.shape[0] != length:
        raise ProtocolError("length_mismatch", f"length {length} needs {length + 1} observations and {length} "
                                               f"rewards, got {obs.shape[0]} and {rewards.shape[0]}")
    if not (np.isfinite(obs).all() and np.isfinite(actions).all() and np.isfinite(rewards).all()):
        raise ProtocolError("non_finite", "episode contains NaN or infinite values")
    if not math.isfinite(ep.episode_return):
        raise ProtocolError("non_finite", "episode_return is NaN or infinite")
    if action_kind_of(actions) != limits.action_kind:
        raise ProtocolError("action_kind", f"episode carries {action_kind_of(actions)} actions, the run's env has "
                                           f"{limits.action_kind} ones")
    if limits.n_actions:
        if actions.min() < 0 or actions.max() >= limits.n_actions:
            raise ProtocolError("action_range", f"action indices must be in [0, {limits.n_actions})")
    elif np.abs(actions).max() > 1.0 + 1e-5:
        raise ProtocolError("action_range", "actions must be the policy's squashed outputs in [-1, 1]")
    total = float(rewards.sum(dtype=np.float64))
    if abs(total - ep.episode_return) > 1e-3 * max(1.0, abs(ep.episode_return)):
        raise ProtocolError("return_mismatch", f"episode_return {ep.episode_return} differs from the sum of rewards {total}")
    if not (ep.terminated or ep.truncated):
        raise ProtocolError("not_finished", "episode is neither terminated nor truncated")


@dataclass(frozen=True)
class EpisodeAck:
    """The buffer to one actor (incarnation): every episode of it up to `confirmed` is held durably
    (-1: none yet). `resend_from` asks for episodes again from that seq on: the buffer refused one
    that came after a gap (the ones before it were lost on the way). Acks are cumulative, so a
    later one repairs any that went missing."""

    actor_id: int
    incarnation: int
    confirmed: int
    resend_from: int | None = None

    def encode(self) -> bytes:
        return _pack({"kind": "episode_ack", "actor_id": int(self.actor_id), "incarnation": int(self.incarnation),
                      "confirmed": int(self.confirmed)}
                     | ({} if self.resend_from is None else {"resend_from": int(self.resend_from)}))

    @classmethod
    def decode(cls, payload: bytes) -> "EpisodeAck":
        msg = _unpack_kind(payload, "episode_ack", max_bytes=65536)
        return cls(_int(msg, "actor_id", 0), _int(msg, "incarnation", 0), _int(msg, "confirmed", -1),
                   _int(msg, "resend_from", 0) if "resend_from" in msg else None)


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
    #: the policy's kind: a tanh-Gaussian ("continuous") or a categorical one over action indices ("discrete")
    action_kind: str = "continuous"
    #: how the arrays travel (a key of WEIGHTS_WIRE); decoded weights are float32 whatever they travelled as
    wire_dtype: str = "float32"

    def supersedes(self, current: "Weights | None") -> bool:
        """The actors' rule: take weights that are newer than `current` or come from another learner incarnation."""
        return current is None or self.incarnation != current.incarnation or self.version > current.version

    def encode(self) -> bytes:
        wire = WEIGHTS_WIRE[self.wire_dtype]
        with np.errstate(over="ignore"):  # checked just below
            params = {k: np.asarray(a, dtype=wire) for k, a in self.params.items()}
        if wire != "<f4" and not all(np.isfinite(a).all() for a in params.values()):
            # a weight beyond float16's range (65,504) would reach the actors as inf, and they would refuse
            # every publication: this one travels as float32 instead, and says so in its `param_dtype`
            log.warning("weights version %d: a weight is beyond float16's range; sent as float32", self.version)
            wire, params = "<f4", {k: np.asarray(a, dtype="<f4") for k, a in self.params.items()}
        return _pack({
            "kind": "weights",
            "action_kind": self.action_kind,
            "version": int(self.version),
            "incarnation": int(self.incarnation),
            "sent_at": float(self.sent_at),
            "arch": dict(self.arch),
            "param_dtype": wire,
            "params": {k: pack_array(a) for k, a in params.items()},
        })

    @classmethod
    def decode(cls, payload: bytes, max_bytes: int = DEFAULT_MAX_EPISODE_BYTES) -> "Weights":
        msg = _unpack_kind(payload, "weights", max_bytes)
        version = _int(msg, "version", 0)  # actors stamp it on every episode: int64, as the buffer stores it
        arch = _get(msg, "arch", dict)
        raw = _get(msg, "params", dict)
        wire = msg.get("param_dtype", "<f4")  # absent before version 3
        if wire not in WEIGHTS_WIRE.values():
            raise ProtocolError("bad_dtype", f"param_dtype is {wire!r}, expected one of {list(WEIGHTS_WIRE.values())}")
        params = {str(k): unpack_array(v, f"params.{k}", wire).astype(np.float32, copy=False) for k, v in raw.items()}
        for k, a in params.items():
            if not np.isfinite(a).all():
                raise ProtocolError("non_finite", f"weights {k!r} contain NaN or infinite values")
        sent_at = _finite(msg, "sent_at", default=0.0)  # actors report latencies from it: finite
        incarnation = _int(msg, "incarnation", 0, default=0)  # absent from weights of learners before 0.2
        dtype = next(name for name, w in WEIGHTS_WIRE.items() if w == wire)
        return cls(version, params, arch, sent_at, incarnation, _action_kind(msg), dtype)


def new_incarnation() -> int:
    """A random id for a process whose counters start again when it restarts (actors, learners)."""
    return int.from_bytes(os.urandom(7), "little")


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
    #: the requesting learner's incarnation (as on its weights); over Zenoh the buffer serves only a live learner
    learner: int = 0
    #: the learner's count of updates made when it sent the request (None: not sent); the buffer's rate
    #: limiter takes it from a learner's first request, so a learner restarted from an older checkpoint
    #: is served again the updates it lost (ReplayState.take_learner_count)
    updates: int | None = None

    def encode(self) -> bytes:
        msg: dict[str, Any] = {"kind": "sample", "batches": self.batches, "batch_size": self.batch_size}
        if self.learner:
            msg["learner"] = self.learner
        if self.updates is not None:
            msg["updates"] = self.updates
        if self.disc_batch_size:
            msg |= {"disc_batch_size": self.disc_batch_size, "recent_window": self.recent_window}
        return _pack(msg)

    @classmethod
    def decode(cls, payload: bytes) -> "SampleRequest":
        msg = _unpack_map(payload, max_bytes=4096)
        batches = _get(msg, "batches", int)
        batch_size = _get(msg, "batch_size", int)
        if not 1 <= batches <= MAX_BATCHES_PER_REQUEST:
            raise ProtocolError("bad_request", f"batches={batches} is outside [1, {MAX_BATCHES_PER_REQUEST}]")
        if not 2 <= batch_size <= MAX_BATCH_SIZE:
            raise ProtocolError("bad_request", f"batch_size={batch_size} is outside [2, {MAX_BATCH_SIZE}]")
        if batches * batch_size > MAX_ROWS_PER_REQUEST:
            raise ProtocolError("bad_request", f"{batches} batches of {batch_size} rows are {batches * batch_size} rows, "
                                               f"more than {MAX_ROWS_PER_REQUEST} per request")
        disc = _get(msg, "disc_batch_size", int) if "disc_batch_size" in msg else 0
        window = _get(msg, "recent_window", int) if disc else 0
        if not 0 <= disc <= MAX_BATCH_SIZE:
            raise ProtocolError("bad_request", f"disc_batch_size={disc} is outside [0, {MAX_BATCH_SIZE}]")
        if disc and not 1 <= window <= INT64_MAX:
            raise ProtocolError("bad_request", f"recent_window={window} must be in [1, 2**63) with disc_batch_size")
        if batches * disc > MAX_ROWS_PER_REQUEST:
            raise ProtocolError("bad_request", f"{batches} x {disc} discriminator rows per class are more than "
                                               f"{MAX_ROWS_PER_REQUEST} per request")
        learner = _int(msg, "learner", 0, default=0)
        updates = _int(msg, "updates", 0) if "updates" in msg else None
        return cls(batches, batch_size, disc, window, learner, updates)


A = TypeVar("A")  # an array type: numpy arrays on the wire and in the buffer, torch tensors in the learner
R = TypeVar("R", bound="_Rows")


class _Rows:
    """Arrays of equal length, one per dataclass field: converted together, sliced together."""

    def map(self: R, fn: Callable[[Any], Any]) -> R:
        """The same rows with `fn` applied to every array (to tensors on a device, say)."""
        return type(self)(**{f.name: fn(getattr(self, f.name)) for f in fields(self)})  # type: ignore[arg-type]

    def rows(self: R, b: int, size: int) -> R:
        """Rows [b * size, (b + 1) * size): batch b of batches of `size` rows."""
        s = slice(b * size, (b + 1) * size)
        return self.map(lambda a: a[s])


@dataclass
class Batch(_Rows, Generic[A]):
    """Rows of transitions, one update's batch after another (`rows(b, size)` is batch b).

    `rewards` are the labels the algorithm trains on (set by the buffer's labeller);
    `terminated`/`truncated` are 1 on an episode's last row when it ended that way;
    `policy_version` is the version of the weights that acted (-1: before any).
    `actions` are float32, or int64 action indices (one column) for a discrete env.
    """

    obs: A
    actions: A
    rewards: A
    next_obs: A
    terminated: A
    truncated: A
    policy_version: A

    #: dtype of each field on the wire (`actions`: that of continuous actions; discrete ones are `<i8`)
    WIRE = {"obs": "<f4", "actions": "<f4", "rewards": "<f4", "next_obs": "<f4", "terminated": "|u1",
            "truncated": "|u1", "policy_version": "<i8"}

    @classmethod
    def empty(cls, n: int, obs_dim: int, act_dim: int, action_dtype: type = np.float32) -> "Batch[np.ndarray]":
        return cls(np.empty((n, obs_dim), np.float32), np.empty((n, act_dim), action_dtype), np.empty(n, np.float32),
                   np.empty((n, obs_dim), np.float32), np.empty(n, np.uint8), np.empty(n, np.uint8),
                   np.empty(n, np.int64))

    @property
    def action_kind(self) -> str:
        return action_kind_of(self.actions)

    @staticmethod
    def wire_for(action_kind: str) -> dict[str, str]:
        """Each field's dtype on the wire for a batch of `action_kind` actions."""
        return Batch.WIRE | {"actions": ACTION_WIRE[action_kind]}


@dataclass
class DiscriminatorRows(_Rows, Generic[A]):
    """GASIL's discriminator data: D_E (s, a) pairs (label 1) and as many from the newest D_O episodes (label 0)."""

    expert_obs: A
    expert_actions: A
    recent_obs: A
    recent_actions: A

    WIRE = {"disc_expert_obs": "<f4", "disc_expert_actions": "<f4", "disc_recent_obs": "<f4",
            "disc_recent_actions": "<f4"}


class BufferMismatch(RuntimeError):
    """The buffer service's replies are not what this learner needs (it runs another --algo or --env)."""


@dataclass(frozen=True)
class BatchHeader:
    """What a reply's `meta` agrees between the buffer and the learner, typed (SB3's `ReplayBufferSamples` in
    spirit): the buffer's algorithm and the layout of an `ok` reply's rows.

    The layout is worked out here only: `batches` consecutive batches of `batch_size` rows, each batch's
    first `online_rows` rows from D_O and the rest, when the algorithm mixes, from D_E. `check` is the one
    test that a buffer's replies suit a learner."""

    algo: str | None  # None: a buffer from before 0.4, which did not name its algorithm
    batches: int = 0  # 0 in a not_ready reply
    batch_size: int = 0
    online_rows: int = 0
    disc_batch_size: int = 0  # discriminator rows per batch (0: none sent)
    action_kind: str | None = None  # the rows' actions (an ok reply's batch)

    @staticmethod
    def online_rows_for(batch_size: int, mixed: bool) -> int:
        """Rows of each batch drawn from D_O (the first ones); the rest, if `mixed`, come from D_E."""
        return batch_size - (batch_size // 2 if mixed else 0)

    @classmethod
    def of(cls, meta: Mapping[str, Any], action_kind: str | None = None, disc: bool = False) -> "BatchHeader":
        size = int(meta.get("batch_size", 0))
        return cls(meta.get("algo"), int(meta.get("batches", 0)), size,
                   int(meta.get("online_rows", size)), int(meta.get("disc_batch_size", 0)) if disc else 0,
                   action_kind)

    def layout(self) -> dict[str, int]:
        """The layout's keys of `meta` (the sampler adds them to the buffer's description)."""
        out = {"batches": self.batches, "batch_size": self.batch_size, "online_rows": self.online_rows}
        return out | ({"disc_batch_size": self.disc_batch_size} if self.disc_batch_size else {})

    @property
    def mixed(self) -> bool:
        return self.online_rows < self.batch_size

    @property
    def expert_from(self) -> int | None:
        """Where D_E's rows start in each batch (None: the batches hold none)."""
        return self.online_rows if self.mixed else None

    def by_table(self, column: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A per-row column as (batches, rows) views: D_O's rows, then D_E's (no columns when not mixed)."""
        rows = column.reshape(self.batches, self.batch_size)
        return rows[:, :self.online_rows], rows[:, self.online_rows:]

    def check_algo(self, algo: Any) -> None:
        """The part of `check` any reply (a not_ready one too) can show: the buffer's algorithm's name."""
        name = self.algo or algo.name  # a buffer before 0.4: the rows' layout (`check`) tells
        if name != algo.name:
            raise BufferMismatch(f"the buffer service runs --algo {name}, this learner --algo {algo.name}; "
                                 f"start both with the same --algo")

    def check(self, algo: Any, env_id: str, action_kind: str) -> None:
        """BufferMismatch unless the buffer runs `algo` (a `common.algorithms.Algorithm`) for an env of
        `action_kind`: the same name, and in an `ok` reply D_E rows exactly when the algorithm mixes,
        discriminator rows when it trains one, and actions of the learner's env's kind."""
        self.check_algo(algo)
        if not self.batches:
            return
        if self.mixed != algo.mixes_expert:
            raise BufferMismatch(f"--algo {algo.name}: the buffer service "
                                 f"{'mixes D_E rows into' if self.mixed else 'sends no D_E rows in'} its batches; "
                                 f"it runs another --algo (start both with the same --algo)")
        if algo.discriminator and not self.disc_batch_size:
            raise BufferMismatch(f"--algo {algo.name}: the buffer service sent no discriminator rows; it runs "
                                 f"another --algo or predates GASIL (start it with --algo {algo.name})")
        if self.action_kind != action_kind:
            raise BufferMismatch(f"the buffer service sent {self.action_kind} actions; this learner's env "
                                 f"{env_id} has {action_kind} ones (it serves another --env)")


@dataclass
class BatchReply:
    """`status` is `ok` (`batch` holds `meta["batches"]` batches of `meta["batch_size"]` rows, and
    `disc` the discriminator's rows if they were asked for) or `not_ready` (see `reason`). `header`
    is `meta`'s agreement between buffer and learner, typed, worked out once per reply (on first use: a reply's
    `meta` is not changed after that)."""

    status: str
    meta: dict[str, Any]
    batch: Batch | None = None
    disc: DiscriminatorRows | None = None
    reason: str = ""
    retry_after_ms: int = 0

    @cached_property
    def header(self) -> BatchHeader:
        return BatchHeader.of(self.meta, self.batch.action_kind if self.batch is not None else None,
                              self.disc is not None)

    def encode(self) -> bytes:
        msg: dict[str, Any] = {"kind": "batch", "status": self.status, "meta": self.meta}
        if self.status == "ok":
            assert self.batch is not None
            msg["action_kind"] = self.batch.action_kind
            msg["arrays"] = {k: pack_array(np.asarray(getattr(self.batch, k), dtype=dt))
                             for k, dt in Batch.wire_for(self.batch.action_kind).items()}
            if self.disc is not None:
                msg["arrays"] |= {k: pack_array(np.asarray(getattr(self.disc, k.removeprefix("disc_")), dtype=dt))
                                  for k, dt in DiscriminatorRows.WIRE.items()}
        else:
            msg["reason"] = self.reason
            msg["retry_after_ms"] = int(self.retry_after_ms)
        return _pack(msg)

    #: meta numbers the learner uses, and what they must be (the rest is informational)
    META_RETURNS = ("expert_min_return", "expert_max_return", "rollout_return", "rollout_length")

    @classmethod
    def decode(cls, payload: bytes) -> "BatchReply":
        """The reply, with every number the learner uses in range and every array shaped for `meta`."""
        msg = _unpack_map(payload)
        status = _get(msg, "status", str)
        meta = _get(msg, "meta", dict)
        if status not in ("ok", "not_ready"):
            raise ProtocolError("bad_field", f"status is {status!r}, expected 'ok' or 'not_ready'")
        _int(meta, "env_steps", 0, default=0)
        if not isinstance(meta.get("algo", ""), str):
            raise ProtocolError("bad_field", "meta field 'algo' is not a string")
        for name in cls.META_RETURNS:
            if meta.get(name) is not None:
                _finite(meta, name)
        if status == "not_ready":
            return cls(status, meta, reason=str(msg.get("reason", "")),
                       retry_after_ms=_int(msg, "retry_after_ms", 0, 60_000, default=0))
        n = _int(meta, "batches", 1, MAX_BATCHES_PER_REQUEST)
        size = _int(meta, "batch_size", 2, MAX_BATCH_SIZE)
        _int(meta, "online_rows", 1, size, default=size)  # the layout `BatchHeader` reads
        raw = _get(msg, "arrays", dict)
        batch = Batch(**{k: unpack_array(raw.get(k), k, dt) for k, dt in Batch.wire_for(_action_kind(msg)).items()})
        _check_rows(batch, n * size, "batch")
        if batch.next_obs.shape != batch.obs.shape:
            raise ProtocolError("bad_shape", "next_obs and obs differ in shape")
        disc = None
        if "disc_expert_obs" in raw:
            disc = DiscriminatorRows(**{k.removeprefix("disc_"): unpack_array(raw.get(k), k, dt)
                                        for k, dt in DiscriminatorRows.WIRE.items()})
            _check_rows(disc, n * _int(meta, "disc_batch_size", 1, MAX_BATCH_SIZE), "discriminator rows")
        return cls("ok", meta, batch, disc)


def _check_rows(rows: _Rows, n: int, what: str) -> None:
    """Every array of `rows` has `n` rows (2-D for observations and actions, 1-D for the rest) of finite values."""
    for f in fields(rows):
        a = getattr(rows, f.name)
        two_d = f.name.endswith("obs") or f.name.endswith("actions")
        if a.ndim != (2 if two_d else 1) or a.shape[0] != n:
            raise ProtocolError("bad_shape", f"{what}: {f.name} has shape {a.shape}, expected {n} rows")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ProtocolError("non_finite", f"{what}: {f.name} contains NaN or infinite values")


# ---------------------------------------------------------------------------
# Control (buffer -> actors; anyone -> everyone) and stats (anyone -> monitors)
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ThrottleNotice:
    """The buffer's rate limiter to the actors: pause, or go on."""

    paused: bool

    def encode(self) -> bytes:
        return _pack({"kind": "throttle", "paused": bool(self.paused)})

    @classmethod
    def decode(cls, payload: bytes) -> "ThrottleNotice":
        return cls(_get(_unpack_kind(payload, "throttle", max_bytes=65536), "paused", bool))


@dataclass(frozen=True)
class ShutdownNotice:
    """The run is over (the learner finished, or the launcher stops it)."""

    reason: str

    #: the reason of the announcement that the run's budget is spent (the learner's, or a launcher's for it)
    FINISHED = "finished"

    def encode(self) -> bytes:
        return _pack({"kind": "shutdown", "reason": self.reason})

    @classmethod
    def decode(cls, payload: bytes) -> "ShutdownNotice":
        return cls(_get(_unpack_kind(payload, "shutdown", max_bytes=65536), "reason", str))


@dataclass
class Stats:
    """A component's stats: a flat JSON object (null for 'no value yet'), readable by any Zenoh client."""

    values: dict[str, Any]

    def encode(self) -> bytes:
        return json.dumps(self.values, separators=(",", ":"), allow_nan=False, default=_json_default).encode()

    @classmethod
    def decode(cls, payload: bytes) -> "Stats":
        try:
            values = json.loads(payload)
        except (ValueError, UnicodeDecodeError) as e:
            raise ProtocolError("not_json", f"stats are not JSON ({e})") from None
        if not isinstance(values, dict):
            raise ProtocolError("not_a_map", "stats are not a JSON object")
        return cls(values)


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer,)):
        return int(o)
    if isinstance(o, (np.floating,)):
        return float(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def finite_or_none(x: float | None) -> float | None:
    """JSON has no NaN or infinity; stats use null for 'no value yet'."""
    return None if x is None or not math.isfinite(x) else float(x)
