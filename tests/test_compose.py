"""deploy/docker-compose.yml: valid for docker-compose, and every command is a real `silcr` command.

No Docker engine runs here, so the file is checked with `docker-compose config`
(Debian's docker-compose package; .ci/run installs it) and every service's
command and environment are parsed by silcr's own option parser.
"""

from __future__ import annotations

import shutil
import subprocess

import pytest
import yaml

from silcr.cli import build_parser
from silcr.common.config import ConfigError, resolve
from tests.helpers import REPO

COMPOSE = REPO / "deploy" / "docker-compose.yml"


@pytest.fixture(scope="module")
def resolved():
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("docker-compose is not installed (Debian: apt-get install docker-compose)")
    r = subprocess.run([exe, "-f", str(COMPOSE), "config"], capture_output=True, text=True, timeout=120, cwd=COMPOSE.parent,
                       env={"PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr
    return yaml.safe_load(r.stdout)


def test_compose_has_the_services_and_volumes(resolved):
    assert set(resolved["services"]) == {"router", "buffer", "learner", "actor", "monitor"}
    assert "runs" in resolved["volumes"]
    for name in ("buffer", "learner"):
        assert any(v.endswith(":/runs:rw") or v.startswith("runs:/runs") for v in resolved["services"][name]["volumes"])
    actor = resolved["services"]["actor"]
    # `--scale actor=N` needs replicas that can coexist: no fixed name, no host port.
    assert "container_name" not in actor and "ports" not in actor


def test_every_service_command_is_a_valid_silcr_command(resolved, tmp_path, monkeypatch):
    parser, subs = build_parser()
    monkeypatch.chdir(REPO / "deploy")  # so /config/silcr.toml can be read from the mounted directory
    for name, svc in resolved["services"].items():
        cmd = [c.replace("/config/", str(REPO / "deploy" / "config") + "/") for c in svc["command"]]
        role = cmd[0]
        assert role in subs, f"{name}: {role} is not a silcr subcommand"
        args = parser.parse_args(cmd)  # exits 2 on an unknown option
        if role == "router":
            continue
        env = {k: str(v) for k, v in (svc.get("environment") or {}).items()}
        try:
            cfg = resolve(args, role, environ=env)
        except ConfigError as e:
            pytest.fail(f"{name}: {e}")
        assert cfg.run == "compose" and cfg.zenoh_mode == "client" and cfg.connect == ["tcp/router:7447"]
        if role in ("buffer", "learner"):
            assert cfg.resume and cfg.runs_dir == "/runs"
        if role == "actor":
            assert cfg.actor_id == -1  # each replica picks its own id


def test_environment_variables_override_the_toml_and_bad_ones_are_named(tmp_path):
    parser, _ = build_parser()
    toml = tmp_path / "c.toml"
    toml.write_text("total_steps = 5\nhidden = [8]\n")
    args = parser.parse_args(["learner", "--config", str(toml), "--run", "r"])
    cfg = resolve(args, "learner", environ={"SILCR_TOTAL_STEPS": "30000", "SILCR_HIDDEN": "64 64"})
    assert cfg.total_steps == 30000 and cfg.hidden == [64, 64]
    args = parser.parse_args(["learner", "--run", "r", "--total-steps", "7"])
    assert resolve(args, "learner", environ={"SILCR_TOTAL_STEPS": "30000"}).total_steps == 7  # command line wins
    with pytest.raises(ConfigError, match="SILCR_TOTAL_STEPS"):
        resolve(parser.parse_args(["learner", "--run", "r"]), "learner", environ={"SILCR_TOTAL_STEPS": "many"})
