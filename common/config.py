"""Run configuration: one flat dataclass, filled from defaults, a TOML file, then the command line.

Every option is declared once, here, with the roles (subcommands) that take it;
`common/option_parser.py` builds each subcommand's parser from these declarations. Defaults are
the paper's Table I and the official code (see docs/algorithm.md for sources).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import tomli_w

from silcr.common import algorithms, run_layout
from silcr.common.envs import EPISODIC_IDS, REWARD_MODES
from silcr.common.protocol import DEFAULT_MAX_EPISODE_BYTES, WEIGHTS_WIRE, validate_run_name

_ENV_REWARD = [a.name for a in algorithms.ALGORITHMS.values() if a.uses_env_reward]
GASIL_REWARD_FORMS = ("logit", "positive", "negative")  # r_D from the discriminator (learner.gasil)
EXPERT_ADMISSIONS = ("return", "recent")  # what D_E keeps (buffer_service.expert_heap)
EXPERT_REFILLS = ("better", "any")  # what may enter the room evictions leave in a full D_E (buffer_service.expert_heap)
TANH_LOG_PROB_FORMS = ("exact", "official")  # log(1 - tanh^2) in the policy's log-probability (learner.sac)
CRITIC_NORMS = ("none", "layer")  # a normalisation after each hidden layer of the critics (learner.sac)
Q_TARGET_CLIPS = ("none", "bound")  # whether the TD target is clipped at the soft-Q bound (learner.sac.clip_target)
# "auto", either option's default, is resolved for the run's algorithm by `critics_of` (a checked Config never holds it).
DEVICES = ("auto", "cpu", "cuda")
ZENOH_MODES = ("peer", "client")
# Above this many actors, `silcr train` makes them Zenoh clients of its router: gossip links
# every peer to every other, and 128 actors as peers on 2 cores spent minutes linking (load
# average above 400) before the learner's first update (docs/scaling.md, "Links").
PEER_ACTORS_MAX = 32

ALL = frozenset({"train", "actor", "buffer", "learner"})
SERVICE = frozenset({"train", "buffer", "learner"})


class ConfigError(ValueError):
    """A bad option value; `option` names it as the user wrote it (`--actors` or the TOML key)."""

    def __init__(self, option: str, message: str) -> None:
        super().__init__(f"{option}: {message}")
        self.option = option


def _opt(default: Any, roles: frozenset[str] | set[str], help: str, **extra: Any) -> Any:
    meta = {"roles": frozenset(roles), "help": help, **extra}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class Config:
    # --- run and environment ------------------------------------------------
    run: str = _opt("", ALL | {"monitor"}, "run name; the Zenoh keys live under silcr/<run>/ (default: <env>-<algo>-<date>-<time>-<hex> for train)")
    runs_dir: str = _opt("runs", SERVICE | {"actor"}, "directory holding one sub-directory per run (an actor "
                         "only reads <runs dir>/<run>/finished.json there, where the run directory is shared, and "
                         "exits at once if the run is finished)")
    env: str = _opt("Hopper-v5", ALL, "gymnasium environment id: flat Box observations, Box (continuous) or Discrete "
                    "actions; MiniGrid-* tasks get a flat one-hot view (docs/algorithm.md)")
    algo: str = _opt(algorithms.DEFAULT, ALL, "; ".join(f"{a.name}: {a.summary}" for a in algorithms.ALGORITHMS.values())
                     + " (docs/algorithm.md)", choices=tuple(algorithms.ALGORITHMS))
    reward: str = _opt("episodic", ALL, f"reward the actors' env pays, for the algorithms that learn from it ({', '.join(_ENV_REWARD)}); "
                       f"the others always use episodic", choices=REWARD_MODES)
    seed: int = _opt(0, ALL, "base seed; actor i uses seed + i")
    # --- Zenoh -----------------------------------------------------------------
    connect: list[str] = _opt([], ALL | {"monitor", "health"}, "Zenoh endpoints to connect to (default: the local router)", nargs="+")
    listen: list[str] = _opt([], ALL, "Zenoh endpoints this process listens on (default tcp/127.0.0.1:0: loopback only)", nargs="+")
    zenoh_mode: str = _opt("peer", ALL | {"monitor", "health"}, "peer (direct links between components) or client (everything through the router)", choices=ZENOH_MODES)
    actor_zenoh_mode: str = _opt("auto", {"train"}, "how the actors `silcr train` starts join the run: peer (gossip "
                                 "links each to every other component and actor), client (one link each, to the "
                                 f"router, which relays), or auto: peer up to {PEER_ACTORS_MAX} actors, client above "
                                 "(docs/scaling.md)", choices=("auto", *ZENOH_MODES))
    zenoh_config: str = _opt("", ALL | {"monitor", "health"}, "Zenoh JSON5 config file applied before the options above")
    zenoh_listen: str = _opt("tcp/127.0.0.1:7447", {"train"}, "endpoint of the router that `silcr train` starts")
    # --- buffer service --------------------------------------------------------
    online_capacity: int = _opt(1_000_000, SERVICE, "D_O size in transitions (Table I: 1e6)")
    expert_capacity: int = _opt(50_000, SERVICE, "D_E size M in transitions (Table I: 5e4)")
    expert_admission: str = _opt("return", {"train", "buffer"}, "what D_E keeps: return: the best episodes by return (SILCR); "
                                 "recent: the latest episodes (a control without the ranking)", choices=EXPERT_ADMISSIONS)
    expert_refill: str = _opt("better", {"train", "buffer"}, "once D_E has filled, which episode may take the room "
                              "that evicting whole episodes leaves: better: only one whose return beats the lowest "
                              "stored, so D_E's lowest return never falls (the official code's rule for its full "
                              "buffer); any: any episode that fits, however low its return (runs recorded before "
                              "this option; docs/algorithm.md)", choices=EXPERT_REFILLS, absent="any")
    batch_size: int = _opt(128, SERVICE, "transitions per update; SILCR takes half from each buffer (official: 64 + 64)")
    learning_starts: int = _opt(10_240, SERVICE, "no update until D_O holds more than this many transitions (official code)")
    samples_per_insert: float = _opt(1.0, SERVICE, "gradient updates per environment step (official: 1)")
    spi_tolerance: float = _opt(2_000.0, SERVICE, "how many updates the learner or actors may run ahead of the ratio")
    no_throttle: bool = _opt(False, {"train", "buffer"}, "let actors run free instead of pausing them when they are ahead")
    demos: str = _opt("", {"train", "buffer"}, "demonstrations file (`silcr demos`) that fills D_E for --algo sqil")
    expert_init: str = _opt("", {"train", "buffer"}, "demonstrations file (`silcr demos`) that D_E starts with for --algo silcr; "
                            "they are ranked and evicted like the agent's own episodes")
    max_episode_bytes: int = _opt(DEFAULT_MAX_EPISODE_BYTES, {"train", "buffer"}, "largest episode message accepted")
    buffer_checkpoint_interval: float = _opt(300.0, {"train", "buffer"}, "seconds between buffer checkpoints (D_O, D_E, counters) in <run dir>/checkpoints/buffer.ckpt; 0: only at shutdown")
    no_episode_log: bool = _opt(False, {"train", "buffer"}, "acknowledge episodes once stored in memory instead of once "
                                "in the episode log (<run dir>/checkpoints/episode-log/, replayed after a crash): a "
                                "killed buffer then loses what came since its last checkpoint. Also off when "
                                "--buffer-checkpoint-interval is 0 (checkpoints are what compact the log)")
    # --- learner ---------------------------------------------------------------
    hidden: list[int] = _opt([800, 400], {"train", "learner", "actor"}, "hidden layer sizes of actor and critics (Table I: 800 400)", nargs="+")
    lr: float = _opt(3e-4, {"train", "learner"}, "Adam learning rate for actor, critics and alpha")
    gamma: float = _opt(0.99, {"train", "learner"}, "discount factor")
    tau: float = _opt(0.005, {"train", "learner"}, "target-critic soft update rate (Table I and the official code: 0.05, "
                      "with which the critics diverged on Hopper and Walker2d; docs/algorithm.md)")
    grad_clip: float = _opt(40.0, {"train", "learner"}, "gradient-norm clip for actor and each critic (0: off)")
    init_alpha: float = _opt(1.0, {"train", "learner"}, "initial entropy temperature")
    time_limit_terminal: bool = _opt(False, {"train", "learner"}, "treat time-limit truncation as terminal, as the official code does")
    absorbing_terminal: bool = _opt(False, {"train", "learner"}, "an episode's end is an absorbing state that keeps paying its "
                                    "rows' label (target r / (1 - gamma); DAC, SQIL): for labelled algorithms on tasks that "
                                    "end at success, such as MiniGrid's goal (docs/algorithm.md)")
    target_entropy_scale: float = _opt(0.89, {"train", "learner"}, "discrete actions: target entropy as a fraction of "
                                       "log |A| (CleanRL's sac_atari.py: 0.89; Christodoulou 2019: 0.98)")
    target_entropy_per_dim: float = _opt(-1.0, {"train", "learner"}, "continuous actions: SAC's target entropy per "
                                         "action dimension (the target is this x |A|; -1 is SAC's -|A|, the paper's). "
                                         "Lower: a narrower policy, whose sampled episodes (what D_E keeps) differ less "
                                         "from its mean action (what evaluations run); below log 2, the most a "
                                         "squashed action dimension can have (docs/algorithm.md, \"Keeping what D_E holds\")")
    critic_norm: str = _opt("auto", {"train", "learner"}, "layer: a LayerNorm after each hidden layer of both "
                            "critics (RLPD, Ball et al. 2023), which keeps Q from extrapolating past the data; "
                            "none: plain layers as in the paper; auto: layer for the labelled algorithms "
                            f"({', '.join(a.name for a in algorithms.ALGORITHMS.values() if a.labels_bounded)}), "
                            "none for the others (docs/algorithm.md, \"Critics that stay bounded\")",
                            choices=("auto", *CRITIC_NORMS), absent="none")
    q_target_clip: str = _opt("auto", {"train", "learner"}, "bound: clip the TD target at the soft-Q bound the labels "
                              "allow, (1 + gamma alpha H_max) / (1 - gamma), for the labelled algorithms "
                              f"({', '.join(a.name for a in algorithms.ALGORITHMS.values() if a.labels_bounded)}); "
                              "none: no clip; auto: bound for those algorithms when --gamma is below 1, else none",
                              choices=("auto", *Q_TARGET_CLIPS), absent="none")
    bc_weight: float = _opt(0.0, {"train", "learner"}, "weight of a self-imitation behaviour-cloning term in the "
                            "actor loss on each batch's D_E rows: bc_weight x mean |Q| x the mean squared distance "
                            "between the policy's mean action and the row's action (TD3+BC's form, Fujimoto and Gu "
                            "2021; self-imitation after Oh et al. 2018); 0: off, as in the paper (docs/algorithm.md, "
                            "\"Keeping what D_E holds\")")
    tanh_log_prob: str = _opt("exact", {"train", "learner"}, "log(1 - tanh(u)^2) in the policy's log-probability: exact (stable form) "
                              "or official (log(1 - a^2 + 1e-6), the official code's)", choices=TANH_LOG_PROB_FORMS)
    total_steps: int = _opt(2_000_000, {"train", "learner", "buffer", "actor"}, "environment-step budget of the run "
                            "(the buffer service makes the actors keep pace with the learner over its last stretch: "
                            "docs/algorithm.md, 'Rate control'; an actor reads it only to tell whether a finished run's "
                            "budget was raised)")
    weights_interval: int = _opt(50, {"train", "learner"}, "publish policy weights every N updates")
    weights_fanout_mb_s: float = _opt(100.0, {"train", "learner"}, "budget of the weights' traffic to all actors "
                                      "together, MB/s: a publication may follow the last after actors x its size / "
                                      "budget seconds, and a newer one replaces one that waits (about a 1 Gb/s link; "
                                      "0: no pacing; docs/scaling.md)")
    weights_dtype: str = _opt("float32", {"train", "learner"}, "how policy weights travel to the actors: float32, or "
                              "float16 (half the bytes of every publication to every actor; the actors' actions stay "
                              "within 0.01 of float32's: docs/protocol.md)", choices=tuple(WEIGHTS_WIRE))
    eval_interval: int = _opt(5_000, {"train", "learner"}, "evaluate the policy every N environment steps (deterministic unless --eval-stochastic)")
    eval_episodes: int = _opt(5, {"train", "learner"}, "episodes per evaluation")
    final_eval_episodes: int = _opt(0, {"train", "learner"}, "episodes of the closing evaluation, the run's final "
                                    "number (0: --eval-episodes); more give a steadier number where episodes either "
                                    "succeed or fail early (Humanoid: docs/algorithm.md)", absent=0)
    eval_stochastic: bool = _opt(False, {"train", "learner"}, "evaluate by sampling the policy's actions (seeded) instead "
                                 "of its deterministic ones: a memoryless policy in a partial view, such as MiniGrid's, "
                                 "can loop forever on its most likely actions (docs/algorithm.md)")
    checkpoint_interval: int = _opt(10_000, {"train", "learner"}, "checkpoint every N updates (and at the end)")
    resume: bool = _opt(False, SERVICE, "continue from the checkpoints in <run dir>/checkpoints/ when they exist (learner: networks, optimizers, alpha, counters; buffer: D_O, D_E, counters)")
    device: str = _opt("auto", {"train", "learner"}, "torch device for the learner (auto: CUDA when present)", choices=DEVICES)
    torch_threads: int = _opt(0, {"train", "learner"}, "torch CPU threads for the learner (0: the faster of 1 and all cores, timed at start and again every minute)")
    keep_denormals: bool = _opt(False, {"train", "learner"}, "compute the CPU update on denormal floats instead of flushing "
                                "them to zero: up to a fifth slower, and the same results to the last digit as runs made "
                                "before silcr 0.4 (docs/performance.md, \"Against Stable-Baselines3\")")
    batches_per_request: int = _opt(4, {"train", "learner"}, "batches fetched per sample query")
    requests_in_flight: int = _opt(2, {"train", "learner"}, "sample queries kept in flight so the learner never waits on the network")
    # --- GASIL (learner.gasil; sources in docs/algorithm.md, "GASIL") -------------
    gasil_alpha: float = _opt(0.1, {"train", "learner"}, "weight of the discriminator's reward: r = r_env + alpha * r_D (GASIL paper: 0.1)")
    gasil_reward: str = _opt("logit", {"train", "learner"}, "r_D from D = P(s, a is from D_E): logit (log D - log(1-D), zero where D cannot "
                             "tell), positive (-log(1-D): a survival bonus) or negative (log D: a bonus for ending)", choices=GASIL_REWARD_FORMS)
    disc_hidden: list[int] = _opt([100, 100], {"train", "learner"}, "discriminator hidden layers, tanh (ASIL, DAC: 100 100)", nargs="+")
    disc_lr: float = _opt(3e-4, {"train", "learner"}, "discriminator Adam learning rate")
    disc_grad_penalty: float = _opt(10.0, {"train", "learner"}, "gradient-penalty weight of the discriminator (DAC: 10; 0: off)")
    disc_batch_size: int = _opt(64, {"train", "learner"}, "discriminator rows per class per update: D_E and recent D_O")
    disc_interval: int = _opt(1, {"train", "learner"}, "SAC updates per discriminator update")
    disc_warmup: int = _opt(0, {"train", "learner"}, "discriminator updates before its reward enters the SAC update")
    recent_window: int = _opt(5_000, {"train", "learner"}, "the discriminator's policy rows come from the newest episodes of D_O "
                              "that hold this many transitions")
    # --- actors ----------------------------------------------------------------
    actors: int = _opt(1, {"train"}, "number of actors (processes; with --single-process, stepped in turn)")
    single_process: bool = _opt(False, {"train"}, "run buffer, learner and actors in this one process, in a fixed order, "
                                "without Zenoh: the same seed gives the same progress.csv (docs/deployment.md)")
    max_restarts: int = _opt(5, {"train"}, "times `silcr train` restarts a component that dies (actors fresh; buffer and learner from their checkpoints) before giving up")
    actor_id: int = _opt(0, {"actor"}, "this actor's id (also its seed offset); -1: a random id, for replicas that share one command (docker compose --scale)")
    envs_per_actor: int = _opt(1, {"train", "actor"}, "environments stepped by each actor with one batched forward pass")
    weights_poll_steps: int = _opt(50, {"train", "actor"}, "check for new weights every N steps")
    actor_outbox_mb: float = _opt(64.0, {"train", "actor"}, "MB of finished episodes an actor keeps until the buffer "
                                  "confirms them (sent again after a cut link or a buffer restart); a full outbox "
                                  "pauses the actor")
    weights_wait: float = _opt(15.0, {"train", "actor"}, "seconds an actor waits at start for the learner's weights before acting with its own random policy")
    # --- stats -----------------------------------------------------------------
    stats_interval: float = _opt(1.0, ALL, "seconds between stats messages")
    health_file: str = _opt("", ALL | {"health"}, "write a heartbeat to this file with every stats message, from the "
                            "component's main loop, for `silcr health` (a scheduler's liveness and readiness probes); "
                            "empty: none")

    # ------------------------------------------------------------------------
    @property
    def run_dir(self) -> Path:
        return Path(self.runs_dir) / self.run

    @property
    def actor_reward(self) -> str:
        """The reward the actors' env pays: `--reward` for the algorithms that learn from it, else episodic."""
        return self.reward if algorithms.algorithm(self.algo).uses_env_reward else "episodic"

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    def save(self, path: Path) -> None:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_bytes(tomli_w.dumps(self.to_dict()).encode())
        tmp.replace(path)


FIELDS = {f.name: f for f in dataclasses.fields(Config)}


def default_of(name: str) -> Any:
    f = FIELDS[name]
    return f.default if f.default is not dataclasses.MISSING else f.default_factory()  # type: ignore[misc]


def value_when_absent(name: str) -> Any:
    """What a run's config.toml without `name` ran with: an option is added keeping the behaviour it
    replaces, so that is its default when added. An option whose default changed later says so
    (`absent=`), so records written before it existed keep reading as what they ran."""
    meta = FIELDS[name].metadata
    return meta["absent"] if "absent" in meta else default_of(name)


def absent_values() -> dict[str, Any]:
    """Every option's `value_when_absent`: laid under a saved config (a run's config.toml, a model file's)
    so that the keys it lacks read as what it ran with."""
    return {name: value_when_absent(name) for name in FIELDS}


def saved_options(path: Path) -> dict[str, Any]:
    """A run's config.toml (as `Config.save` wrote it) with `absent_values` laid under: an option added since reads as
    what the run did. Reading and parsing errors (OSError, TOMLDecodeError, UnicodeDecodeError) are the caller's."""
    return absent_values() | tomllib.loads(Path(path).read_text())


def option_name(name: str) -> str:
    return "--" + name.replace("_", "-")


def _coerce(name: str, value: Any, where: str) -> Any:
    f = FIELDS[name]
    t = str(f.type)
    label = f"{where}{name}" if where else option_name(name)
    ok = {
        "bool": isinstance(value, bool),
        "int": isinstance(value, int) and not isinstance(value, bool),
        "float": isinstance(value, (int, float)) and not isinstance(value, bool),
        "str": isinstance(value, str),
        "list[str]": isinstance(value, list) and all(isinstance(v, str) for v in value),
        "list[int]": isinstance(value, list) and all(isinstance(v, int) and not isinstance(v, bool) for v in value),
    }[t]
    if not ok:
        raise ConfigError(label, f"expected {t}, got {value!r}")
    if "choices" in f.metadata and value not in f.metadata["choices"]:
        raise ConfigError(label, f"invalid choice {value!r} (choose from {', '.join(f.metadata['choices'])})")
    return float(value) if t == "float" else value


def load_toml(path: str, role: str) -> dict[str, Any]:
    p = Path(path)
    try:
        data = tomllib.loads(p.read_text())
    except FileNotFoundError:
        raise ConfigError("--config", f"file not found: {path}") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError("--config", f"{path} is not valid TOML ({e})") from None
    out: dict[str, Any] = {}
    for key, value in data.items():
        name = key.replace("-", "_")
        if name not in FIELDS:
            raise ConfigError(f"{path}: {key}", "unknown option")
        out[name] = _coerce(name, value, f"{path}: ")
    return out


ENV_PREFIX = "SILCR_"


def load_environ(environ: Mapping[str, str], role: str) -> dict[str, Any]:
    """Options from `SILCR_<OPTION>` variables (e.g. SILCR_TOTAL_STEPS=30000, SILCR_HIDDEN="800 400").

    For containers: docker-compose sets settings per service without rewriting
    commands. Only the options of `role` are read; a malformed value is a ConfigError.
    """
    out: dict[str, Any] = {}
    for name, f in FIELDS.items():
        raw = environ.get(ENV_PREFIX + name.upper())
        if raw is None or role not in f.metadata["roles"]:
            continue
        label = ENV_PREFIX + name.upper()
        t = str(f.type)
        try:
            if t == "bool":
                if raw.strip().lower() not in ("1", "true", "yes", "0", "false", "no", ""):
                    raise ValueError
                value: Any = raw.strip().lower() in ("1", "true", "yes")
            elif t.startswith("list"):
                value = [int(v) if t == "list[int]" else v for v in raw.replace(",", " ").split()]
            else:
                value = {"int": int, "float": float, "str": str}[t](raw)
        except ValueError:
            raise ConfigError(label, f"expected {t}, got {raw!r}") from None
        out[name] = _coerce(name, value, f"{label}: ")
    return out


def resolve(args: argparse.Namespace, role: str, environ: Mapping[str, str] | None = None) -> Config:
    """Defaults < (for `silcr train --resume`, the run's config.toml) < TOML file < SILCR_* environment variables
    < command line, then validate: each source's values in their ranges (a bad value is refused even where a later
    source overrides it), then the result."""
    values: dict[str, Any] = {}
    if getattr(args, "config", None):
        from_file = load_toml(args.config, role)
        check_values(from_file, lambda name: f"{args.config}: {name}")
        values.update(from_file)
    from_environ = load_environ(os.environ if environ is None else environ, role)
    check_values(from_environ, lambda name: ENV_PREFIX + name.upper())
    values.update(from_environ)
    for name in FIELDS:
        if name in vars(args):
            values[name] = getattr(args, name)
    if role == "train" and values.get("resume"):
        values = resumed_run_options(values) | values
    return _checked(values, role)


#: What `silcr train --resume` does not take from the run's config.toml: where the run is (nor an option since removed).
_NOT_RESUMED = frozenset({"run", "runs_dir", "resume"})


def resumed_run_options(given: Mapping[str, Any]) -> dict[str, Any]:
    """The options of the run a `silcr train --resume` names (`given`: by the command line, --config or SILCR_*),
    from its config.toml, for what is not given again (a forgotten --total-steps was a 2M budget that reopened a
    finished 300k run); none without a --run name (a new default name) or a file."""
    if not given.get("run"):
        return {}
    path = run_layout.config(Path(given.get("runs_dir", default_of("runs_dir"))) / given["run"])
    try:
        saved = tomllib.loads(path.read_text())
    except FileNotFoundError:
        return {}
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
        raise ConfigError("--resume", f"{path} cannot be read ({e}); give the run's options with --config "
                                      f"or on the command line, or repair the file") from None
    out: dict[str, Any] = {}
    for key, value in saved.items():
        if key in FIELDS and key not in _NOT_RESUMED and "train" in FIELDS[key].metadata["roles"]:
            out[key] = _coerce(key, value, f"{path}: ")
    check_values(out, lambda name: f"{path}: {name}")
    return out


def from_options(options: Mapping[str, Any], role: str, environ: Mapping[str, str] | None = None) -> Config:
    """A checked Config from option values by name (`total_steps=30000`, `hidden=(64, 64)`): what the
    Python API and an experiment file's cells give. Defaults < `environ`'s SILCR_* variables (none
    unless given) < `options`; each value type-checked as a --config file's is, then validated as the
    command line is. A bad one raises ConfigError naming it (`--total-steps: must be >= 1, got 0`)."""
    values = load_environ(environ or {}, role)
    for key, value in options.items():
        name = key.replace("-", "_")
        if name not in FIELDS or role not in FIELDS[name].metadata["roles"]:
            raise ConfigError(option_name(name), f"not an option of `silcr {role}`")
        values[name] = _coerce(name, list(value) if isinstance(value, tuple) else value, "")
    return _checked(values, role)


def _checked(values: dict[str, Any], role: str) -> Config:
    cfg = Config(**values)
    if role == "train" and not cfg.run:
        cfg.run = default_run_name(cfg.env, cfg.algo)
    validate(cfg, role)
    cfg.critic_norm, cfg.q_target_clip = critics_of(cfg)  # config.toml records what ran, not "auto"
    return cfg


def default_run_name(env: str, algo: str) -> str:
    """`<env>-<algo>-<date>-<time>-<4 hex digits>`: the run name when none is given (the command line's and the
    Python API's alike); the random end keeps two runs started in the same second apart."""
    import re
    import secrets

    short = re.sub(r"[^A-Za-z0-9_.-]", "_", env.rsplit(":", 1)[-1].rsplit("/", 1)[-1])[:24]
    return f"{short}-{algo}-{time.strftime('%Y%m%d-%H%M%S')}-{secrets.token_hex(2)}"


def critics_of(cfg: Config) -> tuple[str, str]:
    """The run's `--critic-norm` and `--q-target-clip`, with `auto` (both defaults) resolved for its algorithm.
    Both options together held Humanoid's critics, and the labelled algorithms are the ones measured with
    them (RESULTS.md, "Critics that stay bounded"); an env reward has no known bound to clip at, and SAC's
    critics stayed under theirs without either, so the env-reward algorithms keep plain critics."""
    bounded = algorithms.algorithm(cfg.algo).labels_bounded
    norm = cfg.critic_norm if cfg.critic_norm != "auto" else ("layer" if bounded else "none")
    clip = cfg.q_target_clip if cfg.q_target_clip != "auto" else ("bound" if bounded and cfg.gamma < 1 else "none")
    return norm, clip


def actor_zenoh_mode(cfg: Config) -> str:
    """The Zenoh mode of the actors `silcr train` starts (--actor-zenoh-mode, resolved)."""
    if cfg.zenoh_mode == "client":
        return "client"  # everything through the router already
    if cfg.actor_zenoh_mode != "auto":
        return cfg.actor_zenoh_mode
    return "peer" if cfg.actors <= PEER_ACTORS_MAX else "client"


#: The range of each option on its own (whatever the others are): checked for every source of values, so a
#: bad value in a --config file is refused even when the command line overrides it (issue 42).
_AT_LEAST = {name: 1 for name in ("online_capacity", "expert_capacity", "total_steps", "weights_interval",
                                  "eval_interval", "checkpoint_interval", "actors", "envs_per_actor",
                                  "batches_per_request", "requests_in_flight", "weights_poll_steps", "disc_batch_size",
                                  "disc_interval", "recent_window", "spi_tolerance")} | {
    "batch_size": 2, "eval_episodes": 0, "final_eval_episodes": 0, "disc_warmup": 0, "learning_starts": 0,
    "actor_id": -1, "torch_threads": 0, "bc_weight": 0, "max_restarts": 0, "grad_clip": 0, "gasil_alpha": 0, "disc_grad_penalty": 0, "weights_fanout_mb_s": 0,
    "buffer_checkpoint_interval": 0}
_AT_MOST = {"batches_per_request": 64}
_ABOVE_ZERO = ("samples_per_insert", "lr", "init_alpha", "disc_lr", "stats_interval", "actor_outbox_mb")
_ZERO_TO_ONE = ("gamma", "tau", "target_entropy_scale")  # (0, 1]
_LAYERS = ("hidden", "disc_hidden")
TARGET_ENTROPY_PER_DIM_MAX = 0.6931471805599453  # log 2: a uniform action on (-1, 1), per dimension


def value_problem(name: str, value: Any) -> str | None:
    """What is wrong with `value` for option `name` on its own (None: nothing)."""
    if name in _AT_LEAST and not value >= _AT_LEAST[name]:  # `not >=`: a NaN is refused too
        return f"must be >= {_AT_LEAST[name]}, got {value}"
    if name in _AT_MOST and value > _AT_MOST[name]:
        return f"must be <= {_AT_MOST[name]}, got {value}"
    if name in _ABOVE_ZERO and not value > 0:
        return f"must be > 0, got {value}"
    if name in _ZERO_TO_ONE and not 0 < value <= 1:
        return f"must be in (0, 1], got {value}"
    if name == "target_entropy_per_dim" and not value < TARGET_ENTROPY_PER_DIM_MAX:
        return f"must be below log 2 = {TARGET_ENTROPY_PER_DIM_MAX:.4f} (a squashed action's most), got {value}"
    if name in _LAYERS and (not value or any(h < 1 for h in value)):
        return f"needs one or more positive layer sizes, got {value}"
    if name == "run" and value:
        try:
            validate_run_name(value)
        except ValueError as e:
            return str(e)
    return None


def check_values(values: Mapping[str, Any], label: Callable[[str], str] = option_name) -> None:
    """Each of `values` (one source: a --config file, the environment, the command line) in its own range;
    ConfigError naming the first bad one as `label(name)` says (`--tau`, `run.toml: tau`, `SILCR_TAU`)."""
    for name, value in values.items():
        problem = value_problem(name, value)
        if problem is not None:
            raise ConfigError(label(name), problem)


def validate(cfg: Config, role: str) -> None:
    if not cfg.run and role != "health":  # `silcr health` reads the run from the heartbeat
        raise ConfigError("--run", "a run name is required")
    check_values(cfg.to_dict())
    algo = algorithms.algorithm(cfg.algo)
    for name in algorithms.ALGORITHM_OPTIONS:
        # An option only other algorithms use does nothing here: say so rather than ignore it.
        if name not in algo.options and role in FIELDS[name].metadata["roles"] and getattr(cfg, name) != default_of(name):
            users = " or ".join(f"--algo {a}" for a in algorithms.taking(name))
            raise ConfigError(option_name(name), f"only {users} uses it (got --algo {cfg.algo})")
    if role in ("train", "buffer"):
        if algo.needs_demos and not cfg.demos:
            raise ConfigError("--demos", f"--algo {cfg.algo} needs a demonstrations file (make one with "
                                         f"`silcr demos CHECKPOINT -o demos.npz`)")
        for name in ("demos", "expert_init"):
            if getattr(cfg, name) and not Path(getattr(cfg, name)).is_file():
                raise ConfigError(option_name(name), f"no such file: {getattr(cfg, name)}")
    if cfg.absorbing_terminal and algo.uses_env_reward:
        raise ConfigError("--absorbing-terminal", f"--algo {cfg.algo} learns from the env's reward, which an absorbing "
                                                  f"state would pay forever; it is for the labelled algorithms "
                                                  f"({', '.join(a.name for a in algorithms.ALGORITHMS.values() if not a.uses_env_reward)})")
    if cfg.q_target_clip == "bound" and not algo.labels_bounded:
        raise ConfigError("--q-target-clip", f"--algo {cfg.algo} learns from the env's reward, whose largest value "
                                             f"is not known, so no soft-Q bound can be computed; it is for the "
                                             f"labelled algorithms ({', '.join(a.name for a in algorithms.ALGORITHMS.values() if a.labels_bounded)})")
    if cfg.q_target_clip == "bound" and cfg.gamma >= 1:
        raise ConfigError("--q-target-clip", "needs --gamma below 1 (the soft-Q bound is r_max / (1 - gamma))")
    if cfg.absorbing_terminal and cfg.gamma >= 1:
        raise ConfigError("--absorbing-terminal", "needs --gamma below 1 (an absorbing state's value is r / (1 - gamma))")
    if cfg.env in EPISODIC_IDS and algo.uses_env_reward and cfg.reward == "dense":
        raise ConfigError("--reward", f"{cfg.env} is {EPISODIC_IDS[cfg.env]} with the episodic reward; for the dense "
                                      f"reward use --env {EPISODIC_IDS[cfg.env]}")
    if cfg.learning_starts >= cfg.online_capacity:
        raise ConfigError("--learning-starts", f"must be below --online-capacity ({cfg.online_capacity})")
