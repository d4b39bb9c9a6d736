"""A real Slurm cluster on this machine for tests/test_slurm.py: Debian's slurmctld, slurmd and munge, a controller
and three compute nodes, each node in a network namespace of its own with its own address.

The namespaces hang off a bridge in a namespace of its own (the host's firewall may drop forwarded bridge traffic);
the controller sits on the host end of one more veth, so the test reaches the nodes' addresses from here. Each
slurmd runs in its node's network namespace and a UTS namespace named after the node (`ip netns exec` remounts
/sys, which slurmd 22.05 refuses). Names resolve through /etc/hosts entries added for the cluster's life. Every
daemon, namespace, link and hosts entry is removed on `close` (../shared/notes/slurm.md has what worked).
"""

from __future__ import annotations

import os
import secrets
import shutil
import subprocess
import time
from pathlib import Path

PACKAGES = ("slurmctld", "slurmd", "slurm-client", "munge")
NODES = 3


def problem() -> str | None:
    """Why no cluster can be started here (None: one can)."""
    if os.geteuid() != 0:
        return "needs root (network namespaces, Slurm's daemons)"
    if shutil.which("ip") is None or shutil.which("nsenter") is None or shutil.which("unshare") is None:
        return "needs iproute2's ip and util-linux's nsenter and unshare"
    missing = [p for p, exe in zip(PACKAGES, ("slurmctld", "slurmd", "sbatch", "munged")) if shutil.which(exe) is None]
    if missing:
        r = subprocess.run(["apt-get", "install", "-y", "-q", "--no-install-recommends", *PACKAGES],
                           capture_output=True, text=True, timeout=600,
                           env={**os.environ, "DEBIAN_FRONTEND": "noninteractive"})
        if r.returncode != 0 or shutil.which("slurmctld") is None:
            return f"Debian's {' '.join(missing)} could not be installed ({r.stderr.strip().splitlines()[-1:]})"
    return None


class Cluster:
    """The controller and NODES compute nodes; `node_addr(i)` for i in 1..NODES, `env` for the Slurm tools."""

    def __init__(self, work: Path) -> None:
        self.work = work
        self.tag = secrets.token_hex(2)
        self.subnet = f"10.{200 + secrets.randbelow(50)}.{secrets.randbelow(250)}"
        self.controller_addr = f"{self.subnet}.1"
        self.names = [f"sl{self.tag}n{i}" for i in range(1, NODES + 1)]
        self.bridge_ns = f"sl{self.tag}br"
        self.ctl_link = f"sl{self.tag}c"
        self.controller = f"sl{self.tag}ctl"
        self.hosts_marker = f"# silcr test cluster {self.tag}"
        self.pids: list[int] = []
        self.conf = work / "slurm.conf"
        self.env = {**os.environ, "SLURM_CONF": str(self.conf)}
        self._logs: list = []

    def node_addr(self, i: int) -> str:
        return f"{self.subnet}.{10 + i}"

    # -- start ------------------------------------------------------------------------------------------
    def start(self) -> "Cluster":
        try:
            self._network()
            self._hosts()
            self._munge()
            self._slurm()
        except BaseException:
            self.close()
            raise
        return self

    def _ip(self, *args: str) -> None:
        subprocess.run(["ip", *args], check=True, capture_output=True, timeout=30)

    def _network(self) -> None:
        br = self.bridge_ns
        self._ip("netns", "add", br)
        self._ip("-n", br, "link", "add", "br0", "type", "bridge")
        self._ip("-n", br, "link", "set", "br0", "up")
        self._ip("-n", br, "link", "set", "lo", "up")
        # the controller: the host end of a veth into the bridge
        self._ip("link", "add", self.ctl_link, "type", "veth", "peer", "name", f"{self.ctl_link}b")
        self._ip("link", "set", f"{self.ctl_link}b", "netns", br)
        self._ip("-n", br, "link", "set", f"{self.ctl_link}b", "master", "br0", "up")
        self._ip("addr", "add", f"{self.controller_addr}/24", "dev", self.ctl_link)
        self._ip("link", "set", self.ctl_link, "up")
        for i, name in enumerate(self.names, 1):
            self._ip("netns", "add", name)
            self._ip("link", "add", f"{name}b", "type", "veth", "peer", "name", "eth0", "netns", name)
            self._ip("link", "set", f"{name}b", "netns", br)
            self._ip("-n", br, "link", "set", f"{name}b", "master", "br0", "up")
            self._ip("-n", name, "addr", "add", f"{self.node_addr(i)}/24", "dev", "eth0")
            self._ip("-n", name, "link", "set", "eth0", "up")
            self._ip("-n", name, "link", "set", "lo", "up")

    def _hosts(self) -> None:
        lines = [f"{self.controller_addr} {self.controller} {self.hosts_marker}"]
        lines += [f"{self.node_addr(i)} {name} {self.hosts_marker}" for i, name in enumerate(self.names, 1)]
        with open("/etc/hosts", "a") as f:
            f.write("\n".join(lines) + "\n")

    def _spawn(self, name: str, args: list[str]) -> int:
        log = open(self.work / f"{name}.out", "w")
        self._logs.append(log)
        p = subprocess.Popen(args, stdout=log, stderr=subprocess.STDOUT, env=self.env, start_new_session=True)
        self.pids.append(p.pid)
        return p.pid

    def _munge(self) -> None:
        d = self.work / "munge"
        d.mkdir()
        key = d / "munge.key"
        key.write_bytes(secrets.token_bytes(1024))
        key.chmod(0o400)
        self.munge_socket = d / "munge.socket"
        self._spawn("munged", ["munged", "-F", "--force", f"--key-file={key}", f"--socket={self.munge_socket}",
                               f"--pid-file={d / 'munged.pid'}", f"--log-file={d / 'munged.log'}",
                               f"--seed-file={d / 'munged.seed'}"])
        deadline = time.monotonic() + 20
        while not self.munge_socket.exists():
            if time.monotonic() > deadline:
                raise RuntimeError(f"munged did not start: {(self.work / 'munged.out').read_text()[-1000:]}")
            time.sleep(0.1)

    def _slurm(self) -> None:
        d = self.work
        (d / "state").mkdir()
        (d / "spool").mkdir()
        addrs = ",".join(self.node_addr(i) for i in range(1, NODES + 1))
        nodes = f"sl{self.tag}n[1-{NODES}]"
        port = 26000 + secrets.randbelow(1000) * 2
        self.conf.write_text(f"""ClusterName=silcr{self.tag}
MailProg=/bin/true
SlurmctldHost={self.controller}({self.controller_addr})
SlurmUser=root
SlurmdUser=root
SlurmctldPort={port}
SlurmdPort={port + 1}
AuthType=auth/munge
CredType=cred/munge
AuthInfo=socket={self.munge_socket}
StateSaveLocation={d / 'state'}
SlurmdSpoolDir={d / 'spool'}/%n
SlurmctldPidFile={d / 'slurmctld.pid'}
SlurmdPidFile={d / 'spool'}/slurmd-%n.pid
SlurmctldLogFile={d / 'slurmctld.log'}
SlurmdLogFile={d / 'spool'}/slurmd-%n.log
ProctrackType=proctrack/linuxproc
TaskPlugin=task/none
SelectType=select/cons_tres
SelectTypeParameters=CR_Core
SwitchType=switch/none
MpiDefault=none
ReturnToService=2
AccountingStorageType=accounting_storage/none
JobAcctGatherType=jobacct_gather/none
JobCompType=jobcomp/none
KillWait=30
MinJobAge=3600
NodeName={nodes} NodeAddr={addrs} CPUs=2 RealMemory=2000 State=UNKNOWN
PartitionName=test Nodes={nodes} Default=YES MaxTime=INFINITE State=UP
""")
        # slurmctld runs only where the host's name is SlurmctldHost's: a UTS namespace of its own gives it that name
        self._spawn("slurmctld", ["unshare", "--uts", "sh", "-c",
                                  f"hostname {self.controller}; exec slurmctld -D -f {self.conf}"])
        for name in self.names:
            self._spawn(f"slurmd-{name}", ["nsenter", f"--net=/run/netns/{name}", "unshare", "--uts", "sh", "-c",
                                           f"hostname {name}; exec slurmd -D -f {self.conf} -N {name}"])
        deadline = time.monotonic() + 60
        while True:
            r = subprocess.run(["sinfo", "-h", "-N", "-t", "idle", "-o", "%N"], capture_output=True, text=True,
                               env=self.env, timeout=30)
            if len(set(r.stdout.split())) == NODES:
                return
            if time.monotonic() > deadline:
                raise RuntimeError(f"the nodes did not come up: {r.stdout} {r.stderr}; "
                                   f"{(self.work / 'slurmctld.log').read_text()[-2000:] if (self.work / 'slurmctld.log').exists() else ''}")
            time.sleep(0.5)

    # -- use ---------------------------------------------------------------------------------------------
    def run(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
        return subprocess.run(list(args), capture_output=True, text=True, env=self.env, timeout=timeout)

    def job(self, job_id: str) -> dict[str, str]:
        """`scontrol show job`'s fields (JobState, ExitCode, NodeList, ...); {} once Slurm forgot the job."""
        r = self.run("scontrol", "show", "job", "-o", job_id)
        fields = {}
        for part in r.stdout.split():
            key, _, value = part.partition("=")
            fields.setdefault(key, value)
        return fields

    # -- stop --------------------------------------------------------------------------------------------
    def close(self) -> None:
        subprocess.run(["scancel", "--full", "--signal=KILL", "-u", "root"], capture_output=True, env=self.env,
                       timeout=30)
        for pid in reversed(self.pids):
            try:
                os.killpg(pid, 15)
            except ProcessLookupError:
                pass
        deadline = time.monotonic() + 10
        for pid in self.pids:
            while time.monotonic() < deadline:
                try:
                    if os.waitpid(pid, os.WNOHANG)[0]:
                        break
                except ChildProcessError:
                    break
                time.sleep(0.1)
            try:
                os.killpg(pid, 9)
            except ProcessLookupError:
                pass
        for log in self._logs:
            log.close()
        # What a job left behind on a node (a step's processes outlive a killed slurmd): every process in its
        # network namespace.
        for name in self.names:
            pids = subprocess.run(["ip", "netns", "pids", name], capture_output=True, text=True, timeout=30).stdout
            for pid in pids.split():
                try:
                    os.kill(int(pid), 9)
                except (ProcessLookupError, ValueError):
                    pass
        for name in [*self.names, self.bridge_ns]:
            subprocess.run(["ip", "netns", "del", name], capture_output=True, timeout=30)
        subprocess.run(["ip", "link", "del", self.ctl_link], capture_output=True, timeout=30)
        try:
            lines = Path("/etc/hosts").read_text().splitlines(keepends=True)
            Path("/etc/hosts").write_text("".join(line for line in lines if self.hosts_marker not in line))
        except OSError:
            pass
