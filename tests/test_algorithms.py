"""The algorithm registry is the one place that says what an algorithm is.

Every role derives its behaviour from `silcr.common.algorithms`; these tests keep it so:
no other module names an algorithm in a literal, the CLI offers exactly the registered
ones, every registered labelling has a labeller, and docs/algorithm.md shows the
registry's own table.
"""

from __future__ import annotations

import ast
from pathlib import Path

import numpy as np
import pytest

from silcr.buffer_service.labels import LABELLERS, labeller_for
from silcr.buffer_service.replay import ReplayState
from silcr.cli import build_parser
from silcr.common import protocol as P
from silcr.common.algorithms import ALGORITHMS, LABELS, algorithm, markdown_table
from silcr.common.config import Config
from silcr.common.envs import EnvSpec
from tests.conftest import make_episode
from tests.helpers import REPO

REGISTRY = REPO / "common" / "algorithms.py"
SOURCES = sorted(p for p in REPO.glob("*/*.py") if p.parent.name not in ("tests", ".venv") and p != REGISTRY)


def algorithm_literals(path: Path, names: set[str], root: Path = REPO) -> list[str]:
    """String constants equal to an algorithm's name, except where they name data rather than an
    algorithm: a dict key, a subscript, `.get()`'s key (the learner checkpoint's "sac" and "gasil"
    sections, named after learner/sac.py and learner/gasil.py) and argparse's `prog` (the program)."""
    tree = ast.parse(path.read_text())
    parent = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
    found = []
    for node in ast.walk(tree):
        if not (isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names):
            continue
        up = parent.get(node)
        if ((isinstance(up, ast.Dict) and node in up.keys) or (isinstance(up, ast.Subscript) and up.slice is node)
                or (isinstance(up, ast.Call) and isinstance(up.func, ast.Attribute) and up.func.attr == "get"
                    and up.args[:1] == [node])
                or (isinstance(up, ast.keyword) and up.arg == "prog")):
            continue
        found.append(f"{path.relative_to(root)}:{node.lineno}: {node.value!r}")
    return found


def test_no_module_but_the_registry_names_an_algorithm():
    assert len(SOURCES) > 40  # the scan sees the code
    found = [hit for path in SOURCES for hit in algorithm_literals(path, set(ALGORITHMS))]
    assert found == [], "decide from the registry (silcr.common.algorithms), not from a name:\n" + "\n".join(found)


def test_the_scan_finds_a_literal_when_there_is_one(tmp_path):
    bad = tmp_path / "bad.py"
    bad.write_text('def f(cfg):\n    return cfg.algo in ("silcr", "gasil") or cfg.algo == "sqil" or {"sac": 1}["sac"]\n')
    assert sorted(algorithm_literals(bad, set(ALGORITHMS), tmp_path)) == [
        "bad.py:2: 'gasil'", "bad.py:2: 'silcr'", "bad.py:2: 'sqil'"]  # the dict key and subscript name data


def test_the_cli_offers_exactly_the_registered_algorithms():
    train = build_parser()[1]["train"]
    action = next(a for a in train._actions if a.dest == "algo")
    assert list(action.choices) == list(ALGORITHMS)
    for name, algo in ALGORITHMS.items():
        assert f"{name}: {algo.summary}" in action.help


@pytest.mark.parametrize("name", sorted(ALGORITHMS))
def test_every_algorithm_has_a_labeller_and_a_buffer(tmp_path, name):
    algo = algorithm(name)
    assert algo.labels in LABELS and set(LABELLERS) == set(LABELS)
    assert labeller_for(algo).copies_env_rewards == algo.uses_env_reward
    demos = {}
    if algo.needs_demos:
        demos = {"demos": str(REPO / "tests" / "golden" / "demos-InvertedPendulum-v5.npz")}
    replay = ReplayState(Config(run="r", env="InvertedPendulum-v5", algo=name, learning_starts=20, expert_capacity=1000,
                                **demos), EnvSpec.of("InvertedPendulum-v5"))
    assert (replay.heap is not None) == algo.keeps_expert
    for i in range(6):
        replay.intake.store(make_episode(10, ret=float(i), seq=i))
    reply = replay.sampler.sample(P.SampleRequest(2, 8))
    assert reply.status == "ok" and reply.meta["algo"] == name
    assert (reply.meta["online_rows"] < 8) == algo.mixes_expert
    assert np.isfinite(reply.batch.rewards).all()


def test_the_docs_show_the_registrys_table():
    assert markdown_table() in (REPO / "docs" / "algorithm.md").read_text()
