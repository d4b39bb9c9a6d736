"""experiments/keep-screen-rule.py: the keep screen's decision rule from the committed records."""

from __future__ import annotations

import importlib.util
import shutil
import subprocess
import sys

from tests.helpers import REPO

SCRIPT = REPO / "experiments" / "keep-screen-rule.py"
SCREEN = REPO / "results" / "keep-screen" / "runs"


def _rule():
    spec = importlib.util.spec_from_file_location("keep_screen_rule", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # a dataclass looks its module up while the module is being run
    spec.loader.exec_module(module)
    return module


def _run(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(SCRIPT), *args], capture_output=True, text=True, timeout=300)


def test_the_rule_gives_the_figures_silcr_plot_gave(tmp_path):
    """RESULTS.md's line for silcr-bc came from `silcr plot ... --compare silcr-layernorm-clip`: the script must
    give the same P and intervals (the stratified bootstrap draws task by task, so even the tasks' order counts)."""
    screen = tmp_path / "runs"
    for cell in sorted(SCREEN.glob("silcr-bc_*")):
        shutil.copytree(cell, screen / cell.name)
    r = _run("--screen", str(screen))
    assert r.returncode == 0, r.stderr
    line = next(x for x in r.stdout.splitlines() if x.startswith("| silcr-bc |"))
    assert "| 0.44 [0.17, 0.83] | 0.50 [0.11, 0.83] | no (undecided) | 3 of 3 seeds |" in line
    assert "| silcr-de4x | 0 of 6 cells finished | | | | 0.00 h |" in r.stdout
    assert "waits for every arm's cells (1 of 5 arms complete)" in r.stdout

    # A cell without the sweep's done marker is still running (or stopped): it does not count.
    (screen / "silcr-bc_Hopper-v5_s1" / "sweep-done.json").unlink()
    r = _run("--screen", str(screen))
    assert "| silcr-bc | 5 of 6 cells finished |" in r.stdout
    assert "| Hopper-v5 | silcr-bc | 2 | 2,593, 1,085 |" in r.stdout

    (screen / "silcr-bc_Hopper-v5_s2" / "progress.csv").write_text("time,env_steps\n")  # a cut record
    r = _run("--screen", str(screen))
    assert r.returncode == 2 and "silcr-bc_Hopper-v5_s2: progress.csv has no values of eval_return" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr

    r = _run("--screen", str(tmp_path / "nowhere"))
    assert r.returncode == 2 and "--screen" in r.stderr and "no such directory" in r.stderr and "Traceback" not in r.stderr


def test_the_arm_for_humanoid_follows_item_4():
    rule = _rule()
    arms = {arm: {task: [rule.Cell(0, 0, keep, 0, None, 0)] for task in rule.TASKS}
            for arm, keep in zip(rule.ARMS, (0.7, 0.9, 0.6, 0.8, 0.5))}

    def p(last, last_five):
        return {"last": (last, 0, 1), "last_five": (last_five, 0, 1)}

    everything = list(rule.ARMS)
    # Above 0.5 under both definitions, then the highest on the last five; within 0.05, a tie.
    ps = {arm: p(0.4, 0.4) for arm in rule.ARMS} | {"silcr-utd2": p(0.6, 0.70), "silcr-de4x": p(0.7, 0.66),
                                                   "silcr-bc": p(0.45, 0.9)}
    assert rule.choose(ps, arms, everything).startswith("silcr-utd2 and silcr-de4x (")
    ps["silcr-de4x"] = p(0.7, 0.64)
    assert rule.choose(ps, arms, everything).startswith("silcr-utd2 (")
    # None above 0.5 under both: the highest median keep ratio on Walker2d, called a guess.
    ps = {arm: p(0.5, 0.9) for arm in rule.ARMS}
    assert rule.choose(ps, arms, everything).startswith("silcr-bc, a guess")
    assert rule.choose(ps, arms, everything[:4]).startswith("waits")

