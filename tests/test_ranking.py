"""The ranking is tested: if D_E stops keeping the best episodes by return, this fails.

Task: `silcr/PointGoal-v0` (common/point_goal.py): every episode lasts 50 steps and
pays only at its end, minus the distance to a goal, so surviving earns nothing and
constant rewards on D_E help only through what D_E holds. The control keeps D_E the
same size but fills it with the latest episodes (`--expert-admission recent`).

Measured on the 2-core machine (docs/testing.md): the untrained policy ends about
1.0 from the goal. SILCR ends within 0.06 by 7,500 steps; the recency control
wanders (1.2 to 1.9 over the same steps). With D_E ranked by a random key instead
of the return (a deliberately broken ranking) this test fails.
"""

from __future__ import annotations

import csv
import subprocess
import sys

import pytest

from tests.helpers import REPO

RUN = ["--single-process", "--env", "silcr/PointGoal-v0", "--hidden", "64", "64", "--learning-starts", "1000",
       "--total-steps", "10000", "--expert-capacity", "250", "--tau", "0.005", "--eval-interval", "2500",
       "--eval-episodes", "10", "--seed", "0", "--torch-threads", "1"]
SILCR_FINAL_DISTANCE = 0.25  # the untrained policy's is about 1.0
MARGIN = 0.3  # the recency control must end at least this much farther away


def _final_distance(tmp_path, admission: str) -> tuple[float, list[float]]:
    r = subprocess.run([sys.executable, "-m", "silcr.cli", "train", *RUN, "--expert-admission", admission,
                        "--runs-dir", str(tmp_path), "--run", admission], capture_output=True, text=True, cwd=REPO,
                       timeout=900)
    assert r.returncode == 0, r.stdout + r.stderr
    distances = [-float(row["eval_return"]) for row in csv.DictReader(open(tmp_path / admission / "progress.csv"))]
    return sum(distances[-2:]) / 2, distances


@pytest.mark.slow
def test_silcr_beats_the_same_expert_buffer_filled_by_recency(tmp_path):
    silcr, silcr_curve = _final_distance(tmp_path, "return")
    recent, recent_curve = _final_distance(tmp_path, "recent")
    assert silcr_curve[0] > 0.5, silcr_curve  # the untrained policy is far from the goal
    assert silcr <= SILCR_FINAL_DISTANCE, f"SILCR did not reach the goal: distances {silcr_curve}"
    assert recent - silcr >= MARGIN, f"the ranking made no difference: SILCR {silcr_curve}, recency {recent_curve}"
