"""deploy/k8s (issue 39): the kustomize base and its overlays render, every object is valid Kubernetes, and
every container runs a real `silcr` command wired to the router.

No cluster runs here. `kubectl kustomize` renders each directory (kubectl has kustomize built in); every
object is then loaded into the official `kubernetes` Python client's typed model, with a check that the
model knows every field (the client itself ignores unknown ones, so a misspelt field would pass); the
wiring is checked (clients name the router Service and its port, volumes and claims match, the actor
Job's parallelism scales the actors, every part is a Job that a finished run leaves complete); and every container's command, environment and probes are
parsed by silcr's own option parser, as tests/test_compose.py does for compose. What this cannot show:
that a cluster schedules the pods, pulls the image, binds the claims, or that the network carries Zenoh.
"""

from __future__ import annotations

import re
import shutil
import subprocess

import pytest
import yaml

from silcr.cli import build_parser
from silcr.common.config import resolve
from tests.helpers import REPO

K8S = REPO / "deploy" / "k8s"
OVERLAYS = ["base", "gpu", "tls"]
ROLES = {"silcr-buffer": "buffer", "silcr-learner": "learner", "silcr-actor": "actor", "silcr-monitor": "monitor"}

kubernetes = pytest.importorskip("kubernetes", reason="the kubernetes client is in the test extra")


def _render(which: str) -> list[dict]:
    exe = shutil.which("kubectl")
    if exe is None:
        pytest.skip("kubectl is not installed (it carries kustomize); the development machines have it")
    path = K8S if which == "base" else K8S / "overlays" / which
    r = subprocess.run([exe, "kustomize", str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    return [d for d in yaml.safe_load_all(r.stdout) if d]


@pytest.fixture(scope="module", params=OVERLAYS)
def rendered(request):
    return request.param, _render(request.param)


def _model(type_name: str):
    return getattr(kubernetes.client.models, type_name)


def strict(value, type_name: str, where: str) -> None:
    """Every key of `value` is a field of the client's model `type_name`, all the way down."""
    m = re.fullmatch(r"List\[(.+)\]", type_name) or re.fullmatch(r"list\[(.+)\]", type_name)
    if m:
        assert isinstance(value, list), f"{where}: expected a list"
        for i, v in enumerate(value):
            strict(v, m.group(1), f"{where}[{i}]")
        return
    m = re.fullmatch(r"Dict\[str, (.+)\]", type_name) or re.fullmatch(r"dict\(str, (.+)\)", type_name)
    if m:
        assert isinstance(value, dict), f"{where}: expected a map"
        for k, v in value.items():
            strict(v, m.group(1), f"{where}.{k}")
        return
    if type_name in ("str", "int", "bool", "float", "object", "datetime", "bytes"):
        return
    cls = _model(type_name)
    assert isinstance(value, dict), f"{where}: expected a {type_name} object"
    known = {json_key: attr for attr, json_key in cls.attribute_map.items()}
    unknown = set(value) - set(known)
    assert not unknown, f"{where}: {type_name} has no field {sorted(unknown)}"
    for key, v in value.items():
        strict(v, cls.openapi_types[known[key]], f"{where}.{key}")


def _typed(doc: dict):
    type_name = f"V1{doc['kind']}"
    strict(doc, type_name, f"{doc['kind']}/{doc['metadata']['name']}")
    return kubernetes.client.ApiClient()._ApiClient__deserialize(doc, type_name)


def _by(docs, kind):
    return {d["metadata"]["name"]: d for d in docs if d["kind"] == kind}


def _workloads(docs):
    return _by(docs, "Job")


def _env(docs, container) -> dict[str, str]:
    """The container's environment: its ConfigMaps (envFrom) and then its own `env`."""
    maps = {d["metadata"]["name"]: d.get("data", {}) for d in docs if d["kind"] == "ConfigMap"}
    env: dict[str, str] = {}
    for source in container.get("envFrom", []):
        env |= maps[source["configMapRef"]["name"]]
    env |= {e["name"]: e["value"] for e in container.get("env", [])}
    return env


def test_every_object_renders_and_is_valid_kubernetes(rendered):
    which, docs = rendered
    kinds = sorted(d["kind"] for d in docs)
    assert kinds.count("Job") == 5 and kinds.count("Service") == 1 and kinds.count("PersistentVolumeClaim") == 2
    assert "Deployment" not in kinds and "StatefulSet" not in kinds
    for doc in docs:
        typed = _typed(doc)
        assert typed.metadata.name.startswith("silcr-")
    # the check would catch a misspelt field
    bad = dict(_workloads(docs)["silcr-actor"], spec={**_workloads(docs)["silcr-actor"]["spec"], "paralelism": 3})
    with pytest.raises(AssertionError, match="no field"):
        strict(bad, "V1Job", "bad")


def test_clients_name_the_router_service_and_its_port(rendered):
    which, docs = rendered
    services = _by(docs, "Service")
    router = services["silcr-router"]
    port = router["spec"]["ports"][0]
    assert router["spec"]["selector"] == _workloads(docs)["silcr-router"]["spec"]["template"]["metadata"]["labels"]
    scheme = "tls" if which == "tls" else "tcp"
    for name, workload in _workloads(docs).items():
        container = workload["spec"]["template"]["spec"]["containers"][0]
        if name == "silcr-router":
            args = container["args"]
            assert args[args.index("--listen") + 1] == f"{scheme}/0.0.0.0:{port['port']}"
            assert container["ports"][0]["name"] == port["targetPort"]
            continue
        assert _env(docs, container)["SILCR_CONNECT"] == f"{scheme}/silcr-router:{port['port']}", name


def test_volumes_claims_and_config_maps_match(rendered):
    which, docs = rendered
    maps = set(_by(docs, "ConfigMap"))
    claims = set(_by(docs, "PersistentVolumeClaim"))
    claimed = []
    for name, workload in _workloads(docs).items():
        pod = workload["spec"]["template"]["spec"]
        volumes = {v["name"]: v for v in pod.get("volumes", [])}
        for container in pod["containers"]:
            for mount in container.get("volumeMounts", []):
                assert mount["name"] in volumes, f"{name}: {mount['name']}"
            for source in container.get("envFrom", []):
                assert source["configMapRef"]["name"] in maps
        for volume in volumes.values():
            if "configMap" in volume:
                assert volume["configMap"]["name"] in maps, f"{name}: {volume}"
            if "secret" in volume:  # the one object the user makes (deploy/make-certs.sh): only its own role's key
                assert which == "tls" and volume["secret"]["secretName"] == "silcr-certs"
                role = ROLES.get(name, "router")
                assert {i["key"] for i in volume["secret"]["items"]} == {"ca.pem", f"{role}.key", f"{role}.pem"}
            if "persistentVolumeClaim" in volume:  # the learner's and the buffer's run directories, one pod each
                assert volume["persistentVolumeClaim"]["claimName"] in claims, f"{name}: {volume}"
                assert workload["spec"]["parallelism"] == 1 and volume["name"] == "runs"
                claimed.append(volume["persistentVolumeClaim"]["claimName"])
                mount = next(m for m in pod["containers"][0]["volumeMounts"] if m["name"] == "runs")
                assert mount["mountPath"] == _env(docs, pod["containers"][0])["SILCR_RUNS_DIR"]
    assert sorted(claimed) == sorted(claims) == ["silcr-buffer-runs", "silcr-learner-runs"]  # one claim, one pod


def test_the_actor_jobs_parallelism_is_the_scaling_knob(rendered):
    _, docs = rendered
    actor = _workloads(docs)["silcr-actor"]
    # workers that end together: no completion count, so each pod's exit 0 at the run's end completes the Job
    assert actor["kind"] == "Job" and actor["spec"]["parallelism"] >= 1 and "completions" not in actor["spec"]
    container = actor["spec"]["template"]["spec"]["containers"][0]
    args = container["args"]
    assert args[args.index("--actor-id") + 1] == "-1"  # replicas of one pod spec pick their own ids
    assert "ports" not in container and container["resources"]["requests"]["cpu"] == "1"
    assert sum(1 for w in _workloads(docs).values() if w["spec"]["template"]["metadata"]["labels"]
               == actor["spec"]["template"]["metadata"]["labels"]) == 1  # one kind of pod per Job


def test_every_command_environment_and_probe_is_a_valid_silcr_command(rendered, monkeypatch):
    which, docs = rendered
    parser, subs = build_parser()
    settings = _by(docs, "ConfigMap")
    toml = next(v for k, v in settings.items() if k.startswith("silcr-settings"))["data"]["silcr.toml"]
    assert toml == (REPO / "deploy" / "config" / "silcr.toml").read_text()  # the copy kustomize can read
    assert toml == (K8S / "base" / "silcr.toml").read_text()
    for name, workload in _workloads(docs).items():
        container = workload["spec"]["template"]["spec"]["containers"][0]
        args = [a.replace("/config/silcr.toml", str(K8S / "base" / "silcr.toml")) for a in container["args"]]
        role = args[0]
        assert role in subs
        env = _env(docs, container)
        if which == "tls" and "SILCR_ZENOH_CONFIG" in env:
            env["SILCR_ZENOH_CONFIG"] = str(K8S / "overlays" / "tls" / env["SILCR_ZENOH_CONFIG"].lstrip("/"))
        parsed = parser.parse_args(args)  # exits 2 on an unknown option
        if role == "router":
            continue
        cfg = resolve(parsed, role, environ=env)
        assert cfg.run == "k8s" and cfg.zenoh_mode == "client"
        if role in ("buffer", "learner"):
            assert cfg.resume and cfg.runs_dir == "/runs" and cfg.total_steps == 2_000_000
        if role == "actor":
            assert cfg.actor_id == -1
        if role == "learner":
            assert cfg.device == ("cuda" if which == "gpu" else "auto")
            limits = container["resources"].get("limits", {})
            assert (limits.get("nvidia.com/gpu") == "1") == (which == "gpu")
        if role != "monitor":
            assert cfg.health_file == "/tmp/silcr-health.json"
            for probe in ("startupProbe", "livenessProbe", "readinessProbe"):
                command = container[probe]["exec"]["command"]
                assert command[:2] == ["silcr", "health"], (name, probe)
                health = resolve(parser.parse_args(command[1:]), "health", environ=env)
                assert health.health_file == cfg.health_file and health.connect == cfg.connect
            assert "--ready" in container["readinessProbe"]["exec"]["command"]
            assert "--ready" not in container["livenessProbe"]["exec"]["command"]  # stuck, not unreachable


def test_the_tls_overlays_zenoh_files_are_the_templates_with_the_clusters_paths():
    """zenoh/*.json5 in the overlay are deploy/zenoh's templates with CERTS, RUN and ROLE filled in (outside
    comments), so the two cannot drift apart."""
    def filled(text: str, pairs) -> str:
        out = []
        for line in text.splitlines(keepends=True):
            if not line.lstrip().startswith("//"):
                for a, b in pairs:
                    line = line.replace(a, b)
            out.append(line)
        return "".join(out)

    def body(path) -> str:
        return "".join(line for line in path.read_text().splitlines(keepends=True)[2:])  # after the 2-line note

    tls, templates = K8S / "overlays" / "tls" / "zenoh", REPO / "deploy" / "zenoh"
    assert body(tls / "router.json5") == filled((templates / "router-tls-acl.json5").read_text(),
                                                [("CERTS", "/certs"), ("RUN", "k8s")])
    for role in ROLES.values():
        assert body(tls / f"{role}.json5") == filled((templates / "client-tls.json5").read_text(),
                                                     [("CERTS", "/certs"), ("ROLE", role)])


def test_a_finished_run_leaves_every_job_complete(rendered):
    """The finished-run rule on Kubernetes: every part of a run is a Job whose pods are restarted only on failure,
    so a component that exits 0 at the run's end is done, and nothing retrains the run (a Deployment or a
    StatefulSet restarts every pod that ends). The router follows the run and ends with it."""
    _, docs = rendered
    for name, job in _workloads(docs).items():
        pod = job["spec"]["template"]["spec"]
        assert pod["restartPolicy"] == "OnFailure" and job["spec"]["backoffLimit"] >= 1, name
        assert job["spec"].get("completions", 1) == 1 or name == "silcr-actor"
    router = _workloads(docs)["silcr-router"]["spec"]["template"]["spec"]["containers"][0]["args"]
    env = _env(docs, _workloads(docs)["silcr-learner"]["spec"]["template"]["spec"]["containers"][0])
    assert router[router.index("--run") + 1] == env["SILCR_RUN"]
