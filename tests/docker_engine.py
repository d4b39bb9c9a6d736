"""What the real-engine compose test needs around it: a Docker engine, a `python:3.11-slim` base image, a package
index for torch on 127.0.0.1, and silcr's image built from deploy/Dockerfile as a user builds it.

No image registry is reachable on the project's machines: when `python:3.11-slim` cannot be pulled, a stand-in of
that name is built from Debian's packages (debootstrap, then `docker import`), with Python where the official image
has it. Torch comes from a PEP 503 index served on 127.0.0.1 from what `pip download torch==2.13.0` fetches; every
other dependency from the index pip is configured with, through the host's CA bundle (`deploy/ca-certificates/`).
"""

from __future__ import annotations

import functools
import hashlib
import html
import http.server
import os
import re
import shutil
import subprocess
import sys
import tarfile
import threading
from pathlib import Path

BASE_IMAGE = "python:3.11-slim"
HOST_CA_BUNDLE = Path("/etc/ssl/certs/ca-certificates.crt")
#: What the image's build context holds (as the repository's .dockerignore lets through, and a little more).
CONTEXT_SKIP = (".git", ".venv", "runs", "results", "build", "dist", "*.egg-info", "__pycache__", ".pytest_cache",
                ".hypothesis", "bench-results", "demos")


def docker(*args: str, timeout: float = 120, check: bool = True, **kw) -> subprocess.CompletedProcess:
    r = subprocess.run(["docker", *args], capture_output=True, text=True, timeout=timeout, **kw)
    if check and r.returncode != 0:
        raise RuntimeError(f"docker {' '.join(args[:3])} failed ({r.returncode}): {r.stdout.strip()[-3000:]}\n"
                           f"{r.stderr.strip()[-2000:]}")
    return r


def engine_problem() -> str | None:
    """Why no engine can be used here, or None."""
    if shutil.which("docker") is None:
        return "the docker command is not installed (Debian: apt-get install docker.io)"
    try:
        r = docker("info", "--format", "{{.ServerVersion}}", timeout=30, check=False)
    except subprocess.TimeoutExpired:
        return "docker info did not answer within 30 s"
    if r.returncode != 0:
        return f"no Docker engine answers docker info ({r.stderr.strip().splitlines()[-1] if r.stderr.strip() else r.returncode})"
    return None


def compose_command() -> list[str] | None:
    """Debian's docker-compose 1.29, or the engine's `docker compose` (v2)."""
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    return None


def ensure_base_image(work: Path) -> str:
    """`python:3.11-slim` present: pulled, or a stand-in built from Debian's packages. How it got there."""
    if docker("image", "inspect", BASE_IMAGE, check=False).returncode == 0:
        return "present"
    if docker("pull", BASE_IMAGE, timeout=300, check=False).returncode == 0:
        return "pulled"
    if os.geteuid() != 0 or shutil.which("debootstrap") is None:
        raise RuntimeError(f"{BASE_IMAGE} cannot be pulled, and a stand-in needs root and debootstrap "
                           f"(apt-get install debootstrap)")
    rootfs = work / "rootfs"
    subprocess.run(["debootstrap", "--variant=minbase", "--include=python3,python3-pip,python3-venv,ca-certificates",
                    "bookworm", str(rootfs), "http://deb.debian.org/debian"], check=True, capture_output=True,
                   timeout=1200)
    # Where the official image has them: `python` and `pip` on the PATH, and pip free to install.
    for name, target in (("python", "/usr/bin/python3"), ("pip", "/usr/bin/pip3")):
        link = rootfs / "usr/local/bin" / name
        link.parent.mkdir(parents=True, exist_ok=True)
        link.unlink(missing_ok=True)
        link.symlink_to(target)
    for marker in rootfs.glob("usr/lib/python3*/EXTERNALLY-MANAGED"):
        marker.unlink()
    shutil.rmtree(rootfs / "var/cache/apt/archives", ignore_errors=True)
    archive = work / "rootfs.tar"
    with tarfile.open(archive, "w") as tar:
        tar.add(rootfs, arcname=".")
    shutil.rmtree(rootfs)
    docker("import", "--change", "ENV PATH=/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin", "--change",
           'CMD ["python3"]', str(archive), BASE_IMAGE, timeout=600)
    archive.unlink()
    return "stand-in built from Debian's packages"


def _normalised(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def torch_index(directory: Path) -> Path:
    """A PEP 503 index (`<directory>/simple/<project>/`) of torch 2.13.0 and what it needs, as pip downloads them."""
    wheels = directory / "wheels"
    wheels.mkdir(parents=True, exist_ok=True)
    subprocess.run([sys.executable, "-m", "pip", "download", "--quiet", "--dest", str(wheels), "torch==2.13.0"],
                   check=True, timeout=900, capture_output=True)
    simple = directory / "simple"
    projects: dict[str, list[Path]] = {}
    for f in sorted(wheels.iterdir()):
        projects.setdefault(_normalised(f.name.split("-")[0]), []).append(f)
    for project, files in projects.items():
        page = simple / project
        page.mkdir(parents=True, exist_ok=True)
        links = []
        for f in files:
            (page / f.name).unlink(missing_ok=True)
            (page / f.name).symlink_to(f)
            digest = hashlib.sha256(f.read_bytes()).hexdigest()
            links.append(f'<a href="{html.escape(f.name)}#sha256={digest}">{html.escape(f.name)}</a><br>')
        (page / "index.html").write_text("<!DOCTYPE html><html><body>\n" + "\n".join(links) + "\n</body></html>\n")
    return simple


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, *args) -> None:
        pass


def serve(directory: Path) -> tuple[http.server.ThreadingHTTPServer, int]:
    """Serve `directory` on 127.0.0.1 (a free port) from a thread; the server and its port."""
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), functools.partial(QuietHandler, directory=str(directory)))
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server, server.server_address[1]


def build_context(repo: Path, where: Path) -> Path:
    """The repository as a user's checkout holds it, with the host's CA bundle where the Dockerfile takes extra
    certificates from (this machine reaches the package index through a TLS-intercepting proxy)."""
    shutil.copytree(repo, where, ignore=shutil.ignore_patterns(*CONTEXT_SKIP), symlinks=True)
    if HOST_CA_BUNDLE.exists():
        shutil.copy(HOST_CA_BUNDLE, where / "deploy" / "ca-certificates" / "host.crt")
    return where


def build_image(context: Path, tag: str, torch_index_url: str) -> None:
    """`docker build` of deploy/Dockerfile, on the host's network (the torch index listens on its loopback)."""
    docker("build", "--network", "host", "-f", "deploy/Dockerfile", "-t", tag, "--build-arg",
           f"TORCH_INDEX={torch_index_url}", "--build-arg", "PIP_TRUSTED_HOST=127.0.0.1", ".", cwd=context,
           timeout=1500, env={**os.environ, "DOCKER_BUILDKIT": "0"})
