"""The algorithms silcr runs, each declared once.

Every algorithm is soft actor-critic fed from the same two tables, D_O (a FIFO of the
agent's episodes) and D_E (an expert table of whole episodes). They differ only in the
facts below, and every role reads them from here: the buffer (what D_E holds, how rows
are labelled, whether batches mix D_E), the learner (whether it trains a discriminator),
the actors (which reward their env pays), the CLI (choices, help, validation), `silcr
plot` (labels, which settings apply) and docs/algorithm.md (its table is `markdown_table()`,
checked by a test). No other module names an algorithm in a literal (tests/test_algorithms.py).

Adding an algorithm is one entry here; a new way of labelling rows is one labeller in
`silcr.buffer_service.labels`, named by `labels`.
"""

from __future__ import annotations

from dataclasses import dataclass

#: What D_E holds: the agent's own best episodes, ranked by return ("own"); a fixed set of
#: demonstrations (`--demos`, "demos"); or nothing ("none": batches come from D_O alone).
EXPERT_SOURCES = ("own", "demos", "none")
#: How a batch's rows get their rewards (`silcr.buffer_service.labels`):
#:   constant  0 for D_O rows, 1 for D_E rows (SILCR's eq. 3; SQIL)
#:   env       the reward the actors' env paid (`--reward dense|episodic`)
#:   credit    IRCR's guidance reward: the row's episode's return per step, min-max
#:             normalised over the episodes now in D_O and D_E
LABELS = ("constant", "env", "credit")
#: The largest label a row can get: D_E's constant 1, the top of IRCR's min-max normalised credit.
LABEL_MAX = 1.0


@dataclass(frozen=True)
class Algorithm:
    name: str
    #: one line for `--help` and the docs table
    summary: str
    #: the paper it comes from
    source: str
    expert: str
    labels: str
    #: each batch takes half its rows from D_E (the rest from D_O)
    mixes_expert: bool
    #: the learner trains GASIL's discriminator (D_E rows against the newest D_O rows)
    discriminator: bool = False
    #: options only this algorithm uses (others refuse them with one line)
    options: tuple[str, ...] = ()
    #: runs on an env with discrete actions (`sac_discrete.py`'s update); the others refuse one with one line
    discrete: bool = True

    def __post_init__(self) -> None:
        if self.expert not in EXPERT_SOURCES or self.labels not in LABELS:
            raise ValueError(f"algorithm {self.name}: expert must be one of {EXPERT_SOURCES}, labels one of {LABELS}")
        if self.mixes_expert and self.expert == "none":
            raise ValueError(f"algorithm {self.name}: batches cannot mix an empty D_E")

    @property
    def ranks_own_episodes(self) -> bool:
        """D_E keeps the agent's best episodes by return (ordered by `--expert-admission`)."""
        return self.expert == "own"

    @property
    def needs_demos(self) -> bool:
        return self.expert == "demos"

    @property
    def keeps_expert(self) -> bool:
        return self.expert != "none"

    @property
    def labels_bounded(self) -> bool:
        """Every row's reward is a label in [0, LABEL_MAX] (constant or credit), so the soft-Q bound is known and
        `--q-target-clip bound` applies; an env's reward has no known range."""
        return self.labels in ("constant", "credit")

    @property
    def uses_env_reward(self) -> bool:
        """The learner sees the env's reward, so `--reward dense|episodic` matters (and labels its runs)."""
        return self.labels == "env"


_GASIL_OPTIONS = ("gasil_alpha", "gasil_reward", "disc_hidden", "disc_lr", "disc_grad_penalty", "disc_batch_size",
                  "disc_interval", "disc_warmup", "recent_window")

ALGORITHMS: dict[str, Algorithm] = {a.name: a for a in (
    Algorithm("silcr", "constant rewards: 0 for D_O rows, 1 for rows of the top-M D_E by return",
              "Chen and Lin (the paper)", expert="own", labels="constant", mixes_expert=True,
              options=("expert_admission", "expert_init", "bc_weight")),
    Algorithm("sac", "plain SAC on the env's reward (--reward dense or episodic), from D_O alone",
              "Haarnoja et al. 2018", expert="none", labels="env", mixes_expert=False),
    Algorithm("sqil", "constant rewards as SILCR, with D_E fixed to demonstrations (--demos)",
              "Reddy et al. 2020", expert="demos", labels="constant", mixes_expert=True, options=("demos", "bc_weight"),
              discrete=False),  # demonstration files hold continuous actions
    Algorithm("gasil", "SAC on the env's reward plus a discriminator's reward for looking like the top-M D_E",
              "Guo et al. 2018", expert="own", labels="env", mixes_expert=False, discriminator=True,
              options=_GASIL_OPTIONS, discrete=False),  # its discriminator reads continuous (s, a) pairs
    Algorithm("ircr", "each row labelled with its episode's return per step, min-max normalised over the episodes in "
              "D_O and D_E; top-M D_E by return, half of each batch from it",
              "Gangwani et al. 2020", expert="own", labels="credit", mixes_expert=True, options=("bc_weight",)),
)}

DEFAULT = "silcr"
#: Every option that only some algorithms use.
ALGORITHM_OPTIONS = tuple(sorted({o for a in ALGORITHMS.values() for o in a.options}))


def algorithm(name: str) -> Algorithm:
    try:
        return ALGORITHMS[name]
    except KeyError:
        raise ValueError(f"unknown algorithm {name!r} (choose from {', '.join(ALGORITHMS)})") from None


def taking(option: str) -> list[str]:
    """The algorithms that use `option`."""
    return [a.name for a in ALGORITHMS.values() if option in a.options]


def markdown_table() -> str:
    """The algorithms as docs/algorithm.md shows them (a test keeps the two equal)."""
    expert = {"own": "the agent's top-M episodes by return", "demos": "demonstrations (`--demos`), fixed", "none": "-"}
    labels = {"constant": "0 (D_O) / 1 (D_E)", "env": "the env's (`--reward`)",
              "credit": "its episode's return per step, min-max normalised over D_O and D_E"}
    lines = ["| `--algo` | D_E holds | rows' reward | batch | discriminator | discrete actions | own options | source |",
             "|---|---|---|---|---|---|---|---|"]
    for a in ALGORITHMS.values():
        options = ", ".join(f"`--{o.replace('_', '-')}`" for o in a.options) or "-"
        lines.append(f"| `{a.name}` | {expert[a.expert]} | {labels[a.labels]} | "
                     f"{'half D_O, half D_E' if a.mixes_expert else 'D_O'} | {'yes' if a.discriminator else '-'} | "
                     f"{'yes' if a.discrete else 'refused'} | "
                     f"{options} | {a.source} |")
    return "\n".join(lines)
