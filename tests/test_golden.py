"""Golden progress.csv files: a short `--single-process` run per algorithm gives today the numbers it gave when
the file was recorded, to the last digit, outside the wall-clock columns.

They guard against refactors that change results by accident: the runs of a study made before a
refactor stay comparable with those made after it only if this passes. A change that is meant to
change results regenerates them on purpose, and says so in its commit:

    SILCR_REGENERATE_GOLDEN=1 python -m pytest -q tests/test_golden.py

Columns added after a file was recorded are not compared (a new column is not a changed result).

The last digits depend on the machine as well as on the code: the CPU's vector instructions pick
torch's and NumPy's kernels, and their versions change them (on the project's renewed machine of
2026-12-02, an AVX-512 CPU, with the same torch, MuJoCo and gymnasium, the files recorded on the
previous one differed by up to 4e-6 relative after 1,600 steps).
`machine.json` records what the files were recorded on. On that machine (same fingerprint) the
comparison is exact, and catches any change of result (a 0.1% change of the target entropy moves
alpha by 1e-6). Elsewhere floats are compared to a relative 1e-5 (and an absolute 1e-7, for means
of terms that cancel) and counts exactly: that still catches a 1% change of the target entropy
(alpha 1.1e-5 apart), not subtler ones. Regenerating on a new machine restores the exact check.
"""

from __future__ import annotations

import csv
import json
import os
import platform
import shutil
import subprocess

import pytest

from silcr.cli import command
from tests.helpers import REPO

GOLDEN = REPO / "tests" / "golden"
WALL_CLOCK_COLUMNS = {"time", "updates_per_s", "wall_time"}
ENV = "InvertedPendulum-v5"
# Small, but every part runs: two actors with two envs each, D_E full and turning over,
# several weights versions, evaluations and checkpoints.
COMMON = ["--env", ENV, "--hidden", "16", "16", "--learning-starts", "400", "--total-steps", "1600",
          "--eval-interval", "400", "--eval-episodes", "2", "--actors", "2", "--envs-per-actor", "2",
          "--weights-interval", "25", "--checkpoint-interval", "300", "--expert-capacity", "1000",
          "--batch-size", "64", "--seed", "7", "--torch-threads", "1"]
DEMOS = GOLDEN / f"demos-{ENV}.npz"  # 8 episodes of an untrained policy (tests/golden/README.md)
CASES = {
    "silcr": ["--algo", "silcr"],
    "silcr-recent": ["--algo", "silcr", "--expert-admission", "recent"],
    "sac-dense": ["--algo", "sac", "--reward", "dense"],
    "sac-episodic": ["--algo", "sac", "--reward", "episodic"],
    "sqil": ["--algo", "sqil", "--demos", str(DEMOS)],
    "gasil-dense": ["--algo", "gasil", "--reward", "dense", "--disc-batch-size", "32", "--recent-window", "400"],
}


MACHINE = GOLDEN / "machine.json"
RELATIVE_TOLERANCE = 1e-5
ABSOLUTE_TOLERANCE = 1e-7  # GASIL's mean reward near 0: 2e-9 apart across machines, 2e-5 relative


def fingerprint() -> dict[str, object]:
    """What decides the last digits of a run besides the code: the libraries and the CPU features they use."""
    import gymnasium
    import mujoco
    import numpy as np
    import torch

    simd = np.show_config(mode="dicts").get("SIMD Extensions", {}).get("found", [])
    return {"machine": platform.machine(), "torch": torch.__version__, "torch_cpu": torch.backends.cpu.get_cpu_capability(),
            "numpy": np.__version__, "numpy_simd": simd, "mujoco": mujoco.__version__, "gymnasium": gymnasium.__version__}


def _same(golden: str, now: str, exact: bool) -> bool:
    if golden == now or exact:
        return golden == now
    try:
        g, n = float(golden), float(now)
    except ValueError:
        return False
    return abs(g - n) <= RELATIVE_TOLERANCE * max(abs(g), abs(n)) + ABSOLUTE_TOLERANCE


def _rows(path) -> list[dict[str, str]]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.mark.parametrize("case", sorted(CASES))
def test_a_short_run_gives_its_golden_progress_csv(tmp_path, case):
    r = subprocess.run(command("train", "--single-process", "--run", case, "--runs-dir", str(tmp_path), *COMMON,
                               *CASES[case]), capture_output=True, text=True, cwd=REPO, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    got = _rows(tmp_path / case / "progress.csv")
    golden = GOLDEN / f"{case}.csv"
    if os.environ.get("SILCR_REGENERATE_GOLDEN") == "1":
        shutil.copy(tmp_path / case / "progress.csv", golden)
        MACHINE.write_text(json.dumps(fingerprint(), indent=1) + "\n")
        pytest.skip(f"regenerated {golden.relative_to(REPO)}")
    want = _rows(golden)
    assert len(got) == len(want) >= 5
    assert int(got[-1]["updates"]) >= 1100  # it did train
    exact = json.loads(MACHINE.read_text()) == fingerprint()
    how = "exactly" if exact else f"to a relative {RELATIVE_TOLERANCE:g} (recorded on another machine: {MACHINE.name})"
    for i, (g, w) in enumerate(zip(got, want)):
        diff = {k: (w[k], g.get(k)) for k in w if k not in WALL_CLOCK_COLUMNS and not _same(w[k], g.get(k, ""), exact)}
        assert not diff, f"{case}: row {i} differs from {golden.relative_to(REPO)} {how} (golden, now): {diff}"
