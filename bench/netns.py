"""Several hosts on one Linux machine: network namespaces joined by veth links (needs root and iproute2).

`hub` is one namespace; each of `hosts` more is linked to it by its own veth pair, as a
machine on its own cable, and the root namespace (where the caller runs) is linked to the
hub too. Link 0 joins root and hub; link i joins host i and hub. On link i the hub's
address is `addr(i, 1)` and the other end's `addr(i, 2)`. Used by `silcr bench scale
--hosts` and tests/test_multihost.py.
"""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess


# Every namespace this module makes starts with it, so that a leftover is easy to find.
NAME_PREFIX = "silcrns"


def _ip(*args: str) -> None:
    subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)


def why_not_namespaces() -> str | None:
    """Why network namespaces cannot be made here, or None if they can."""
    if shutil.which("ip") is None:
        return "iproute2 (`ip`) is not installed"
    if os.geteuid() != 0:
        return "network namespaces need root"
    probe = f"silcrprobe{secrets.token_hex(2)}"
    r = subprocess.run(["ip", "netns", "add", probe], capture_output=True, text=True)
    if r.returncode != 0:
        return f"cannot create a network namespace here: {r.stderr.strip()}"
    subprocess.run(["ip", "netns", "del", probe], capture_output=True)
    return None


class Namespaces:
    """A hub, `hosts` hosts linked to it, and the root namespace linked to it; torn down on exit."""

    def __init__(self, hosts: int) -> None:
        if not 1 <= hosts <= 200:
            raise ValueError(f"hosts must be 1 to 200, got {hosts}")
        self.tag = secrets.token_hex(2)
        self.hub = f"{NAME_PREFIX}{self.tag}h"
        self.hosts = [f"{NAME_PREFIX}{self.tag}a{i}" for i in range(1, hosts + 1)]
        self.net = 200 + secrets.randbelow(50)
        self.created: list[str] = []

    def addr(self, link: int, host: int) -> str:
        return f"10.{self.net}.{link}.{host}"

    def link_name(self, side: str, link: int) -> str:
        return f"sv{self.tag}{side}{link}"  # <= 15 characters

    def __enter__(self) -> "Namespaces":
        try:
            for ns in (self.hub, *self.hosts):
                _ip("netns", "add", ns)
                self.created.append(ns)
                _ip("-n", ns, "link", "set", "lo", "up")
            for link, ns in ((0, None), *enumerate(self.hosts, start=1)):
                near, far = self.link_name("x", link), self.link_name("h", link)
                _ip("link", "add", near, "type", "veth", "peer", "name", far)
                _ip("link", "set", far, "netns", self.hub)
                _ip("-n", self.hub, "addr", "add", f"{self.addr(link, 1)}/24", "dev", far)
                _ip("-n", self.hub, "link", "set", far, "up")
                if ns is not None:
                    _ip("link", "set", near, "netns", ns)
                    _ip("-n", ns, "addr", "add", f"{self.addr(link, 2)}/24", "dev", near)
                    _ip("-n", ns, "link", "set", near, "up")
                else:
                    _ip("addr", "add", f"{self.addr(link, 2)}/24", "dev", near)
                    _ip("link", "set", near, "up")
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        subprocess.run(["ip", "link", "del", self.link_name("x", 0)], capture_output=True)
        for ns in self.created:  # deleting a namespace deletes the veth ends in it
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        self.created = []
