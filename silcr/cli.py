"""The `silcr` console script.

    silcr train    the whole system locally (router, buffer, learner, N actors)
    silcr buffer   the buffer service alone        silcr actor    one actor
    silcr learner  the learner alone               silcr router   a Zenoh router
    silcr monitor  live stats of a running system

A bad option or config file prints one line naming it and exits with code 2.
"""

from __future__ import annotations

import argparse
import os
import re
import shlex
import sys

from silcr.common import run_end
from silcr.common.commands import command  # noqa: F401  (tests and scripts import it from here)
from silcr.common.config import ConfigError, resolve
from silcr.common.option_parser import add_options
from silcr.deploy import preflight

ROLES_HELP = {
    "train": "run router, buffer service, learner and actors locally until the step budget is spent",
    "buffer": "run the buffer service (D_O, D_E, rate limiter)",
    "learner": "run the learner (SAC updates, weights, evaluation, checkpoints)",
    "actor": "run one actor process",
    "router": "run a Zenoh router (the rendezvous point of a run)",
    "monitor": "show the live stats of a running system",
    "bench": "run the benchmark suite (tables on screen, JSON files)",
    "plot": "learning curves (mean +- std over seeds) and a summary table from run directories",
    "eval": "evaluate the deterministic policy of a checkpoint or model file, optionally recording a video",
    "demos": "record the episodes of a checkpoint's or model file's policy as a demonstrations file for --algo sqil",
    "sweep": "run every (algorithm, task, seed) cell of an experiment file, resuming unfinished cells",
    "health": "check a running component's heartbeat (alive) and Zenoh liveliness token (--ready): a scheduler's probe",
}


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> None:  # one line, exit code 2, no traceback
        self.exit(2, f"{self.prog}: error: {message}\n")


def unrecognized(unknown: list[str], sub: argparse.ArgumentParser | None) -> str:
    """The unrecognized arguments, and for a misspelt option the closest one `sub` takes."""
    import difflib

    text = f"unrecognized arguments: {' '.join(unknown)}"
    if sub is None:
        return text
    options = [o for action in sub._actions for o in action.option_strings if o.startswith("--")]
    for arg in unknown:
        if arg.startswith("--"):
            close = difflib.get_close_matches(arg.split("=", 1)[0], options, n=1, cutoff=0.75)
            if close:
                return f"{text} (did you mean {close[0]}?)"
    return text


def build_parser() -> tuple[argparse.ArgumentParser, dict[str, argparse.ArgumentParser]]:
    parser = _Parser(prog="silcr", description="Distributed SILCR: self-imitation learning with constant reward.")
    from silcr.common.version import __version__

    parser.add_argument("--version", action="version", version=f"silcr {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=_Parser)
    subs: dict[str, argparse.ArgumentParser] = {}
    for role, text in ROLES_HELP.items():
        p = sub.add_parser(role, help=text, description=text, formatter_class=argparse.ArgumentDefaultsHelpFormatter
                           if role == "router" else argparse.HelpFormatter)
        subs[role] = p
        if role == "plot":
            p.add_argument("runs", nargs="+", metavar="RUN_DIR", help="run directories (each with config.toml and progress.csv)")
            p.add_argument("-o", "--out", default="curves.png", help="figure file; a .png also gets an .svg beside it (default: curves.png)")
            p.add_argument("--expert", type=float, default=None, help="draw a dashed horizontal line at this return")
            p.add_argument("--table", default=None, help="also write the Markdown summary (final and best return) to this file")
            p.add_argument("--title", default="", help="figure title")
            p.add_argument("--metric", default="eval_return", help="progress.csv column to plot against env steps "
                           "(default: eval_return; e.g. expert_min_return, q_max, alpha), or one over another: "
                           "q_max/q_bound")
            p.add_argument("--logy", action="store_true", help="log y axis, with the median and the range over seeds instead of mean +- std "
                           "(for q_max across diverging runs)")
            p.add_argument("--stats", choices=["rliable"], default=None, help="also few-seed statistics of the final return "
                           "(rliable: interquartile mean with stratified bootstrap intervals per task and over tasks, "
                           "probability of improvement), added to the table and drawn in <out>-stats.png")
            p.add_argument("--compare", default=None, metavar="LABEL", help="with --stats: the group whose probability of "
                           "improvement over every other group is reported (a curve label, e.g. silcr)")
            p.add_argument("--reference", default=None, metavar="LABEL", help="with --stats: the group whose final return "
                           "is 1 in the normalisation over tasks (default: the sac-dense group)")
            p.add_argument("--against", default=None, metavar="SETTING", help="with --stats: also the final return "
                           "against this numeric config.toml setting (an ablation's axis, e.g. expert_capacity), "
                           "per task with its interval, in the table and in <out>-against-SETTING.png")
            p.add_argument("--bootstrap-reps", type=int, default=2000, metavar="N", help="with --stats: bootstrap "
                           "replications per interval (default: 2000)")
            p.add_argument("--final-evals", type=int, default=1, metavar="K", help="a run's final return is the mean "
                           "of its last K evaluations, in the table and the statistics (default: 1, the last; a few "
                           "smooth out a noisy evaluation)")
            continue
        if role == "eval":
            p.add_argument("checkpoint", help="a learner checkpoint (runs/<run>/checkpoints/learner.pt) or a model "
                                               "file (a run's best policy, runs/<run>/best.silcr; Model.save's)")
            p.add_argument("--episodes", type=int, default=10, help="evaluation episodes (default: 10)")
            p.add_argument("--seed", type=int, default=12345, help="seed of the first episode (default: 12345)")
            p.add_argument("--video", default=None, help="write the first episode as an MP4, rendered off-screen")
            p.add_argument("--stochastic", action="store_true", help="sample the policy's actions (seeded) instead of "
                           "taking its deterministic ones (tanh of the mean, or the most likely action)")
            p.add_argument("--json", action="store_true", help="print the summary and every episode (seed, return, "
                           "length, how it ended) as JSON")
            continue
        if role == "demos":
            p.add_argument("checkpoint", help="a learner checkpoint, normally of dense-reward SAC (runs/<run>/checkpoints/"
                                               "learner.pt), or a model file (runs/<run>/best.silcr)")
            p.add_argument("--episodes", type=int, default=10, help="episodes to record (default: 10)")
            p.add_argument("-o", "--out", default="demos.npz", help="demonstrations file to write (default: demos.npz)")
            p.add_argument("--seed", type=int, default=2024, help="seed of the first episode (default: 2024)")
            p.add_argument("--stochastic", action="store_true", help="sample actions instead of the deterministic tanh(mean)")
            continue
        if role == "sweep":
            p.add_argument("experiment", help="experiment TOML file (see experiments/)")
            p.add_argument("--seeds", default=None, help="seeds as a range and/or list, e.g. 0-4 or 0,3,7 (default: the "
                           "experiment file's `seeds`, else 0-2)")
            p.add_argument("--runs-dir", default="", help="where the cells' run directories go (default: the file's runs_dir, else runs/<experiment>)")
            p.add_argument("--parallel", type=int, default=1, help="cells run at once (default: 1)")
            p.add_argument("--shard", default="1/1", help="K/N: run only the K-th of N shares of the cells, to spread a sweep over N machines (default: 1/1)")
            p.add_argument("--only", default="", help="run only cells whose name contains this text (or any of several, comma-separated: silcr_,sac-)")
            p.add_argument("--dry-run", action="store_true", help="list the cells and their state, run nothing")
            p.add_argument("--resume", action="store_true", help="continue cells that were stopped midway from their "
                           "checkpoints (without it, such cells stop the sweep before anything starts)")
            p.add_argument("--port-base", type=int, default=17500, help="first router port; cell i uses port-base + i (default: 17500)")
            continue
        if role == "bench":
            p.add_argument("which", nargs="?", default="all", choices=["learner", "buffer", "actor", "e2e", "scale", "model", "peer", "all"],
                           help="which benchmark; `all` runs every one but scale (which starts up to 128 actors) "
                                "and peer (Stable-Baselines3 beside silcr train, about 40 minutes for 3 rounds on 2 cores)")
            p.add_argument("--counts", default="", help="scale: actor counts, comma-separated (default: 8,32,128; "
                                                        "--quick: 2,4)")
            p.add_argument("--envs-per-actor", type=int, default=1, help="scale: envs in each actor process (default: 1)")
            p.add_argument("--seconds", type=float, default=0.0, help="scale: the measurement window per count "
                                                                       "(default: 60; --quick: 10)")
            p.add_argument("--hosts", type=int, default=0, help="scale: run the actors on this many network-"
                           "namespace hosts (needs root), each count being the actors per host, each host with a "
                           "Zenoh router of its own; implies --paced (default: 0, all on this host)")
            p.add_argument("--paced", action="store_true", help="scale: actors at the learner's pace, as in a real "
                           "run (default: unthrottled, the transport's load at that many actors)")
            p.add_argument("--train-args", default="", help="scale: more `silcr train` options for every count "
                           "(with --hosts: `silcr learner` options), quoted, e.g. --train-args='--weights-dtype float16'")
            p.add_argument("--tag", default="", help="scale: names the records scale-TAG.json and scale-TAG.png "
                           "(default: scale.json)")
            p.add_argument("--records", default="results/bench-scale/scale-paced-after.json",
                           help="model: the `bench scale --paced` records to calibrate on and check against "
                                "(default: results/bench-scale/scale-paced-after.json)")
            p.add_argument("--updates-per-s", type=float, default=230.0, help="model: the learner's update "
                           "rate to predict 1,000 and 10,000 actors at (default: 230, 256-256 on one core here)")
            p.add_argument("--rounds", type=int, default=0, help="peer: rounds of the three programs (default: 3; "
                                                                  "--quick: 1)")
            p.add_argument("--out", default="bench-results", help="directory for the JSON results (default: bench-results)")
            p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"], help="learner benchmark device (default: auto: CPU, and CUDA when present)")
            p.add_argument("--quick", action="store_true", help="short measurements (a smoke test of the suite)")
            continue
        if role == "router":
            p.add_argument("--listen", nargs="+", default=["tcp/127.0.0.1:7447"], help="endpoints to listen on")
            p.add_argument("--connect", nargs="+", default=[], help="other routers to connect to (multi-host)")
            p.add_argument("--zenoh-config", default="", help="Zenoh JSON5 config file")
            p.add_argument("--run", default="", help="follow this run: exit 0 shortly after it finishes (a compose "
                           "stack's router); empty: run until stopped")
            continue
        add_options(p, role)
        if role == "health":
            p.add_argument("--ready", action="store_true", help="also check that the component's Zenoh liveliness "
                           "token is visible through the router (readiness); without it, only that its loop runs")
            p.add_argument("--stale-after", type=float, default=300.0, metavar="S", help="a heartbeat older than this "
                           "many seconds means stuck (default: 300: longer than a slow evaluation or checkpoint)")
            p.add_argument("--timeout", type=float, default=5.0, metavar="S", help="with --ready: seconds to wait for "
                           "the token (default: 5)")
        if role == "monitor":
            p.add_argument("--once", action="store_true", help="print one snapshot and exit")
            p.add_argument("--json", action="store_true", help="with --once: print the snapshot as JSON")
            p.add_argument("--timeout", type=float, default=5.0, help="with --once: seconds to wait for stats (default: 5)")
            p.add_argument("--interval", type=float, default=10.0, metavar="S", help="without a terminal (a container's "
                           "log): print one plain line of the run's figures every S seconds (default: 10)")
    return parser, subs


def main(argv: list[str] | None = None) -> int:
    try:
        return _main(argv)
    except BrokenPipeError:
        # `silcr sweep ... --dry-run | head` closed the pipe: stop quietly, as other command-line
        # tools do, and keep Python from failing again when it flushes stdout at exit.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, what a shell reports for a tool the pipe ended


def _main(argv: list[str] | None) -> int:
    parser, subs = build_parser()
    args, unknown = parser.parse_known_args(argv)
    role = args.command
    if unknown:
        # Said by the subcommand that was given them (`silcr train: error: ...`), with the option meant if a
        # known one is close (argparse reports them from the top parser, with no suggestion).
        (subs[role] if role in subs else parser).error(unrecognized(unknown, subs.get(role)))
    if role is None:
        parser.print_help()
        return 2

    from silcr.common.lifecycle import StopFlag, setup_logging

    if role == "plot":
        from silcr.plot import plot_command

        return plot_command(args, subs[role])
    if role in ("eval", "demos"):
        import silcr.policy_commands as policy_commands

        return (policy_commands.eval_command if role == "eval" else policy_commands.demos_command)(args, subs[role])
    if role == "sweep":
        from silcr.deploy.sweep import run_sweep_cli

        return run_sweep_cli(args, subs[role])
    if role == "bench":
        from pathlib import Path

        from silcr.bench.cli import run_bench

        try:
            counts = [int(c) for c in args.counts.split(",") if c.strip()]
        except ValueError:
            subs[role].error(f"--counts: {args.counts!r} is not a comma-separated list of actor counts")
        if any(c < 1 for c in counts) or args.envs_per_actor < 1 or args.seconds < 0 or args.rounds < 0:
            subs[role].error("--counts, --envs-per-actor, --seconds and --rounds must be positive")
        if not args.updates_per_s > 0:
            subs[role].error(f"--updates-per-s: must be positive, got {args.updates_per_s}")
        if not 0 <= args.hosts <= 200:
            subs[role].error(f"--hosts: must be 0 to 200, got {args.hosts}")
        if args.hosts and args.envs_per_actor != 1:
            subs[role].error("--hosts runs one env per actor; leave --envs-per-actor out")
        try:
            train_args = shlex.split(args.train_args)
        except ValueError as e:
            subs[role].error(f"--train-args: {e}")
        if args.tag and not re.fullmatch(r"[A-Za-z0-9_.-]+", args.tag):
            subs[role].error(f"--tag: {args.tag!r} may hold only letters, digits, '_', '.' and '-'")
        if args.which == "model":
            from silcr.bench.scale_model import RecordsError
            from silcr.bench.scale_model import run as run_model

            try:
                run_model(Path(args.records), Path(args.out), args.updates_per_s)
            except RecordsError as e:
                print(f"silcr bench model: error: {e}", file=sys.stderr)
                return 2
            return 0
        if args.which == "peer":
            from silcr.bench.peer import MISSING_SB3, sb3_available

            if not sb3_available():
                print(MISSING_SB3, file=sys.stderr)
                return 2
        return run_bench(args.which, Path(args.out), args.device, args.quick, counts, args.envs_per_actor,
                         args.seconds, args.rounds, args.paced, train_args, args.tag, args.hosts)
    if role == "router":
        from silcr.common.zenoh_session import check_endpoint

        for option, endpoints in (("--listen", args.listen), ("--connect", args.connect)):
            for endpoint in endpoints:
                try:
                    check_endpoint(endpoint)
                except ValueError as e:
                    subs[role].error(f"{option}: {e}")
        if args.run:
            from silcr.common.protocol import validate_run_name

            try:
                validate_run_name(args.run)
            except ValueError as e:
                subs[role].error(f"--run: {e}")
        setup_logging("router")
        from silcr.deploy.router import run_router

        try:
            return run_router(args.listen, args.connect, args.zenoh_config, StopFlag().install_signal_handlers(),
                              args.run)
        except Exception as e:  # zenoh raises ZError for a port in use or a bad endpoint
            subs[role].exit(2, f"silcr router: error: {e}\n")

    try:
        cfg = resolve(args, role)
        preflight.check(cfg, role)
    except ConfigError as e:
        subs[role].error(str(e))

    if role == "train":
        from silcr.common.run_lock import RunInUse
        from silcr.deploy.launch import train

        try:
            return train(cfg)
        except (RunInUse, ConfigError) as e:
            subs[role].error(str(e))
    if role == "health":
        from silcr.deploy.health import run_health

        if not args.stale_after > 0 or not args.timeout > 0:
            subs[role].error("--stale-after and --timeout must be > 0")
        return run_health(cfg, args.ready, args.stale_after, args.timeout)
    if role in ("buffer", "learner", "actor"):
        # The finished-run rule (common/run_end.py): an orchestrator that starts a component of a finished run again
        # gets one line and exit 0, and nothing is retrained or rewritten. Actors have no --resume (they hold no
        # state) and see the run directory only where it is shared (compose's volume): they read finished.json.
        if role == "actor":
            done = run_end.finished(cfg)
        else:
            from silcr.learner.checkpoint import finished_run  # torch: not for the actors

            done = finished_run(cfg) if cfg.resume else None
            try:  # without --resume, never a new run over one the directory holds (the launcher checks it too)
                run_end.check_new(cfg)
            except ConfigError as e:
                subs[role].error(str(e))
        if done is not None:
            print(f"silcr {role}: {done.message()}", flush=True)
            if role == "learner":  # the others hear it from the learner, as at the run's end
                run_end.announce(cfg)
            return 0
    stop = StopFlag().install_signal_handlers()
    if role == "monitor":
        from silcr.deploy.monitor import run_monitor

        if not args.interval > 0:
            subs[role].error(f"--interval: must be > 0, got {args.interval}")
        return run_monitor(cfg.run, cfg.connect, cfg.zenoh_mode, cfg.zenoh_config, args.once, args.json, args.timeout,
                           stop, args.interval)
    if role == "actor" and cfg.actor_id == -1:
        import secrets

        cfg.actor_id = secrets.randbelow(2**31)  # distinct seeds and stats keys for identical replicas
    setup_logging(role if role != "actor" else f"actor-{cfg.actor_id}")
    if role == "buffer":
        from silcr.buffer_service.service import run_buffer

        return run_buffer(cfg, stop)
    if role == "learner":
        from silcr.learner.service import run_learner

        return run_learner(cfg, stop)
    from silcr.actor.service import run_actor

    return run_actor(cfg, stop)


if __name__ == "__main__":
    sys.exit(main())
