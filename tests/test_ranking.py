"""The ranking is tested: if D_E stops keeping the best episodes by return, this fails.

Task: `silcr/PointGoal-v0` (common/point_goal.py): every episode lasts 50 steps and
pays only at its end, minus the distance to a goal, so surviving earns nothing and
constant rewards on D_E help only through what D_E holds. The control keeps D_E the
same size but fills it with the latest episodes (`--expert-admission recent`).

Two seeds of each, compared on their mean: a control reinforces whatever its own
recent episodes did, and now and then that wanders near the goal by chance (seed 2
ended 0.3 from it), so one seed alone could not tell. Measured on the 2-core
machine (docs/testing.md): SILCR ends within 0.05 of the goal, the control 1.2 to
1.7 away; with D_E ranked by a random key instead of the return (a deliberately
broken ranking) this test fails.

`test_discrete_silcr_...` is the same test with discrete actions (issue 19), on
`silcr/PointGoalDiscrete-v0`: the same task with 5 moves (stay, +x, -x, +y, -y).

IRCR (the same two buffers, each row labelled with its episode's normalised return per
step) runs beside them. At this budget it gets near the goal but not to it: its last
two evaluations averaged 0.33 and 0.25 from the goal over the two seeds when first
measured (SILCR: under 0.05), so it is held to beating the control and the untrained
policy, not to SILCR's threshold.
"""

from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from tests.helpers import REPO

RUN = ["--single-process", "--env", "silcr/PointGoal-v0", "--hidden", "64", "64", "--learning-starts", "1000",
       "--total-steps", "10000", "--expert-capacity", "250", "--tau", "0.005", "--eval-interval", "2500",
       "--eval-episodes", "10", "--torch-threads", "1"]
SEEDS = (0, 1)
SILCR_FINAL_DISTANCE = 0.25  # mean over the seeds; the untrained policy ends about 1.0 from the goal
IRCR_FINAL_DISTANCE = 0.5
MARGIN = 0.3  # the recency control must end at least this much farther away, on average
VARIANTS = {"return": ["--expert-admission", "return"], "recent": ["--expert-admission", "recent"],
            "ircr": ["--algo", "ircr"]}


def _distances(run_dir: Path) -> list[float]:
    return [-float(row["eval_return"]) for row in csv.DictReader(open(run_dir / "progress.csv"))]


@pytest.mark.slow
def test_silcr_beats_the_same_expert_buffer_filled_by_recency(tmp_path):
    curves: dict[str, list[list[float]]] = {name: [] for name in VARIANTS}
    for seed in SEEDS:  # the variants of a seed at once
        procs = {adm: subprocess.Popen([sys.executable, "-m", "silcr.cli", "train", *RUN, "--seed", str(seed),
                                        *VARIANTS[adm], "--runs-dir", str(tmp_path), "--run", f"{adm}-{seed}"],
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
                 for adm in curves}
        for adm, p in procs.items():
            out, _ = p.communicate(timeout=900)
            assert p.returncode == 0, out
            curves[adm].append(_distances(tmp_path / f"{adm}-{seed}"))
    final = {adm: sum(sum(c[-2:]) / 2 for c in cs) / len(cs) for adm, cs in curves.items()}  # last two evaluations
    assert all(c[0] > 0.5 for c in curves["return"]), curves  # the untrained policy is far from the goal
    assert final["return"] <= SILCR_FINAL_DISTANCE, f"SILCR did not reach the goal: distances {curves['return']}"
    assert final["recent"] - final["return"] >= MARGIN, f"the ranking made no difference: {curves}"
    assert final["ircr"] <= IRCR_FINAL_DISTANCE and final["recent"] - final["ircr"] >= MARGIN, \
        f"IRCR did not learn the task: {curves['ircr']}"


DISCRETE_RUN = [*RUN[:RUN.index("--env") + 1], "silcr/PointGoalDiscrete-v0", *RUN[RUN.index("--env") + 2:]]
DISCRETE_FINAL_DISTANCE = 0.3
DISCRETE_MARGIN = 0.5


@pytest.mark.slow
def test_discrete_silcr_beats_the_same_expert_buffer_filled_by_recency(tmp_path):
    """Measured when written (2 cores, beside other work): SILCR's last two evaluations averaged 0.14 and
    0.11 from the goal on seeds 0 and 1, the recency control 2.39 and 1.18. With D_E ranked by a random
    key instead of the return this fails (docs/testing.md)."""
    finals: dict[str, list[float]] = {"return": [], "recent": []}
    for seed in SEEDS:
        procs = {adm: subprocess.Popen([sys.executable, "-m", "silcr.cli", "train", *DISCRETE_RUN, "--seed", str(seed),
                                        "--expert-admission", adm, "--runs-dir", str(tmp_path), "--run", f"{adm}-{seed}"],
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
                 for adm in finals}
        for adm, p in procs.items():
            out, _ = p.communicate(timeout=900)
            assert p.returncode == 0, out
            finals[adm].append(sum(_distances(tmp_path / f"{adm}-{seed}")[-2:]) / 2)
    mean = {adm: sum(f) / len(f) for adm, f in finals.items()}
    assert mean["return"] <= DISCRETE_FINAL_DISTANCE, f"discrete SILCR did not reach the goal: {finals}"
    assert mean["recent"] - mean["return"] >= DISCRETE_MARGIN, f"the ranking made no difference: {finals}"
