"""The actors' copy of the policy, in NumPy: tanh-Gaussian for continuous actions, categorical for discrete ones.

Actors never import torch: inference at batch size 1-16 on 800-400 layers is a
few matrix-vector products, NumPy does them as fast, and an actor process stays
small (no torch runtime, no thread pool fighting the learner for the 2 cores).
The layouts mirror `learner.sac.Actor`'s and `learner.sac_discrete.CategoricalActor`'s
state_dicts; tests check both agree.
"""

from __future__ import annotations

import numpy as np

from silcr.common.protocol import ProtocolError, Weights

LOG_STD_MIN, LOG_STD_MAX = -20.0, 2.0


def _hidden_layers(p: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The trunk's (in x out weight, bias) pairs, in order (`trunk.0`, `trunk.2`, ...: Linear, ReLU, ...)."""
    layers = []
    i = 0
    while f"trunk.{i}.weight" in p:
        layers.append((p[f"trunk.{i}.weight"].T.copy(), p[f"trunk.{i}.bias"].copy()))
        i += 2
    if not layers:
        raise ProtocolError("bad_field", "weights have no hidden layers")
    return layers


def _head(p: dict[str, np.ndarray], name: str) -> tuple[np.ndarray, np.ndarray]:
    try:
        return p[f"{name}.weight"].T.copy(), p[f"{name}.bias"].copy()
    except KeyError as e:
        raise ProtocolError("bad_field", f"weights lack {e.args[0]!r}") from None


def _check_chain(layers: list[tuple[np.ndarray, np.ndarray]], head: tuple[np.ndarray, np.ndarray], obs_dim: int,
                 outputs: int, what: str) -> None:
    """Every matrix 2-D and every bias 1-D, each layer feeding the next, `obs_dim` in and `outputs` out."""
    if any(w.ndim != 2 or b.ndim != 1 for w, b in [*layers, head]):
        raise ProtocolError("bad_shape", "weights need 2-D matrices and 1-D biases")
    if layers[0][0].shape[0] != obs_dim or head[0].shape[1] != outputs:
        raise ProtocolError("bad_shape", f"weights are for obs {layers[0][0].shape[0]} / {what} {head[0].shape[1]}, "
                                         f"env has {obs_dim} / {outputs}")
    for (w, b), (w2, _) in zip(layers, layers[1:] + [head]):
        if w.shape[1] != b.shape[0] or w.shape[1] != w2.shape[0]:
            raise ProtocolError("bad_shape", "weights' layer shapes do not chain")
    if head[1].shape != (outputs,):
        raise ProtocolError("bad_shape", f"the output layer has {head[1].shape[0]} biases, expected {outputs}")


def _trunk_forward(layers: list[tuple[np.ndarray, np.ndarray]], obs: np.ndarray) -> np.ndarray:
    # In place after each matmul: at batch 1-16 the temporaries of `relu(h @ w + b)`
    # cost as much as the small layers themselves.
    h = np.asarray(obs, dtype=np.float32)
    for w, b in layers:
        h = h @ w
        h += b
        np.maximum(h, 0.0, out=h)
    return h


class NumpyPolicy:
    """The tanh-Gaussian policy (continuous actions in [-1, 1])."""

    def __init__(self, weights: Weights, obs_dim: int, act_dim: int) -> None:
        p = weights.params
        self.version = weights.version
        self.mean = _head(p, "mean")
        self.log_std = _head(p, "log_std")
        layers = _hidden_layers(p)
        _check_chain(layers, self.mean, obs_dim, act_dim, "act")
        if self.log_std[0].shape != self.mean[0].shape or self.log_std[1].shape != (act_dim,):
            raise ProtocolError("bad_shape", f"the log_std head is {self.log_std[0].shape[0]} -> {self.log_std[0].shape[1]} "
                                             f"with {self.log_std[1].shape[0]} biases, expected "
                                             f"{self.mean[0].shape[0]} -> {act_dim}")
        self.layers = layers
        # Both heads in one matmul: one BLAS call fewer per step, and the heads' output
        # is a single array the sampling below works on in place.
        self.act_dim = act_dim
        self.head_w = np.ascontiguousarray(np.concatenate([self.mean[0], self.log_std[0]], axis=1))
        self.head_b = np.concatenate([self.mean[1], self.log_std[1]])

    def _heads(self, obs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out = _trunk_forward(self.layers, obs) @ self.head_w
        out += self.head_b
        mean, log_std = out[..., : self.act_dim], out[..., self.act_dim :]
        np.clip(log_std, LOG_STD_MIN, LOG_STD_MAX, out=log_std)
        return mean, log_std

    def sample(self, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Stochastic action tanh(mean + std * noise) in [-1, 1], as the learner's `Actor.sample`."""
        mean, log_std = self._heads(obs)
        u = np.exp(log_std)
        u *= rng.standard_normal(mean.shape, dtype=np.float32)
        u += mean
        return np.tanh(u, out=u)

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        return np.tanh(self._heads(obs)[0])

    def outputs(self, obs: np.ndarray) -> np.ndarray:
        """The heads' raw values (means and log-stds) before any squashing or clipping hides a NaN or an inf."""
        return _trunk_forward(self.layers, obs) @ self.head_w + self.head_b


class CategoricalPolicy:
    """The categorical policy over `n_actions` action indices (the learner's `CategoricalActor`).

    Actions come out as int64 indices with a trailing axis of 1, the width the buffer stores:
    rows of observations give (rows, 1), one observation gives (1,).
    """

    def __init__(self, weights: Weights, obs_dim: int, n_actions: int) -> None:
        p = weights.params
        self.version = weights.version
        self.head = _head(p, "logits")
        self.layers = _hidden_layers(p)
        _check_chain(self.layers, self.head, obs_dim, n_actions, "actions")
        self.n_actions = n_actions

    def logits(self, obs: np.ndarray) -> np.ndarray:
        out = _trunk_forward(self.layers, obs) @ self.head[0]
        out += self.head[1]
        return out

    def sample(self, obs: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """a ~ pi(.|s) by the Gumbel-max trick: argmax of the logits plus Gumbel noise is a draw from softmax(logits)."""
        z = self.logits(obs)
        z += rng.gumbel(size=z.shape).astype(np.float32)
        return z.argmax(-1)[..., None]

    def deterministic(self, obs: np.ndarray) -> np.ndarray:
        """The most likely action."""
        return self.logits(obs).argmax(-1)[..., None]

    def outputs(self, obs: np.ndarray) -> np.ndarray:
        return self.logits(obs)


Policy = NumpyPolicy | CategoricalPolicy


def policy_for(weights: Weights, spec) -> Policy:
    """The actors' policy for `spec`'s env (an `EnvSpec`) from `weights`; ProtocolError if they do not fit it."""
    if weights.action_kind != spec.action_kind:
        raise ProtocolError("action_kind", f"weights are a {weights.action_kind} policy, the run's env has "
                                           f"{spec.action_kind} actions")
    if spec.discrete:
        return CategoricalPolicy(weights, spec.obs_dim, spec.n_actions)
    return NumpyPolicy(weights, spec.obs_dim, spec.act_dim)


def initial_weights(obs_dim: int, act_dim: int, hidden: list[int], seed: int, n_actions: int = 0) -> Weights:
    """PyTorch's default Linear init (uniform +-1/sqrt(fan_in)), for an actor with no learner yet.

    With `n_actions`, a categorical policy's (one `logits` head); otherwise a tanh-Gaussian's.
    """
    rng = np.random.default_rng(seed)
    params: dict[str, np.ndarray] = {}
    sizes = [obs_dim, *hidden]

    def linear(name: str, fan_in: int, fan_out: int) -> None:
        bound = 1.0 / np.sqrt(fan_in)
        params[f"{name}.weight"] = rng.uniform(-bound, bound, (fan_out, fan_in)).astype(np.float32)
        params[f"{name}.bias"] = rng.uniform(-bound, bound, fan_out).astype(np.float32)

    for i in range(len(hidden)):
        linear(f"trunk.{2 * i}", sizes[i], sizes[i + 1])
    if n_actions:
        linear("logits", hidden[-1], n_actions)
        arch = {"obs_dim": obs_dim, "n_actions": n_actions, "hidden": list(hidden), "action_kind": "discrete"}
        return Weights(-1, params, arch, action_kind="discrete")
    linear("mean", hidden[-1], act_dim)
    linear("log_std", hidden[-1], act_dim)
    return Weights(-1, params, {"obs_dim": obs_dim, "act_dim": act_dim, "hidden": list(hidden)})


def probe_observations(obs_dim: int) -> np.ndarray:
    """Observations every new policy is tried on before an actor acts with it: zeros and wide normal draws."""
    rng = np.random.default_rng(0)
    return np.concatenate([np.zeros((1, obs_dim)), 10.0 * rng.standard_normal((7, obs_dim))]).astype(np.float32)


def usable_policy(weights: Weights, spec) -> Policy:
    """`policy_for`, refused (ProtocolError "non_finite_output") when its outputs on `probe_observations` are NaN or
    infinite: weights finite to the wire's check can still overflow float32 in a forward pass (values near 3e38),
    and an actor acting with them would produce NaN actions, hence episodes the buffer must refuse."""
    policy = policy_for(weights, spec)
    with np.errstate(all="ignore"):
        out = policy.outputs(probe_observations(spec.obs_dim))
    if not np.isfinite(out).all():
        raise ProtocolError("non_finite_output", f"weights version {weights.version} give NaN or infinite outputs (a "
                                                 f"forward pass overflows); the actor keeps its last good policy")
    return policy
