"""deploy/docker-compose.yml on a real Docker engine, as a user starts it (issue 59).

The image is built from deploy/Dockerfile, and the stack started with the compose file as shipped plus only an
`.env` and a TOML in `config/`, for a small InvertedPendulum-v5 run with 2 actors. Checked: the run trains to its
end and stays finished (the learner exits 0, no container is restarted but the one killed, progress.csv's env_steps
never go back and its rows stop growing; starting the stack again changes no file), a SIGKILLed learner comes back
from its checkpoint, the monitor's log shows the run, an outside Zenoh client reads the buffer's stats through the
port the router publishes, `up --exit-code-from learner` returns 0 for a completed run, and `down -v` leaves no
container, network or volume.

Runs when a Docker engine answers (`docker info`; .ci/run starts one) and is skipped with the reason otherwise.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import time
import uuid
from pathlib import Path

import pytest

from silcr.common import protocol as P
from tests import docker_engine as de
from tests.helpers import REPO, SMALL_FINITE_RUN_TOML, LatestJson, client_when_up, free_port, wait_for

pytestmark = pytest.mark.slow

RUN = "engine"
TOTAL_STEPS = 8000
SMALL_TOML = SMALL_FINITE_RUN_TOML  # the env comes from the .env, as a user's would


@pytest.fixture(scope="module")
def engine():
    problem = de.engine_problem()
    if problem is not None:
        pytest.skip(problem)
    compose = de.compose_command()
    if compose is None:
        pytest.skip("neither docker-compose nor `docker compose` is installed (Debian: apt-get install docker-compose)")
    return compose


@pytest.fixture(scope="module")
def image(engine, tmp_path_factory):
    work = tmp_path_factory.mktemp("engine")
    de.ensure_base_image(work)
    de.torch_index(work / "torch-index")
    server, port = de.serve(work / "torch-index")  # the index is its simple/ folder
    try:
        context = de.build_context(REPO, work / "context")
        tag = f"silcr-test:{uuid.uuid4().hex[:8]}"
        de.build_image(context, tag, f"http://127.0.0.1:{port}/simple")
    finally:
        server.shutdown()
    yield tag, context
    de.docker("image", "rm", "-f", tag, check=False)


class Stack:
    """One compose project from the context's deploy/ folder, with its own name, .env and TOML."""

    def __init__(self, compose: list[str], deploy: Path, image: str, total_steps: int, router_port: int) -> None:
        self.compose, self.deploy = compose, deploy
        self.project = f"silcrtest{uuid.uuid4().hex[:8]}"
        (deploy / "config" / "small.toml").write_text(SMALL_TOML)
        (deploy / ".env").write_text(f"SILCR_IMAGE={image}\nSILCR_RUN={RUN}\nSILCR_ENV=InvertedPendulum-v5\n"
                                     f"SILCR_TOTAL_STEPS={total_steps}\nSILCR_CONFIG_FILE=small.toml\n"
                                     f"SILCR_ROUTER_PORTS=127.0.0.1:{router_port}:7447\n")

    def run(self, *args: str, timeout: float = 300) -> subprocess.CompletedProcess:
        return subprocess.run([*self.compose, "-p", self.project, *args], cwd=self.deploy, capture_output=True,
                              text=True, timeout=timeout)

    def containers(self) -> list[dict]:
        ids = de.docker("ps", "-aq", "--filter", f"label=com.docker.compose.project={self.project}").stdout.split()
        return json.loads(de.docker("inspect", *ids).stdout) if ids else []

    def container(self, service: str) -> dict:
        return next(c for c in self.containers() if _service(c) == service)

    def run_dir(self) -> Path:
        volume = f"{self.project}_runs"
        mount = json.loads(de.docker("volume", "inspect", volume).stdout)[0]["Mountpoint"]
        return Path(mount) / RUN

    def leftovers(self) -> dict[str, list[str]]:
        label = f"label=com.docker.compose.project={self.project}"
        return {kind: de.docker(*cmd, "--filter", label).stdout.split() for kind, cmd in
                (("containers", ("ps", "-aq")), ("networks", ("network", "ls", "-q")), ("volumes", ("volume", "ls", "-q")))}


def _service(container: dict) -> str:
    return container["Config"]["Labels"]["com.docker.compose.service"]


def _rows(run_dir: Path) -> list[dict[str, str]]:
    try:
        with open(run_dir / "progress.csv", newline="") as f:
            return list(csv.DictReader(f))
    except OSError:
        return []


def _silcr_child(container: dict) -> int:
    """The silcr process under the container's init (`init: true`), by its host PID."""
    init = container["State"]["Pid"]
    children = Path(f"/proc/{init}/task/{init}/children").read_text().split()
    return int(children[0])


def test_the_stack_trains_once_stays_finished_and_comes_back_from_a_kill(engine, image, tmp_path):
    tag, context = image
    port = free_port()
    stack = Stack(engine, context / "deploy", tag, TOTAL_STEPS, port)
    try:
        up = stack.run("up", "-d", "--scale", "actor=2")
        assert up.returncode == 0, up.stderr
        # An outside client reads the buffer's stats through the router's published port.
        session = client_when_up(port, timeout=120)
        try:
            keys = P.Keys(RUN)
            stats = LatestJson(session, keys.stats_all)
            wait_for(lambda: stats.get(keys.stats_buffer), 180, "buffer stats through the published port")
        finally:
            session.close()
        run_dir = stack.run_dir()
        # Once the learner has checkpointed mid-run, kill its process as a crash would.
        wait_for(lambda: (run_dir / "checkpoints" / "learner.pt").exists() and
                 len(_rows(run_dir)) >= 3, 300, "a mid-run learner checkpoint")
        steps_at_kill = int(_rows(run_dir)[-1]["env_steps"])
        assert steps_at_kill < TOTAL_STEPS
        os.kill(_silcr_child(stack.container("learner")), signal.SIGKILL)
        wait_for(lambda: stack.container("learner")["RestartCount"] >= 1, 120, "the learner's restart")
        # The run ends: the learner exits 0, then every service, by itself.
        wait_for(lambda: stack.container("learner")["State"]["Status"] == "exited", 600, "the learner's end")
        wait_for(lambda: all(c["State"]["Status"] == "exited" for c in stack.containers()), 120,
                 "every service's end", interval=1)
        final = _rows(run_dir)
        states = [(_service(c), c["State"]["ExitCode"], c["RestartCount"]) for c in stack.containers()]
        assert all(code == 0 for _, code, _ in states), states
        assert [(service, n) for service, _, n in states if n] == [("learner", 1)], states  # the kill's, only
        steps = [int(r["env_steps"]) for r in final]
        assert steps == sorted(steps) and steps[-1] >= TOTAL_STEPS, steps
        logs = stack.run("logs", "learner").stdout
        assert "resumed from /runs/engine/checkpoints/learner.pt" in logs, logs[-3000:]
        monitor = stack.run("logs", "monitor").stdout
        assert sum("learner: env_steps" in line for line in monitor.splitlines()) >= 2, monitor[-2000:]
        assert f"run {RUN} finished at " in monitor

        # Started again as a user would: every component says the run is finished, and no file changes.
        before = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock"}
        again = stack.run("up", "-d", "--scale", "actor=2")
        assert again.returncode == 0, again.stderr
        time.sleep(3)
        wait_for(lambda: all(c["State"]["Status"] == "exited" for c in stack.containers() if _service(c) != "router"),
                 120, "the components of the finished run to exit", interval=1)
        for service in ("learner", "buffer", "actor"):
            c = stack.container(service)
            assert c["State"]["ExitCode"] == 0
            assert f"run {RUN} already finished at " in stack.run("logs", service).stdout
        after = {p: p.read_bytes() for p in run_dir.rglob("*") if p.is_file() and p.name != ".lock"}
        assert after.keys() == before.keys() and all(after[p] == before[p] for p in before)
    finally:
        down = stack.run("down", "-v", "--remove-orphans")
    assert down.returncode == 0, down.stderr
    assert stack.leftovers() == {"containers": [], "networks": [], "volumes": []}


def test_up_with_exit_code_from_the_learner_returns_0_for_a_completed_run(engine, image):
    tag, context = image
    stack = Stack(engine, context / "deploy", tag, 3000, free_port())
    try:
        up = stack.run("up", "--scale", "actor=2", "--exit-code-from", "learner", timeout=600)
        assert up.returncode == 0, up.stdout[-3000:] + up.stderr[-2000:]
    finally:
        stack.run("down", "-v", "--remove-orphans")
    assert stack.leftovers() == {"containers": [], "networks": [], "volumes": []}
