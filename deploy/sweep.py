"""`silcr sweep`: every (variant, task, seed) cell of an experiment file, resumable.

An experiment is a TOML file (see `experiments/`):

    name = "hopper-30k"                 # default run directory: runs/<name>
    tasks = ["Hopper-v5"]
    seeds = "0-2"                       # default for --seeds
    [common]                            # `silcr train` options for every cell
    total_steps = 30000
    [variants.silcr-episodic]           # one table per algorithm setting
    algo = "silcr"
    [variants.sqil]
    algo = "sqil"
    demos = "demos/{task}.npz"          # {task} is replaced by the cell's task
    [variants.sac-dense]
    algo = "sac"
    seeds = "0"                         # a reference: this variant runs only these of the selected seeds

Each cell is one `silcr train` run named `<variant>_<task>_s<seed>` in the sweep's
runs directory. A cell is *done* once its run exited cleanly (marker file
`sweep-done.json`); a cell with a learner checkpoint but no marker was stopped
midway and, with `silcr sweep --resume`, continues from its checkpoints; any other
cell starts fresh. So `--resume` after a crash, Ctrl-C or the end of a working
session picks up where it stopped; without it, stopped cells are reported and
nothing starts (a sweep never silently continues or overwrites a half-done run).
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from silcr.common import run_layout
from silcr.common.commands import command, option_args
from silcr.common.config import FIELDS, ConfigError, from_options
from silcr.common.lifecycle import caller_signal_handlers, ignore_stop_signals, stop_signals_interrupt
from silcr.common.run_records import wall_seconds
from silcr.learner.progress import read_rows

# Set per cell by the sweep itself, so an experiment file may not set them.
_SWEEP_OWNED = {"run", "runs_dir", "seed", "resume", "zenoh_listen", "config"}


class ExperimentError(ValueError):
    pass


@dataclass(frozen=True)
class Cell:
    variant: str
    task: str
    seed: int
    options: dict[str, Any]

    @property
    def name(self) -> str:
        return f"{self.variant}_{self.task.replace('/', '-')}_s{self.seed}"


def parse_seeds(text: str) -> list[int]:
    """`0-4`, `0,3,7` or a mix (`0-2,5`) as a sorted list of distinct seeds."""
    seeds: set[int] = set()
    try:
        for part in str(text).split(","):
            part = part.strip()
            if "-" in part[1:]:
                lo, hi = part.split("-", 1) if not part.startswith("-") else (part, "")
                a, b = int(lo), int(hi)
                if b < a:
                    raise ValueError
                seeds.update(range(a, b + 1))
            else:
                seeds.add(int(part))
    except ValueError:
        raise ExperimentError(f"seeds {text!r}: use a range like 0-4 and/or a list like 0,3,7") from None
    return sorted(seeds)


def load_experiment(path: Path) -> dict[str, Any]:
    try:
        data = tomllib.loads(path.read_text())
    except OSError as e:
        raise ExperimentError(f"{path}: {e.strerror or e}") from None
    except tomllib.TOMLDecodeError as e:
        raise ExperimentError(f"{path}: not valid TOML ({e})") from None
    unknown = set(data) - {"name", "description", "tasks", "seeds", "runs_dir", "common", "variants"}
    if unknown:
        raise ExperimentError(f"{path}: unknown top-level keys {sorted(unknown)}")
    if not isinstance(data.get("tasks"), list) or not data["tasks"] or not all(isinstance(t, str) for t in data["tasks"]):
        raise ExperimentError(f"{path}: 'tasks' must be a non-empty list of environment ids")
    if not isinstance(data.get("variants"), dict) or not data["variants"]:
        raise ExperimentError(f"{path}: needs at least one [variants.<name>] table")
    for scope, table in [("common", data.get("common", {}))] + [(f"variants.{k}", v) for k, v in data["variants"].items()]:
        if not isinstance(table, dict):
            raise ExperimentError(f"{path}: [{scope}] must be a table of silcr train options")
        for key in table:
            k = key.replace("-", "_")
            if k == "seeds" and scope != "common":
                parse_seeds(table[key])  # a variant's own seeds: checked here, applied in cells_of
                continue
            if k in _SWEEP_OWNED:
                raise ExperimentError(f"{path}: [{scope}] may not set {key!r}; the sweep sets it per cell")
            if k not in FIELDS or "train" not in FIELDS[k].metadata["roles"]:
                raise ExperimentError(f"{path}: [{scope}] {key!r} is not a `silcr train` option")
    data.setdefault("name", path.stem)
    return data


def cells_of(exp: dict[str, Any], seeds: list[int]) -> list[Cell]:
    """Every cell, task by task in the file's order. A variant with its own `seeds` runs only
    those of `seeds` (a one-seed reference beside 3-seed cells, for example)."""
    common = {k.replace("-", "_"): v for k, v in exp.get("common", {}).items()}
    out = []
    for task in exp["tasks"]:
        for variant, table in exp["variants"].items():
            table = dict(table)
            own = table.pop("seeds", None)
            opts = common | {k.replace("-", "_"): v for k, v in table.items()} | {"env": task}
            opts = {k: (v.replace("{task}", task) if isinstance(v, str) else v) for k, v in opts.items()}
            chosen = seeds if own is None else [s for s in seeds if s in set(parse_seeds(own))]
            out.extend(Cell(variant, task, s, opts) for s in chosen)
    return out


def cell_state(run_dir: Path) -> str:
    if run_layout.sweep_done(run_dir).exists():
        return "done"
    if run_layout.learner_checkpoint(run_dir).exists():
        return "partial"
    return "new"


def cell_detail(cell: Cell, run_dir: Path, state: str) -> str:
    """What `--dry-run` adds after a cell's state: how far a stopped cell got (its progress.csv's
    last env-step count), and whether a process holds the run now (a sweep in another terminal,
    or one cut from its terminal that still runs)."""
    from silcr.common.run_lock import RunInUse, check_free

    parts = []
    if state == "partial":
        total = int(cell.options.get("total_steps", FIELDS["total_steps"].default))
        try:
            last = read_rows(run_dir)[-1]
            parts.append(f"{int(float(last['env_steps'])):,} of {total:,} env steps")
        except (IndexError, KeyError, ValueError, TypeError):  # read_rows gives [] for a missing or unreadable file
            parts.append("no progress.csv rows yet")
    try:
        check_free(run_dir)
    except RunInUse:
        parts.append("running now")
    return f"  ({'; '.join(parts)})" if parts else ""


def _command(cell: Cell, runs_dir: Path, port: int, resume: bool) -> list[str]:
    return command("train", *option_args(_cell_options(cell, runs_dir, port, resume)))


def _cell_options(cell: Cell, runs_dir: Path, port: int, resume: bool) -> dict[str, Any]:
    """The cell's `silcr train` options: the experiment's, and what the sweep sets per cell."""
    return cell.options | {"run": cell.name, "runs_dir": str(runs_dir), "seed": cell.seed,
                           "zenoh_listen": f"tcp/127.0.0.1:{port}", "resume": resume}


def _port_free(port: int) -> bool:
    import socket

    with socket.socket() as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def _run_minutes(run_dir: Path) -> float | None:
    """The run's wall time in minutes with every resumed stretch added (progress.csv's `time`)."""
    seconds = wall_seconds(read_rows(run_dir))
    return None if seconds is None else seconds / 60


class _Running:
    def __init__(self, cell: Cell, proc: subprocess.Popen, port: int, started: float, log) -> None:
        self.cell, self.proc, self.port, self.started, self.log = cell, proc, port, started, log


def selected_cells(exp: dict[str, Any], seeds: list[int], only: str, shard: tuple[int, int]) -> list[Cell]:
    """The cells this invocation runs: those whose name contains `only` (or any of its
    comma-separated parts), then every N-th from K."""
    k, n = shard
    parts = [p for p in only.split(",") if p] or [""]
    cells = [c for c in cells_of(exp, seeds) if any(p in c.name for p in parts)]
    return [c for i, c in enumerate(cells) if i % n == k - 1]


def run_sweep(exp: dict[str, Any], seeds: list[int], runs_dir: Path, parallel: int, shard: tuple[int, int],
              only: str, dry_run: bool, port_base: int, resume: bool = True) -> int:
    with caller_signal_handlers():
        return _run_sweep(exp, seeds, runs_dir, parallel, shard, only, dry_run, port_base, resume)


def _run_sweep(exp: dict[str, Any], seeds: list[int], runs_dir: Path, parallel: int, shard: tuple[int, int],
               only: str, dry_run: bool, port_base: int, resume: bool) -> int:
    cells = selected_cells(exp, seeds, only, shard)
    k, n = shard
    states = {c.name: cell_state(runs_dir / c.name) for c in cells}
    todo = [c for c in cells if states[c.name] != "done"]
    partial = [c.name for c in cells if states[c.name] == "partial"]
    print(f"silcr sweep {exp['name']}: {len(cells)} cells in {runs_dir} (shard {k}/{n}); "
          f"{len(cells) - len(todo)} done, {len(partial)} to resume, "
          f"{sum(s == 'new' for s in states.values())} new", flush=True)
    if dry_run:
        for c in cells:
            print(f"  {states[c.name]:8s} {c.name}{cell_detail(c, runs_dir / c.name, states[c.name])}")
        return 0
    if partial and not resume:
        raise ExperimentError(f"{len(partial)} cell(s) were stopped midway ({', '.join(partial[:3])}"
                              f"{', ...' if len(partial) > 3 else ''}); add --resume to continue them from their "
                              f"checkpoints, or delete their directories to start them again")
    runs_dir.mkdir(parents=True, exist_ok=True)

    stop_signals_interrupt()  # `kill` takes the same clean path as Ctrl-C
    running: list[_Running] = []
    failed: list[str] = []
    finished = len(cells) - len(todo)
    free_ports = [p for p in range(port_base, port_base + 64)]
    try:
        while todo or running:
            while todo and len(running) < parallel:
                cell = todo.pop(0)
                port = next((p for p in free_ports if p not in {r.port for r in running} and _port_free(p)), None)
                if port is None:
                    raise ExperimentError(f"no free port in {port_base}-{port_base + 63}; pass another --port-base")
                resume = states[cell.name] == "partial"
                (runs_dir / cell.name).mkdir(parents=True, exist_ok=True)
                log = open(run_layout.sweep_log(runs_dir / cell.name), "ab")
                # Own process group: Ctrl-C reaches the sweep only, and it stops the cells in order.
                proc = subprocess.Popen(_command(cell, runs_dir, port, resume), stdout=log, stderr=subprocess.STDOUT,
                                        start_new_session=True, env=os.environ | {"PYTHONUNBUFFERED": "1"})
                running.append(_Running(cell, proc, port, time.monotonic(), log))
                print(f"[{finished}/{len(cells)}] {'resume' if resume else 'start '} {cell.name} "
                      f"(log: {run_layout.sweep_log(runs_dir / cell.name)})", flush=True)
            time.sleep(0.5)
            for r in list(running):
                rc = r.proc.poll()
                if rc is None:
                    continue
                running.remove(r)
                r.log.close()
                minutes = (time.monotonic() - r.started) / 60
                if rc == 0:
                    finished += 1
                    total = _run_minutes(runs_dir / r.cell.name)
                    # `minutes` is this stretch; a resumed cell's compute is the sum over its stretches.
                    marker = {"cell": r.cell.name, "variant": r.cell.variant, "task": r.cell.task, "seed": r.cell.seed,
                              "finished_at": time.time(), "minutes": minutes, "minutes_all_stretches": total}
                    run_layout.sweep_done(runs_dir / r.cell.name).write_text(json.dumps(marker))
                    spent = f" ({total:.1f} min over every stretch)" if total is not None and total > minutes + 1 else ""
                    print(f"[{finished}/{len(cells)}] done   {r.cell.name} in {minutes:.1f} min{spent}", flush=True)
                else:
                    failed.append(r.cell.name)
                    print(f"[{finished}/{len(cells)}] FAILED {r.cell.name} (exit {rc}); see {run_layout.sweep_log(runs_dir / r.cell.name)}",
                          flush=True)
    except KeyboardInterrupt:
        print(f"\nsilcr sweep: interrupted; stopping {len(running)} running cell(s); run the same command with --resume "
              f"to continue",
              file=sys.stderr, flush=True)
        for r in running:
            r.proc.send_signal(signal.SIGINT)
        try:
            for r in running:
                try:
                    r.proc.wait(60)
                except subprocess.TimeoutExpired:
                    os.killpg(r.proc.pid, signal.SIGKILL)
                    r.proc.wait()
        except KeyboardInterrupt:  # a second Ctrl-C or kill: stop now (checkpoints are written whole or not at all)
            print("silcr sweep: interrupted again; killing the cells now", file=sys.stderr, flush=True)
            for r in running:
                if r.proc.poll() is None:
                    os.killpg(r.proc.pid, signal.SIGKILL)
                r.proc.wait()
        for r in running:
            r.log.close()
        return 130
    if failed:
        print(f"silcr sweep: {len(failed)} cell(s) failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    print(f"silcr sweep: all {len(cells)} cells done; plot with: silcr plot {runs_dir}/* -o {runs_dir}/curves.png")
    return 0


def run_sweep_cli(args: argparse.Namespace, parser: argparse.ArgumentParser) -> int:
    try:
        exp = load_experiment(Path(args.experiment))
        seeds = parse_seeds(args.seeds if args.seeds is not None else exp.get("seeds", "0-2"))
    except ExperimentError as e:
        parser.error(str(e))
    if args.parallel < 1:
        parser.error(f"--parallel must be >= 1, got {args.parallel}")
    try:
        k, n = (int(x) for x in args.shard.split("/"))
        if not 1 <= k <= n:
            raise ValueError
    except ValueError:
        parser.error(f"--shard {args.shard!r}: use K/N with 1 <= K <= N, e.g. 2/3")
    runs_dir = Path(args.runs_dir or exp.get("runs_dir") or Path("runs") / exp["name"])
    # Check every selected cell's options the way `silcr train` would, before starting any (the
    # cells inherit this environment, so its SILCR_* variables count as they will there).
    problems: dict[str, list[str]] = {}  # one line per distinct problem, naming the cells it affects
    for cell in selected_cells(exp, seeds, args.only, (k, n)):
        try:
            from_options(_cell_options(cell, runs_dir, args.port_base, False), "train", os.environ)
        except ConfigError as e:
            problems.setdefault(str(e), []).append(cell.name)
    lines = [f"{msg} ({len(names)} cell{'s' * (len(names) > 1)}: {', '.join(names[:3])}{', ...' * (len(names) > 3)})"
             for msg, names in problems.items()]
    if problems and not args.dry_run:
        for line in lines[:-1]:
            print(f"silcr sweep: error: {line}", file=sys.stderr)
        parser.error(lines[-1])
    try:
        rc = run_sweep(exp, seeds, runs_dir, args.parallel, (k, n), args.only, args.dry_run, args.port_base, args.resume)
    except ExperimentError as e:
        print(f"silcr sweep: error: {e}", file=sys.stderr)
        return 2 if "--resume" in str(e) else 1
    if rc == 130:
        # The cells are stopped: a later signal has nothing left to stop, and one that came during the
        # interpreter's exit killed the sweep (exit -15, not 130) once the handlers were reset; ignored
        # handlers are not reset. (Here, not in run_sweep: an in-process caller gets its handlers back.)
        ignore_stop_signals()
    for line in lines:  # a dry run shows the plan and then everything that would stop it
        print(f"silcr sweep: error: {line}", file=sys.stderr)
    return 2 if problems else rc
