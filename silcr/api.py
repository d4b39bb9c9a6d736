"""The Python API, in Stable-Baselines3's shape: build a model, `learn`, `save`, `load`, `predict`.

    from silcr import SILCR
    model = SILCR("Hopper-v5", hidden=(256, 256), expert_capacity=5000)
    model.learn(200_000)
    model.save("hopper.silcr")
    action, _ = SILCR.load("hopper.silcr").predict(obs, deterministic=True)

One class per algorithm of the registry (`silcr.common.algorithms`), generated from it:
`SILCR`, `SAC`, `SQIL`, `GASIL`, `IRCR`. Discrete actions need no class of their own: the
env's action space picks the update, as on the command line. Below this module the API and
`silcr train` share one path: the options are checked by `config.from_options` and
`deploy.preflight` (the CLI's `resolve` and the same checks), and a run is the CLI's run:
`deploy.single_process.SingleProcessRun` with `actors=0`, `deploy.launch.train` (router,
buffer, learner, actors as processes) with `actors=N`, writing the same run directory.
"""

from __future__ import annotations

import contextlib
import re
import warnings
from pathlib import Path
from typing import Any, Callable, ClassVar

import numpy as np

from silcr.learner import model_file
from silcr.common.algorithms import ALGORITHMS, algorithm
from silcr.common.config import FIELDS, Config, ConfigError, absent_values, default_run_name, from_options
from silcr.training import DistributedTraining, InProcessTraining

#: Options the constructor's own arguments and `learn` set; passing them as options is refused.
_OWNED = {"env": "the first argument", "algo": "the class", "seed": "seed=", "actors": "actors=",
          "single_process": "actors=0", "run": "run=", "runs_dir": "runs_dir=", "device": "device=",
          "resume": "learn(), which goes on from the last one", "total_steps": "learn(total_steps)"}
class Callback:
    """Called after each evaluation with its progress.csv row (`row`: the column names as keys);
    returning False stops training cleanly (checkpoints written, the model usable). A plain
    function `callback(info)` works too: `info` is {"row": row, "model": model}."""

    def on_evaluation(self, row: dict[str, Any], model: "Model") -> bool:
        return True


def _as_callback(callback: Callable[[dict[str, Any]], Any] | Callback | None, model: "Model"):
    if callback is None:
        return None
    if isinstance(callback, Callback):
        return lambda row: callback.on_evaluation(row, model) is not False
    if callable(callback):
        return lambda row: callback({"row": row, "model": model}) is not False
    raise ValueError(f"callback: a function or a silcr.api.Callback, got {type(callback).__name__}")


def _python_error(e: ConfigError) -> ValueError:
    """A CLI option error (`--hidden: ...`) as the Python API names the option (`hidden: ...`)."""
    name = e.option[2:].replace("-", "_") if e.option.startswith("--") else e.option
    return ValueError(f"{name}: {str(e).split(': ', 1)[1] if ': ' in str(e) else e}")


def env_reference(env: Any, actors: int) -> str:
    """What `env` is as the run's `--env`: a gymnasium id as given, an importable callable as
    `module:qualname` (every process imports it), and with `actors=0` any other callable,
    registered in this process as `silcr-api/<name>-v0`."""
    import gymnasium as gym

    if isinstance(env, str):
        if not env:
            raise ValueError("env: an empty environment id")
        return env
    if isinstance(env, gym.Env):
        raise ValueError("env: give the env's gymnasium id or a zero-argument callable that makes it (each actor "
                         "makes its own env), not an env instance")
    if not callable(env):
        raise ValueError(f"env: a gymnasium id or a zero-argument callable returning a gymnasium.Env, got "
                         f"{type(env).__name__}")
    module, qualname = getattr(env, "__module__", None), getattr(env, "__qualname__", None)
    if module and qualname and module != "__main__" and "<" not in qualname:
        from silcr.common.envs import factory_of

        ref = f"{module}:{qualname}"
        with contextlib.suppress(ValueError):
            if factory_of(ref) is env:
                return ref
    if actors > 0:
        raise ValueError(f"env: {env!r} cannot be imported by the actor processes (a lambda, a local function, "
                         f"a partial or a name defined in __main__); define it at the top level of a module, or "
                         f"train with actors=0")
    name = re.sub(r"[^A-Za-z0-9_.]", "_", f"{module or 'env'}.{qualname or type(env).__name__}")[-48:]
    env_id = f"silcr-api/{name}-v0"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # registering again (a second model of the same callable) is intended
        gym.register(id=env_id, entry_point=env)
    return env_id


def _run_name(algo: str, env_id: str) -> str:
    return default_run_name(env_id, algo)  # the command line's scheme


def _algorithm_doc(name: str) -> str:
    a = ALGORITHMS[name]
    return (f"{a.summary} ({a.source}).\n\nA silcr model in Stable-Baselines3's shape: "
            f"{name.upper()}(env, actors=0, seed=0, run=None, device='cpu', **options), then learn, save, load, "
            f"predict (docs/api.md).")


class Model:
    """An algorithm of silcr's registry, trained in this process (`actors=0`) or by the distributed system
    (`actors=N`: a router, the buffer service, the learner and N actors as processes, stopped on return)."""

    algo: ClassVar[str] = ""

    def __init_subclass__(cls, **kwargs: Any) -> None:
        """A class named after a registry entry (`SILCR`) is that algorithm's; a user's subclass of one keeps it."""
        super().__init_subclass__(**kwargs)
        if not cls.algo:
            cls.algo = algorithm(cls.__name__.lower()).name  # ValueError naming the registry's algorithms
            cls.__doc__ = _algorithm_doc(cls.algo)

    def __init__(self, env: str | Callable[[], Any], *, actors: int = 0, seed: int = 0, run: str | None = None,
                 device: str = "cpu", runs_dir: str | Path = "runs", **options: Any) -> None:
        """`env`: a gymnasium id (`"Hopper-v5"`, `"module:Env-v0"`) or a zero-argument callable returning a
        gymnasium.Env. `options`: every `silcr train` option by its Python name (`hidden=(256, 256)`,
        `learning_starts=5000`, `expert_capacity=5000`, `tau=0.005`, ...), checked as the command line
        checks them: a bad one raises ValueError naming it, before anything is started or written."""
        if not self.algo:
            raise TypeError("Model is the base class: use silcr.SILCR, silcr.SAC, ... (one per algorithm)")
        if isinstance(actors, bool) or not isinstance(actors, int) or actors < 0:
            raise ValueError(f"actors: an integer >= 0 (0: train in this process), got {actors!r}")
        for key in options:
            if key.replace("-", "_") in _OWNED:
                raise ValueError(f"{key}: set by {_OWNED[key.replace('-', '_')]}, not as an option")
        env_id = env_reference(env, actors)
        values = {**options, "env": env_id, "algo": self.algo, "seed": seed, "device": device,
                  "runs_dir": str(runs_dir), "actors": max(actors, 1), "single_process": actors == 0,
                  "run": run or _run_name(self.algo, env_id)}
        from silcr.common.envs import EnvSpec

        cfg = _checked(values)
        self._start(cfg, actors, EnvSpec.of(cfg.env))
        self._pick_port = "zenoh_listen" not in options  # a free port for each distributed learn

    def _start(self, cfg: Config, actors: int, spec: Any, weights: Any = None, steps: int = 0,
               trainable: bool = True) -> None:
        self.cfg, self.actors, self.spec = cfg, actors, spec
        self._session: InProcessTraining | None = None  # an actors=0 model's run, from its first learn to close()
        self._weights = weights  # the policy of a loaded or distributed model
        self._steps = steps  # env steps trained on (a loaded or distributed model's; a live run counts its own)
        self._trainable = trainable
        self._rng = np.random.default_rng(cfg.seed)
        self._pick_port = True

    # -- facts ------------------------------------------------------------------------------------
    @property
    def run_dir(self) -> Path:
        """The run directory: config.toml, progress.csv, TensorBoard events, checkpoints, logs."""
        return self.cfg.run_dir

    @property
    def env_id(self) -> str:
        return self.cfg.env

    @property
    def observation_space(self):
        return self.spec.observation_space

    @property
    def action_space(self):
        return self.spec.action_space

    @property
    def num_timesteps(self) -> int:
        """Env steps trained on so far (SB3's name)."""
        return self._session.env_steps if self._session is not None else self._steps

    # -- learn ------------------------------------------------------------------------------------
    def learn(self, total_steps: int, *, callback: Callable[[dict[str, Any]], Any] | Callback | None = None,
              progress_bar: bool = False) -> "Model":
        """Train for `total_steps` more env steps; a second call goes on from where the first stopped (the
        same D_O, D_E and counters, as `silcr train --resume` does). `callback` is called after each
        evaluation; returning False stops training cleanly. Ctrl-C stops it too (checkpoints written)
        and raises KeyboardInterrupt; no process is left behind either way."""
        _check_learn(total_steps, self._trainable)
        on_row = _as_callback(callback, self)
        self.cfg.total_steps = self.num_timesteps + int(total_steps)
        if self.actors == 0:
            if self._session is None:
                self._session = InProcessTraining(self.cfg)
            self._session.learn(on_row, progress_bar)
        else:  # a second learn goes on from the checkpoints; a free port unless the user named one
            run = DistributedTraining(self.cfg, resume=self._steps > 0, free_port=self._pick_port)
            try:
                run.learn(on_row, progress_bar)
            finally:  # also after Ctrl-C or a callback's exception: the model keeps what its checkpoint holds
                if run.weights is not None:
                    self._weights, self._steps = run.weights, run.env_steps
        return self

    # -- predict -----------------------------------------------------------------------------------
    def policy_weights(self):
        """The actor network now (`protocol.Weights`): the live learner's, a loaded file's, or the untrained one."""
        if self._session is not None:
            return self._session.weights()
        if self._weights is None:
            from silcr.actor.policy import initial_weights

            self._weights = initial_weights(self.spec.obs_dim, self.spec.act_dim, self.cfg.hidden, self.cfg.seed,
                                            self.spec.n_actions)
        return self._weights

    def predict(self, observation: Any, state: Any = None, episode_start: Any = None,
                deterministic: bool = True) -> tuple[np.ndarray, None]:
        """The policy's action for one observation (obs_dim,) or a batch (n, obs_dim), in the env's action
        space (continuous actions mapped from [-1, 1] to its bounds, discrete ones as indices), and None
        for the state: Stable-Baselines3's signature, so its `evaluate_policy` runs on a model unchanged.
        `deterministic`: tanh of the mean, or the most likely action; otherwise a sample."""
        from silcr.actor.policy import policy_for

        obs = np.asarray(observation, dtype=np.float32)
        single = obs.shape == (self.spec.obs_dim,)
        if not single and (obs.ndim != 2 or obs.shape[1] != self.spec.obs_dim):
            raise ValueError(f"observation: shape ({self.spec.obs_dim},) or (n, {self.spec.obs_dim}) for "
                             f"{self.env_id}, got {obs.shape}")
        policy = policy_for(self.policy_weights(), self.spec)
        batch = obs[None] if single else obs
        actions = policy.deterministic(batch) if deterministic else policy.sample(batch, self._rng)
        env_actions = self.spec.to_env_action(actions)
        return (env_actions[0] if single else env_actions), None

    # -- save and load ---------------------------------------------------------------------------------
    def save(self, path: str | Path, include_training_state: bool = False) -> None:
        """One file with the configuration, the actor's weights and the spaces (`silcr.model_file`); with
        `include_training_state` also the critics, optimisers, counters and both buffers, to train on later."""
        training = None
        if include_training_state:
            if self._session is not None:
                self._session.checkpoint()  # both checkpoints hold this moment
            training = model_file.training_state(self.run_dir)
        model_file.write(Path(path), self.algo, self.cfg.to_dict(), self.policy_weights(), self.spec, training,
                         env_steps=self.num_timesteps)

    @classmethod
    def load(cls, path: str | Path, env: str | Callable[[], Any] | None = None, *, include_training_state: bool = False,
             run: str | None = None, runs_dir: str | Path = "runs", device: str = "cpu") -> "Model":
        """A model from `save`'s file, ready to `predict`. `env` replaces the saved env (a callable must be
        given again when it was not importable); `include_training_state` restores the critics and buffers
        too, into a new run directory, so that `learn` goes on from where the saved model stopped."""
        payload = model_file.read(Path(path))
        if payload["algo"] != cls.algo:
            other = next((c.__name__ for c in MODELS.values() if c.algo == payload["algo"]), payload["algo"])
            raise model_file.ModelFileError(f"{path} holds a {payload['algo']} model, not {cls.algo}: load it with "
                                            f"silcr.{other}.load")
        cfg, actors, spec = _saved_run(payload, env)
        cfg.device, cfg.runs_dir, cfg.run = device, str(runs_dir), run or _run_name(cls.algo, cfg.env)
        steps = int(payload.get("env_steps", (payload.get("evaluation") or {}).get("env_steps", 0)))  # num_timesteps
        if include_training_state:
            if payload.get("training") is None:
                raise model_file.ModelFileError(f"{path} was saved without its training state "
                                                f"(save it with include_training_state=True)")
            steps = model_file.restore_training(payload["training"], cfg.run_dir)
            cfg.resume = True
        model = cls.__new__(cls)
        model._start(cfg, actors, spec, model_file.weights_of(payload["policy"]), steps, include_training_state)
        return model

    # -- lifecycle ---------------------------------------------------------------------------------
    def close(self) -> None:
        """Write an actors=0 model's last checkpoints, release its run directory (also at exit); OSError once if one failed."""
        if self._session is not None:
            self._weights, self._steps = self._session.weights(), self._session.env_steps
            session, self._session = self._session, None
            self.cfg.resume = True  # a later learn goes on from the checkpoints just written
            session.close()

    def __enter__(self) -> "Model":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.env_id!r}, actors={self.actors}, run_dir={str(self.run_dir)!r})"


def _check_learn(total_steps: Any, trainable: bool) -> None:
    if isinstance(total_steps, bool) or not isinstance(total_steps, (int, np.integer)) or total_steps < 1:
        raise ValueError(f"total_steps: an integer >= 1, got {total_steps!r}")
    if not trainable:
        raise ValueError("this model was loaded for predict only: load it with include_training_state=True to "
                         "train it further")


def _saved_run(payload: dict[str, Any], env: Any) -> tuple[Config, int, Any]:
    """A model file's configuration, actors and env spec, with `env` (if given) in place of the saved one."""
    # A setting the file lacks ran as it did before the option existed (critics saved before LayerNorm was the default)
    cfg = Config(**(absent_values() | {k: v for k, v in payload["config"].items() if k in FIELDS}))
    actors = 0 if cfg.single_process else cfg.actors
    spec = model_file.spec_of(payload["spec"])
    if env is not None:
        cfg.env, spec = _env_like(env, actors, spec)
    return cfg, actors, spec


def _env_like(env: Any, actors: int, saved: Any) -> tuple[str, Any]:
    """`env` as the run's --env and its spec, which must have the saved policy's shapes."""
    from silcr.common.envs import EnvSpec

    env_id = env_reference(env, actors)
    given = EnvSpec.of(env_id)
    if (given.obs_dim, given.act_dim, given.n_actions) != (saved.obs_dim, saved.act_dim, saved.n_actions):
        raise ValueError(f"env: {env_id} has observations of {given.obs_dim} and actions of "
                         f"{given.n_actions or given.act_dim}; the saved policy's are {saved.obs_dim} and "
                         f"{saved.n_actions or saved.act_dim}")
    return env_id, given


def _checked(values: dict[str, Any]) -> Config:
    """The options as `silcr train` checks them (values, then what needs the env and the machine)."""
    from silcr.deploy import preflight

    try:
        cfg = from_options(values, "train")
        preflight.check(cfg, "train")
    except ConfigError as e:
        raise _python_error(e) from None
    return cfg


# One class per algorithm of the registry, written out so that IDEs and type checkers see them; each takes
# its algorithm from its name (`Model.__init_subclass__`), and tests/test_api.py checks that they are exactly
# the registry's.
class SILCR(Model):
    pass


class SAC(Model):
    pass


class SQIL(Model):
    pass


class GASIL(Model):
    pass


class IRCR(Model):
    pass


#: The classes by name (`SILCR`, `SAC`, ...).
MODELS: dict[str, type[Model]] = {c.__name__: c for c in (SILCR, SAC, SQIL, GASIL, IRCR)}
__all__ = ["Model", "Callback", *MODELS]
