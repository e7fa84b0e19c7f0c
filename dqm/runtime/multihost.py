"""Run a job across "hosts": network namespaces joined to a router namespace by veth pairs.

Used by ``scripts/multihost_demo.py`` (by hand) and ``tests/runtime/test_runtime_multihost.py``;
the job helpers (:func:`start_job`, :func:`finish_job`) also serve the TLS and
concurrent-job tests, where every process runs on loopback.

Topology (needs root and network namespaces; nothing leaves the machine)::

    <tag>-h1  eth0 10.213.1.2/24 ---- r-h1 10.213.1.1/24 \
    <tag>-h2  eth0 10.213.2.2/24 ---- r-h2 10.213.2.1/24  >  <tag>-router  (dqm router)
    <tag>-h3  eth0 10.213.3.2/24 ---- r-h3 10.213.3.1/24 /

The router listens on each of its veth addresses; the processes of host i
connect to 10.213.i.1. Every agent-to-agent message crosses two veths (sender
host -> router -> receiver host), so the router-side counters of the veths
(``ip -s -j link``) are the kernel's view of the traffic the runtime meters.
"""
from __future__ import annotations

import json
import logging
import os
import shutil
import subprocess
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Dict, List, Optional, Sequence

from ..distributed.config import DQMConfig
from .launcher import (  # noqa: F401
    START_LIMITS,
    Processes,
    finish_job,
    make_certs,
    secure_router_args,
    start_job,
    tls_options,
    wait_listening,
    write_agent_files,
)

LOG = logging.getLogger("dqm.runtime")
SUBNET = "10.213"
ROUTER_PORT = 7447


def _kill_in_namespace(inode) -> None:
    """SIGKILL every process whose network namespace has this (device, inode)."""
    for entry in os.listdir("/proc"):
        if not entry.isdigit():
            continue
        try:
            st = os.stat(f"/proc/{entry}/ns/net")
        except OSError:
            continue
        if (st.st_dev, st.st_ino) == inode:
            try:
                os.kill(int(entry), 9)
            except ProcessLookupError:
                pass


class NamespacesUnavailable(RuntimeError):
    """Network namespaces / veth pairs cannot be created here (not root, no ip, a sandbox)."""


def _ip(*args: str, check: bool = True, timeout: float = 10.0) -> subprocess.CompletedProcess:
    r = subprocess.run(["ip", *args], capture_output=True, text=True, timeout=timeout)
    if check and r.returncode != 0:
        raise subprocess.CalledProcessError(r.returncode, ["ip", *args], r.stdout, r.stderr)
    return r


def netns_unavailable_reason() -> Optional[str]:
    """None if this process may create network namespaces, else why not (for a skip message)."""
    if not hasattr(os, "geteuid") or os.geteuid() != 0:
        return "network namespaces need root (run as root, e.g. sudo)"
    if shutil.which("ip") is None:
        return "the 'ip' command (iproute2) is not installed"
    probe = f"dqmprobe{os.getpid()}"
    try:
        r = _ip("netns", "add", probe, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"'ip netns add' failed: {exc}"
    if r.returncode != 0:
        return f"network namespaces are not permitted here ('ip netns add' said: {r.stderr.strip()})"
    _ip("netns", "del", probe, check=False)
    return None


@dataclass
class Namespaces:
    """A router namespace and ``hosts`` host namespaces, each joined to the router by a veth pair.

    Use as a context manager: the namespaces (and with them the veths) are
    deleted on exit, also after an error. Processes started in them must be
    stopped before (``Processes.stop_all``); :meth:`delete` kills stragglers.
    """

    hosts: int = 3
    tag: str = field(default_factory=lambda: f"dqm{os.getpid() % 100000}")
    subnet: str = SUBNET
    created: List[str] = field(default_factory=list)

    @property
    def router_ns(self) -> str:
        return f"{self.tag}-router"

    def host_ns(self, h: int) -> str:
        return f"{self.tag}-h{h + 1}"

    def router_addr(self, h: int) -> str:
        """The router's address on host h's link (what host h connects to)."""
        return f"{self.subnet}.{h + 1}.1"

    def host_addr(self, h: int) -> str:
        return f"{self.subnet}.{h + 1}.2"

    def router_veth(self, h: int) -> str:
        return f"r-h{h + 1}"

    @staticmethod
    def prefix(ns: str) -> List[str]:
        """Command prefix that runs a program inside namespace ``ns``."""
        return ["ip", "netns", "exec", ns]

    def create(self) -> "Namespaces":
        try:
            for ns in [self.router_ns] + [self.host_ns(h) for h in range(self.hosts)]:
                _ip("netns", "add", ns)
                self.created.append(ns)
                # IPv6 off: no router solicitations / MLD reports in the counters
                for key in ("all", "default"):
                    subprocess.run(["ip", "netns", "exec", ns, "sysctl", "-q", "-w",
                                    f"net.ipv6.conf.{key}.disable_ipv6=1"], capture_output=True, timeout=10)
                _ip("-n", ns, "link", "set", "lo", "up")
            for h in range(self.hosts):
                hn, rv = self.host_ns(h), self.router_veth(h)
                _ip("link", "add", rv, "netns", self.router_ns, "type", "veth", "peer", "name", "eth0", "netns", hn)
                _ip("-n", self.router_ns, "addr", "add", f"{self.router_addr(h)}/24", "dev", rv)
                _ip("-n", hn, "addr", "add", f"{self.host_addr(h)}/24", "dev", "eth0")
                _ip("-n", self.router_ns, "link", "set", rv, "up")
                _ip("-n", hn, "link", "set", "eth0", "up")
        except (subprocess.CalledProcessError, OSError, subprocess.TimeoutExpired) as exc:
            detail = getattr(exc, "stderr", "") or str(exc)
            self.delete()
            raise NamespacesUnavailable(f"cannot build the namespace topology: {detail.strip()}") from None
        return self

    def delete(self) -> None:
        """Delete the namespaces; no process may keep one alive after we are gone.

        A process being started with ``ip netns exec`` may enter its namespace
        just after a listing of the namespace's processes: so the name is
        removed first (later entries fail), then every process whose network
        namespace is that one (same inode) is killed, over a few scans.
        """
        for ns in reversed(self.created):
            try:
                st = os.stat(f"/var/run/netns/{ns}")
                inode = (st.st_dev, st.st_ino)
            except OSError:
                inode = None
            _ip("netns", "del", ns, check=False)
            for _ in range(6):
                if inode is not None:
                    _kill_in_namespace(inode)
                time.sleep(0.05)
        self.created.clear()

    def __enter__(self) -> "Namespaces":
        return self.create()

    def __exit__(self, *exc) -> None:
        self.delete()

    def counters(self) -> Dict[int, Dict[str, int]]:
        """Kernel byte/packet counters of each host's veth, seen from the router side:
        ``rx`` = what host h sent to the router, ``tx`` = what the router sent to host h."""
        out = {}
        for h in range(self.hosts):
            info = json.loads(_ip("-n", self.router_ns, "-s", "-j", "link", "show", "dev", self.router_veth(h)).stdout)
            st = info[0]["stats64"]
            out[h] = {"rx_bytes": st["rx"]["bytes"], "rx_packets": st["rx"]["packets"],
                      "tx_bytes": st["tx"]["bytes"], "tx_packets": st["tx"]["packets"]}
        return out


CGROUP_CPU = Path("/sys/fs/cgroup/cpu")


@dataclass
class EmulatedHosts(Namespaces):
    """:class:`Namespaces` that behave like small machines on a real network: every host (and its
    processes) in a cgroup-v1 CPU quota of ``cpu_cores`` cores (the router namespace, the network,
    has none), and every veth capped at ``rate_mbit`` Mbit/s in each direction with ``tc tbf``
    (``netem`` is not available here, so links add no delay beyond queueing). ``None``: no limit.
    """

    rate_mbit: Optional[float] = None
    cpu_cores: Optional[float] = None
    cgroups: List[Path] = field(default_factory=list)

    def cgroup(self, h: int) -> Path:
        return CGROUP_CPU / f"{self.tag}-h{h + 1}"

    def create(self) -> "EmulatedHosts":
        super().create()
        try:
            if self.rate_mbit is not None:
                bps = self.rate_mbit * 1e6 / 8
                burst = int(max(96 * 1024, bps / 250))  # >= a 64 KiB GSO segment, >= 4 ms of traffic
                limit = int(max(256 * 1024, bps * 0.1))  # 100 ms of queue
                for h in range(self.hosts):
                    for ns, dev in ((self.host_ns(h), "eth0"), (self.router_ns, self.router_veth(h))):
                        _ip_tc(ns, "qdisc", "replace", "dev", dev, "root", "tbf", "rate", f"{self.rate_mbit}mbit",
                               "burst", str(burst), "limit", str(limit))
            if self.cpu_cores is not None:
                if not (CGROUP_CPU / "cpu.cfs_quota_us").exists():
                    raise NamespacesUnavailable(f"no cgroup-v1 CPU controller at {CGROUP_CPU}")
                for h in range(self.hosts):
                    cg = self.cgroup(h)
                    cg.mkdir(exist_ok=True)
                    self.cgroups.append(cg)
                    (cg / "cpu.cfs_period_us").write_text("100000\n")
                    (cg / "cpu.cfs_quota_us").write_text(f"{max(1000, int(self.cpu_cores * 100000))}\n")
        except (subprocess.CalledProcessError, OSError) as exc:
            detail = getattr(exc, "stderr", "") or str(exc)
            self.delete()
            raise NamespacesUnavailable(f"cannot emulate the hosts: {str(detail).strip()}") from None
        LOG.info("%d emulated hosts (%s): links %s, CPU %s", self.hosts, self.tag,
                 "unlimited" if self.rate_mbit is None else f"{self.rate_mbit:g} Mbit/s",
                 "unlimited" if self.cpu_cores is None else f"{self.cpu_cores:g} cores each")
        return self

    def host_prefix(self, h: int) -> List[str]:
        """Command prefix that runs a program on host h: in its CPU quota, in its namespace."""
        ns = self.prefix(self.host_ns(h))
        if self.cpu_cores is None:
            return ns
        return ["sh", "-c", f'echo $$ > {self.cgroup(h)}/cgroup.procs && exec "$@"', "sh", *ns]

    def delete(self) -> None:
        super().delete()
        for cg in self.cgroups:
            for _ in range(20):  # the processes are gone with their namespaces; the kernel frees the group soon
                try:
                    cg.rmdir()
                    break
                except OSError:
                    time.sleep(0.05)
        self.cgroups.clear()


def _ip_tc(ns: str, *args: str) -> None:
    r = subprocess.run(["ip", "netns", "exec", ns, "tc", *args], capture_output=True, text=True, timeout=10)
    if r.returncode != 0:
        raise subprocess.CalledProcessError(r.returncode, ["tc", *args], r.stdout, r.stderr)


# ---------------------------------------------------------------------- jobs over any endpoint layout
def start_router(procs: Processes, endpoints: Sequence[str], workdir: Path, wait_addr, *,
                 prefix: Optional[List[str]] = None, tls_args: Sequence[str] = (), env=None,
                 deadline_s: float = 15.0, log_name: str = "router.log") -> subprocess.Popen:
    """Start ``dqm router`` and wait until it listens. ``wait_addr``: (host, port) to probe, or a
    callable that returns when the router is ready (e.g. one that probes inside a namespace)."""
    args = ["router"]
    for e in endpoints:
        args += ["--listen", e]
    ready = workdir / (log_name + ".ready")
    router = procs.start(args + ["--ready-file", str(ready), *tls_args], workdir / log_name,
                         dict(os.environ if env is None else env), prefix=prefix)
    if callable(wait_addr):
        wait_addr(router, ready, deadline_s)
    else:
        wait_listening(wait_addr[0], wait_addr[1], deadline_s, router)
    return router


def _wait_ready_file(router: subprocess.Popen, ready: Path, deadline_s: float) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        if router.poll() is not None:
            raise RuntimeError(f"the router exited with code {router.returncode} before listening")
        if ready.exists():
            return
        time.sleep(0.05)
    raise RuntimeError(f"the router was not ready within {deadline_s:.0f} s")


# ---------------------------------------------------------------------- the whole multi-host run
@dataclass
class MultihostResult:
    report: dict
    placement: Dict[str, int]            # process name -> host index
    counters: Dict[int, Dict[str, int]]  # per host: kernel bytes/packets during the job (router side)
    namespaces: List[str]

    def metered_per_host(self) -> Dict[int, Dict[str, int]]:
        """Metered bytes sent from / delivered to the processes of each host."""
        out = {h: {"sent": 0, "received": 0} for h in self.counters}
        for e in self.report["links"]:
            out[self.placement[e["src"]]]["sent"] += e["bytes"]
            out[self.placement[e["dst"]]]["received"] += e["bytes"]
        return out

    def kernel_totals(self) -> Dict[str, int]:
        return {"to_router": sum(c["rx_bytes"] for c in self.counters.values()),
                "from_router": sum(c["tx_bytes"] for c in self.counters.values()),
                "packets": sum(c["rx_packets"] + c["tx_packets"] for c in self.counters.values())}


def run_across_namespaces(descriptors, image_ids, cfg: DQMConfig, workdir: Path, hosts: int = 3,
                          timeout_s: float = 120.0, tag: Optional[str] = None, log=None,
                          tls_certs: Optional[Path] = None, acl: bool = False) -> MultihostResult:
    """Router in its own namespace, agent a on host a mod ``hosts``, coordinator on host 0.

    Builds the namespaces, runs the job, stops every process and deletes the
    namespaces (also on failure). Raises NamespacesUnavailable if they cannot be built.
    With ``tls_certs`` (a folder from :func:`make_certs` with certificates
    router, agent<i>, coordinator) every link is mutual TLS; with ``acl`` too, the router enforces
    the job's roster (:func:`dqm.runtime.roster.job_roster`: each process only its own keys).
    """
    log = log or (lambda text: None)
    cfg = cfg.validated(len(descriptors), runtime=True)
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    files = write_agent_files(descriptors, image_ids, cfg.agents, workdir)
    if acl and not tls_certs:
        raise ValueError("access control needs identities: pass tls_certs")
    router_args = (secure_router_args(workdir, cfg, tls_certs) if acl
                   else tls_options(tls_certs, "router") if tls_certs else [])
    nss = Namespaces(hosts=hosts, **({"tag": tag} if tag else {}))
    procs = Processes()
    host_of = lambda a: 0 if a < 0 else a % hosts  # noqa: E731
    with nss:
        names = [nss.router_ns] + [nss.host_ns(h) for h in range(hosts)]
        log(f"namespaces: {', '.join(names)}")
        try:
            proto = "tls" if tls_certs else "tcp"
            endpoints = [f"{proto}/{nss.router_addr(h)}:{ROUTER_PORT}" for h in range(hosts)]
            start_router(procs, endpoints, workdir, _wait_ready_file, prefix=nss.prefix(nss.router_ns),
                         tls_args=router_args)
            log(f"router in {nss.router_ns} listening on {', '.join(endpoints)}")
            before = nss.counters()
            job = start_job(procs, cfg, files, workdir,
                            connect=lambda a: f"{proto}/{nss.router_addr(host_of(a))}:{ROUTER_PORT}",
                            prefix=lambda a: nss.prefix(nss.host_ns(host_of(a))),
                            client_args=lambda a: (tls_options(tls_certs, "coordinator" if a < 0 else f"agent{a}")
                                                   if tls_certs else []),
                            limits=START_LIMITS.but(job_timeout_s=timeout_s))
            for a in range(cfg.agents):
                log(f"agent {a} in {nss.host_ns(host_of(a))} ({nss.host_addr(host_of(a))})")
            log(f"coordinator in {nss.host_ns(host_of(-1))}")
            report = finish_job(job, timeout_s + 15)
            after = nss.counters()
        finally:
            procs.stop_all()
    placement = {"coordinator": host_of(-1), **{f"agent{a}": host_of(a) for a in range(cfg.agents)}}
    counters = {h: {k: after[h][k] - before[h][k] for k in after[h]} for h in after}
    return MultihostResult(report, placement, counters, names)


#: what :func:`run_on_hosts` runs: the distributed modes, every source's features gathered to one
#: host that runs centralized QuickMatch (exact, or approximate), and ``dqm run``'s --mode auto (the
#: coordinator measures the links and picks gather, lean or balanced)
HOST_MODES = ("gather", "gather-approx", "lean", "balanced", "auto")


@dataclass
class HostRun:
    """One mode's run on emulated hosts: time to result (from starting the processes to the exit of the one
    that writes the labels: the coordinator, or the gathering host's process), bytes moved, the labels ordered
    by feature id, and timings (``job_s``, ``gather_s``, ``match_s``; lean, balanced, auto: also
    ``all_exited_s``, until the last agent's exit; auto: ``picked``, the mode it picked, and ``probe_s``)."""

    mode: str
    seconds: float
    bytes: int
    ids: "object"
    labels: "object"
    detail: Dict[str, object] = field(default_factory=dict)


def _by_id(ids, labels) -> tuple:
    """``(ids, labels)`` ordered by feature id."""
    import numpy as np

    ids, labels = np.asarray(ids), np.asarray(labels)
    order = np.argsort(ids)
    return ids[order], labels[order]


def run_on_hosts(nss: "EmulatedHosts", mode: str, cfg: DQMConfig, files: Sequence[Path], workdir: Path,
                 timeout_s: float = 600.0, gather_cores: Optional[float] = None, agent0_forked: bool = True) -> HostRun:
    """Run ``mode`` (:data:`HOST_MODES`) once on hosts that already exist, with a router listening in the
    router namespace on :data:`ROUTER_PORT`: source a's FEATURES file ``files[a]`` is on host a (one
    agent per host); the coordinator, or the gathering host, is host 0, where agent 0 runs forked from the
    coordinator's process (``dqm coordinator --also-agent``: host 0 starts one interpreter, as a gathering host
    does; ``auto``: told that every host has
    the hosts' CPU quota, which it cannot read inside a namespace, and that agent 0's host gives a gathering
    match ``gather_cores``, by default the same). ``agent0_forked=False``: agent 0 is a process of its own there."""
    m = cfg.agents
    connect = lambda h: f"tcp/{nss.router_addr(max(h, 0))}:{ROUTER_PORT}"  # noqa: E731
    procs = Processes()
    tag = f"{mode}-"
    try:
        if mode in ("lean", "balanced", "auto"):
            job = start_job(procs, cfg.but(mode=mode), files, workdir,
                            connect=connect, prefix=lambda a: nss.host_prefix(max(a, 0)),
                            limits=START_LIMITS.but(job_timeout_s=timeout_s),
                            tag=tag, threads_per_agent=None, host_cores=nss.cpu_cores,
                            gather_cores=nss.cpu_cores if gather_cores is None else gather_cores,
                            agent0_in_coordinator=agent0_forked)
            rep = finish_job(job, timeout_s + 15)
            # the agents' exits after the coordinator's are not waited for, as a gathering's senders are not
            detail: Dict[str, object] = {"job_s": rep["time_run_s"], "all_exited_s": rep["wall_s"]}
            if "auto" in rep:
                detail.update(picked=rep["auto"]["picked"], probe_s=rep["auto"]["probe_s"],
                              rates_mbit={p: r * 8 / 1e6 for p, r in rep["auto"]["rates_bytes_s"].items()},
                              predicted_s=rep["auto"]["predicted_s"], probe_pairs=rep["auto"]["probe_pairs"],
                              rates_at_least=rep["auto"]["rates_at_least"],
                              coordinator_kernel_cpu_s=rep["auto"]["kernel_cpu_s"])
            return HostRun(mode, rep["coordinator_s"], int(rep["total_bytes"]), *_by_id(rep["ids"], rep["labels"]),
                           detail)
        if mode not in ("gather", "gather-approx"):
            raise ValueError(f"unknown mode {mode!r}; one of {', '.join(HOST_MODES)}")
        out = workdir / f"{tag}result.json"
        t0 = time.monotonic()
        gather = "dqm.runtime.gather"
        recv = procs.start(["receive", "--sources", str(m), "--connect", connect(0), "--job", cfg.job,
                            "--out", str(out), "--timeout", str(timeout_s), str(files[0])]
                           + (["--approximate"] if mode == "gather-approx" else ["--engine", cfg.engine]),
                           workdir / f"{tag}receive.log", prefix=nss.host_prefix(0), module=gather)
        senders = [procs.start(["send", "--id", str(h), "--connect", connect(h), "--job", cfg.job,
                                "--timeout", str(timeout_s), str(files[h])],
                               workdir / f"{tag}send{h}.log", prefix=nss.host_prefix(h), module=gather)
                   for h in range(1, m)]
        rc = recv.wait(timeout=timeout_s + 15)
        seconds = time.monotonic() - t0
        for s in senders:
            s.wait(timeout=15)
        if rc != 0 or not out.exists():
            raise RuntimeError(f"gathering failed (exit {rc}): {(workdir / f'{tag}receive.log').read_text()[-500:]}")
        res = json.loads(out.read_text())
        return HostRun(mode, seconds, int(res["bytes"]), *_by_id(res["ids"], res["labels"]),
                       {"gather_s": res["gather_s"], "match_s": res["match_s"]})
    finally:
        procs.stop_all()
