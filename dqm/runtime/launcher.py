"""``dqm run``: router, M agents and the coordinator as separate processes on this host.

The launcher writes each agent's own features (the images it owns) to a file
(every agent also learns where the others' files are, so that it can take over
a lost agent), starts the processes, waits with deadlines, and always cleans
up: on success, on failure and on Ctrl-C / SIGTERM no child is left behind;
the children also die with the launcher if it is killed outright
(dqm.runtime.lifeline), and a killed launcher's temporary folder is removed
by the next run.
"""
from __future__ import annotations

import json
import logging
import os
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator, List, Optional, Sequence

import numpy as np

from .. import io
from ..distributed.config import DQMConfig, config_args
from ..distributed.sources import split_features
from ..process_env import with_env_defaults
from ..wording import seconds
from .bus import LEASE_MS
from .coordinator import failure_paragraph, failure_path
from .lifeline import PARENT_ENV, child_preexec, signals_deferred
from .limits import DEFAULT_READY_TIMEOUT_S, RuntimeLimits, limits_arg
from .roster import job_roster

LOG = logging.getLogger("dqm.runtime")

#: temporary folders of ``dqm run``: dqm-run-<launcher pid>-<random>
WORKDIR_PREFIX = "dqm-run-"


#: measured on this 2-core host: an agent process spends about 1 CPU s starting (imports, zenoh session)
#: and holds about 100 MB before its own features
AGENT_START_CPU_S = 1.0
AGENT_BASE_BYTES = 100 << 20
#: agents per core beyond which ``dqm run`` warns that they only share the cores
AGENTS_PER_CORE = 4
#: agents per core beyond which ``dqm run`` refuses: measured on 2 cores, 40 agent processes ran the
#: default job in 38 s, 64 took minutes, and 150 missed their liveliness leases and were taken for lost
MAX_AGENTS_PER_CORE = 24


def check_scale(m: int, n_images: int, ready_timeout_s: Optional[float] = None) -> float:
    """Guard ``dqm run --agents M`` on this host, before anything starts; returns the ready timeout.

    Refused (InputError): more agent processes than the memory holds, or more than
    :data:`MAX_AGENTS_PER_CORE` per core (they miss their liveliness leases). Warned: more agents than
    images (the extra agents start with no features of their own; they still compute their cells)
    and many agents per core (they share the cores: more agents make the job slower, not faster).
    The default ready timeout grows with the start-up work per core.
    """
    import warnings

    from ..core.memory import available_bytes, format_bytes
    from ..validation import InputError

    cores = os.cpu_count() or 1
    need, avail = (m + 2) * AGENT_BASE_BYTES, available_bytes()
    if need > 0.8 * avail:
        raise InputError(f"--agents {m}: {m} agent processes need about {format_bytes(need)} before any features, "
                         f"more than this host can give ({format_bytes(avail)} available); start fewer agents here "
                         "and the others on other hosts (deploy/README.md)")
    if m > MAX_AGENTS_PER_CORE * cores:
        raise InputError(f"--agents {m} on {cores} cores: beyond {MAX_AGENTS_PER_CORE} agent processes per core they "
                         f"cannot keep their {LEASE_MS / 1000:g} s liveliness leases (150 on 2 cores were taken for "
                         f"lost); run at most {MAX_AGENTS_PER_CORE * cores} agents on this host and the others on "
                         "other hosts (deploy/README.md)")
    if m > n_images:
        warnings.warn(f"--agents {m} for {n_images} images: an agent starts with whole images, so {m - n_images} "
                      "agents start with none of their own (they still compute their cells)", stacklevel=2)
    if m > AGENTS_PER_CORE * cores:
        warnings.warn(f"--agents {m} on {cores} cores: the agent processes only share the cores, so the job is "
                      f"slower than with fewer agents; starting them alone takes about "
                      f"{AGENT_START_CPU_S * m / cores:.0f} s", stacklevel=2)
    if ready_timeout_s is not None:
        return float(ready_timeout_s)
    return max(30.0, 3.0 * AGENT_START_CPU_S * m / cores)


class JobFailure(RuntimeError):
    """A distributed job failed; ``str()`` is the operator's paragraph, ``failure`` the coordinator's
    account (what, agent, phase, advice) when it gave one, ``logs`` the last lines of every log."""

    def __init__(self, paragraph: str, exit_code: Optional[int], failure: Optional[dict] = None, logs: str = ""):
        super().__init__(paragraph)
        self.exit_code = exit_code
        self.failure = failure or {}
        self.logs = logs


def overload_note(exc: JobFailure, exit_codes: List[Optional[int]], m: int) -> JobFailure:
    """A job that failed for "lost" agent processes which were in fact running (each exited by itself,
    none was killed): on one host that means they missed their liveliness lease, the host being
    overloaded. Say so, instead of leaving the operator to look for crashes that did not happen."""
    if "were lost" not in str(exc) or any(code is None or code < 0 for code in exit_codes):
        return exc
    cores = os.cpu_count() or 1
    text = (f"{exc} None of the {m} agent processes crashed (each left by itself when the job was aborted): "
            f"{m} processes on {cores} cores could not answer the {LEASE_MS / 1000:g} s liveliness lease in time "
            "and were taken for lost. Run fewer agents on this host.")
    return JobFailure(text, exc.exit_code, exc.failure, exc.logs)


@contextmanager
def work_folder(keep: Optional[str], prefix: str) -> Iterator[Path]:
    """The folder a script works in: ``keep`` (made if missing, and left in place) or a fresh temporary
    folder named ``prefix...``, removed when the block ends, however it ends."""
    wd = Path(keep) if keep else Path(tempfile.mkdtemp(prefix=prefix))
    wd.mkdir(parents=True, exist_ok=True)
    try:
        yield wd
    finally:
        if not keep:
            shutil.rmtree(wd, ignore_errors=True)


def remove_stale_workdirs(root: Optional[str] = None) -> int:
    """Remove temporary folders left by launchers that no longer run (killed with SIGKILL); returns how many."""
    import shutil

    base = Path(root or tempfile.gettempdir())
    removed = 0
    for d in base.glob(WORKDIR_PREFIX + "*"):
        try:
            pid = int(d.name[len(WORKDIR_PREFIX):].split("-")[0])
        except ValueError:
            continue
        try:
            os.kill(pid, 0)
            continue  # its launcher still runs
        except ProcessLookupError:
            pass
        except PermissionError:
            continue
        shutil.rmtree(d, ignore_errors=True)
        removed += 1
    return removed


def log_tails(workdir: Path, lines: int = 5) -> str:
    return "\n".join(f"--- {f.name}\n" + "".join(f.read_text(errors="replace").splitlines(True)[-lines:])
                     for f in sorted(workdir.glob("*.log")))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_listening(host: str, port: int, deadline_s: float, proc: subprocess.Popen) -> None:
    t0 = time.monotonic()
    while time.monotonic() - t0 < deadline_s:
        if proc.poll() is not None:
            raise RuntimeError(f"the router exited with code {proc.returncode} before listening")
        try:
            with socket.create_connection((host, port), timeout=0.2):
                return
        except OSError:
            time.sleep(0.05)
    raise RuntimeError(f"the router did not listen on {host}:{port} within {seconds(deadline_s)}")


def write_agent_files(descriptors, image_ids, m: int, workdir: Path, features: Optional[io.FeatureSet] = None,
                      image_lists=None) -> List[Path]:
    """One FEATURES file per agent, ``workdir/agent<i>.npz``: ``features`` (or the descriptors and image
    ids) split by image ownership (image k -> agent k mod m) or by ``image_lists``
    (:func:`dqm.distributed.sources.split_features`: keypoints, image names and feature ids kept;
    feature ids are the row numbers unless the set has its own)."""
    fs = features if features is not None else io.FeatureSet(descriptors, np.asarray(image_ids, np.int64))
    return save_agent_files(split_features(fs, m, image_lists), workdir)


def save_agent_files(parts: List[io.FeatureSet], workdir: Path) -> List[Path]:
    """Write ``workdir/agent<i>.npz`` for every agent's FEATURES set; returns the paths."""
    paths = []
    for a, part in enumerate(parts):
        p = Path(workdir) / f"agent{a}.npz"
        io.save_features(p, part)
        paths.append(p)
    return paths


class Processes:
    """Children started by the launcher; :meth:`stop_all` never leaves one behind."""

    def __init__(self):
        self.procs: List[subprocess.Popen] = []

    def start(self, args: List[str], log_path: Path, env=None, prefix: Optional[List[str]] = None,
              pass_fds=(), module: str = "dqm") -> subprocess.Popen:
        """Start ``python -m MODULE ARGS`` (``dqm`` by default; output to ``log_path``); it dies with this
        process."""
        fh = open(log_path, "w")
        env = dict(os.environ if env is None else env)
        with_env_defaults(env)  # OpenBLAS's workers do not spin, numpy asks for no huge pages (dqm.process_env)
        env[PARENT_ENV] = str(os.getpid())
        try:
            with signals_deferred():  # Ctrl-C / SIGTERM arrive once the child is started and known
                p = subprocess.Popen((prefix or []) + [sys.executable, "-m", module] + args, stdout=fh,
                                     stderr=subprocess.STDOUT, env=env, start_new_session=True,
                                     preexec_fn=child_preexec(os.getpid()), pass_fds=tuple(pass_fds))
                self.procs.append(p)
        finally:
            fh.close()
        LOG.debug("started %s (pid %d), output to %s", " ".join(args[:3]), p.pid, log_path)
        return p

    def stop_all(self, grace_s: float = 5.0) -> None:
        for p in self.procs:
            if p.poll() is None:
                try:
                    p.send_signal(signal.SIGTERM)
                except ProcessLookupError:
                    pass
        t0 = time.monotonic()
        for p in self.procs:
            left = max(0.1, grace_s - (time.monotonic() - t0))
            try:
                p.wait(timeout=left)
            except subprocess.TimeoutExpired:
                LOG.warning("pid %d did not end %.1f s after SIGTERM; killed", p.pid, grace_s)
                p.kill()
                p.wait(timeout=5)


def tls_options(certs: Path, name: str) -> List[str]:
    """--tls-* options for the certificate ``name`` (router, agent<i>, coordinator) in ``certs``
    (as made by deploy/make-certs.sh)."""
    certs = Path(certs)
    return ["--tls-ca", str(certs / "ca.pem"), "--tls-cert", str(certs / f"{name}.pem"),
            "--tls-key", str(certs / f"{name}.key")]


def client_tls(certs: Path, name: str) -> dict:
    """zenoh's client TLS settings for the certificate ``name`` in ``certs`` (what ``--tls-*`` options
    of :func:`tls_options` become in a client)."""
    certs = Path(certs)
    return {"root_ca_certificate": str(certs / "ca.pem"), "connect_certificate": str(certs / f"{name}.pem"),
            "connect_private_key": str(certs / f"{name}.key"), "enable_mtls": True}


def secure_router_args(workdir: Path, cfg: DQMConfig, certs: Path) -> List[str]:
    """The router's options for ``cfg``'s job under strict access control: its TLS certificate and the
    job's roster (:func:`dqm.runtime.roster.job_roster`), written to ``workdir``."""
    roster = Path(workdir) / "roster.txt"
    roster.write_text(job_roster(cfg.agents, [cfg.job]).text())
    return [*tls_options(certs, "router"), "--acl", str(roster)]


def make_certs(out: Path, router_names: Sequence[str], clients: Sequence[str]) -> Path:
    """Run deploy/make-certs.sh (openssl): CA, router certificate naming ``router_names``, client certificates."""
    from ..validation import InputError

    script = Path(__file__).resolve().parents[2] / "deploy" / "make-certs.sh"
    if not script.exists():
        raise InputError(f"{script} is missing (it ships with the source checkout, not the wheel)")
    if shutil.which("openssl") is None:
        raise InputError("making certificates needs openssl (not installed)")
    r = subprocess.run(["sh", str(script), str(out), ",".join(router_names), *clients],
                       capture_output=True, text=True, timeout=120)
    if r.returncode != 0:
        raise RuntimeError(f"make-certs.sh failed: {r.stderr.strip()}")
    return Path(out)


#: the limits :func:`start_job` gives its processes by default: tests and demos want failures in seconds
START_LIMITS = RuntimeLimits(job_timeout_s=120.0, phase_timeout_s=60.0)


def coordinator_args(cfg: DQMConfig, connect: str, report: Path, limits: RuntimeLimits,
                     clusters: Optional[str] = None, host_cores: Optional[float] = None,
                     gather_cores: Optional[float] = None) -> List[str]:
    """Command-line options of the coordinator of ``cfg``'s job (``limits`` as one encoded value;
    ``clusters``: its CLUSTERS file, or none; ``host_cores``, ``gather_cores``: --mode auto's cores per agent
    host and at the coordinator's host, or the coordinator's default: its own host's)."""
    args = ["coordinator", "--agents", str(cfg.agents), "--seed", str(cfg.seed), "--connect", connect,
            "--out", str(report), limits_arg(limits), *config_args(cfg)]
    args += ["--clusters", str(clusters)] if clusters else ["--no-clusters"]
    if host_cores is not None:
        args += ["--host-cores", repr(float(host_cores))]
    if gather_cores is not None:
        args += ["--gather-cores", repr(float(gather_cores))]
    return args


def peer_args(files: List[Path], me: int) -> List[str]:
    """--peer-features for every other agent's file: what a process needs to take over a lost agent."""
    out: List[str] = []
    for a, f in enumerate(files):
        if a != me:
            out += ["--peer-features", f"{a}={f}"]
    return out


def job_outcome(rc: Optional[int], report_path: Path, workdir: Path) -> dict:
    """The coordinator's report, or JobFailure with its paragraph (and every log's last lines)."""
    if rc == 0 and report_path.exists():
        return json.loads(report_path.read_text())
    logs = log_tails(workdir)
    fp = failure_path(str(report_path))
    if fp.exists():
        failure = json.loads(fp.read_text())
        raise JobFailure(failure_paragraph(failure), rc, failure, logs)
    if rc is None:
        raise JobFailure("The distributed job failed: the coordinator did not finish in time and was stopped. "
                         f"The processes' logs end with:\n{logs}", rc, logs=logs)
    raise JobFailure(f"The distributed job failed: the coordinator exited with code {rc} without a report. "
                     f"The processes' logs end with:\n{logs}", rc, logs=logs)


class ForkedAgent:
    """Stands for an agent forked from the coordinator's process (:func:`start_job`'s ``agent0_in_coordinator``)
    where a launched agent's :class:`subprocess.Popen` would be: the coordinator reaps it, so its exit code is
    not known here (None), and it ends with the coordinator."""

    pid = None
    returncode = None

    def poll(self) -> None:
        return None

    def wait(self, timeout: Optional[float] = None) -> None:
        return None


@dataclass
class Job:
    """The processes of one started job (the router runs apart)."""

    cfg: DQMConfig
    workdir: Path
    agents: List[subprocess.Popen]
    coordinator: subprocess.Popen
    report_path: Path
    started: float


def start_job(procs: Processes, cfg: DQMConfig, files: Sequence[Path], workdir: Path,
              connect: Callable[[int], str], prefix: Callable[[int], Optional[List[str]]] = lambda a: None,
              client_args: Callable[[int], List[str]] = lambda a: [], env=None,
              limits: Optional[RuntimeLimits] = None, tag: str = "", clusters: Optional[Path] = None,
              threads_per_agent: Optional[int] = 1, pass_fds: Sequence[int] = (), host_cores: Optional[float] = None,
              gather_cores: Optional[float] = None, agent0_in_coordinator: bool = False) -> Job:
    """Start the coordinator and then the agents of one job (the router is already running): the one start
    path of ``dqm run`` (:func:`run_job`), the multi-host demo and the tests.

    ``connect(a)``, ``prefix(a)`` and ``client_args(a)`` give the endpoint, the command prefix (e.g.
    ``ip netns exec NS``) and extra options (TLS, test hooks) of agent ``a``; ``a = -1`` is the
    coordinator. ``clusters``: the CLUSTERS file the coordinator writes (none by default).
    ``limits``: every process's runtime limits, handed to each as one value (default: :data:`START_LIMITS`,
    short timeouts for tests and demos). ``threads_per_agent``:
    worker threads of each agent unless ``env`` says otherwise (None: all cores); the coordinator
    keeps ``env``'s (it computes only in a gather job, once the agents have sent everything).
    ``host_cores``, ``gather_cores``: the coordinator's --host-cores and --gather-cores (--mode auto).
    ``agent0_in_coordinator``: agent 0 runs on the coordinator's host, forked from the coordinator's process
    (``dqm coordinator --also-agent``: one interpreter to start there, not two); it then has the coordinator's
    command prefix, endpoint and environment (refused where its own differ), and ``Job.agents[0]`` is a
    :class:`ForkedAgent`.
    """
    limits = START_LIMITS if limits is None else limits
    started = time.monotonic()  # the job's clock starts before its first process, as a gathering's does
    coordinator_env = dict(os.environ if env is None else env)
    env = dict(coordinator_env)
    if threads_per_agent is not None:
        for var in ("DQM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
            env.setdefault(var, str(threads_per_agent))
    def agent_args(a: int) -> List[str]:
        return ["agent", "--id", str(a), "--agents", str(cfg.agents), "--connect", connect(a), limits_arg(limits),
                *config_args(cfg), *client_args(a), *peer_args(list(files), a), str(files[a])]

    forked: List[str] = []
    if agent0_in_coordinator:
        if (prefix(0), connect(0)) != (prefix(-1), connect(-1)) or env != coordinator_env:
            raise ValueError("agent 0 runs in the coordinator's process only with its command prefix, endpoint and "
                             "environment")
        forked = ["--also-agent", shlex.join(agent_args(0)[1:]), "--also-agent-log", str(workdir / f"{tag}agent0.log")]
    report_path = workdir / f"{tag}report.json"
    # the work folder is the launcher's: a report of an earlier job there (the same mode at another link rate of
    # scripts/bench_hosts.py) is not this job's, and the coordinator refuses to overwrite it; nor is an earlier
    # job's failure (a coordinator that dies without one would otherwise be reported with that job's reason)
    report_path.unlink(missing_ok=True)
    failure_path(str(report_path)).unlink(missing_ok=True)
    # the coordinator first: its host's start-up (and agent 0's, forked from it) is the longest path to the first
    # message, and each start here takes the launcher 15-20 ms on emulated hosts (0.13 s at M = 8 before it)
    coord = procs.start([*coordinator_args(cfg, connect(-1), report_path, limits,
                                           None if clusters is None else str(clusters), host_cores, gather_cores),
                         *client_args(-1), *forked],
                        workdir / f"{tag}coordinator.log", coordinator_env, prefix=prefix(-1), pass_fds=pass_fds)
    agents = [ForkedAgent() if a == 0 and forked else
              procs.start(agent_args(a), workdir / f"{tag}agent{a}.log", env, prefix=prefix(a))
              for a in range(cfg.agents)]
    return Job(cfg, workdir, agents, coord, report_path, started)


def finish_job(job: Job, timeout_s: float = 120.0) -> dict:
    """Wait for the coordinator's report (``timeout_s`` from the start) and for the agents to exit;
    :class:`JobFailure` with the operator's paragraph and every log's last lines on failure."""
    try:
        rc = job.coordinator.wait(timeout=max(1.0, timeout_s - (time.monotonic() - job.started)))
    except subprocess.TimeoutExpired:
        rc = None
    coordinator_s = time.monotonic() - job.started
    deadline = time.monotonic() + 10.0  # for all of them together: hundreds of agents, one wait
    for p in job.agents:
        try:
            p.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            pass
    try:
        report = job_outcome(rc, job.report_path, job.workdir)
    except JobFailure as exc:
        raise overload_note(exc, [p.returncode for p in job.agents], job.cfg.agents) from None
    report["agent_exit_codes"] = [p.returncode for p in job.agents]
    report["workdir"] = str(job.workdir)
    report["wall_s"] = time.monotonic() - job.started
    report["coordinator_s"] = coordinator_s  # its result written and the process gone; agents may still be ending
    LOG.info("job %s finished in %.2f s (coordinator exit %s, agents %s)", job.cfg.job, report["wall_s"], rc,
             report["agent_exit_codes"])
    return report


def _local_host_cores(agents: int) -> float:
    """--mode auto on this one host: every agent process gets its share of this host's cores (a gather, once the
    other agents have sent their features, has all of them: the coordinator's --gather-cores, this host's)."""
    from .measure import host_cores

    return host_cores() / max(1, agents)


def run_job(descriptors, image_ids, cfg: DQMConfig, limits: Optional[RuntimeLimits] = None,
            workdir: Optional[str] = None, env=None, keep_logs: bool = False, on_started=None,
            agent_args: Optional[List[str]] = None, progress: bool = False,
            features: Optional[io.FeatureSet] = None, clusters: Optional[str] = None, secure: bool = False) -> dict:
    """Run a job as separate processes on this host; returns the coordinator's report.

    The agents start with ``features`` (a FEATURES set: its keypoints and image names reach the
    CLUSTERS file), or with the descriptors and image ids. ``clusters``: where the coordinator
    writes the CLUSTERS file (none: no catalogs travel). Raises :class:`JobFailure` (a
    RuntimeError) whose text is the operator's paragraph. ``progress``: show the live job table
    on this process's standard error if it is a terminal. ``secure``: mutual TLS with throwaway
    certificates (one per process, made in the work folder) and a router that enforces the job's
    roster (:func:`dqm.runtime.roster.job_roster`): every process may use only its own keys.
    ``limits``: the runtime limits of every process (None: the defaults, a 30-s ready timeout).
    """
    limits = (limits or RuntimeLimits()).validated()
    if limits.ready_timeout_s is None:
        limits = limits.but(ready_timeout_s=DEFAULT_READY_TIMEOUT_S)
    cfg = cfg.validated(len(features) if features is not None else len(descriptors), runtime=True)
    remove_stale_workdirs()
    procs = Processes()
    tty = None
    tmp = tempfile.mkdtemp(prefix=f"{WORKDIR_PREFIX}{os.getpid()}-") if workdir is None else workdir
    try:  # from the work folder's making: a stop at any point removes it
        wd = Path(tmp)
        wd.mkdir(parents=True, exist_ok=True)
        files = write_agent_files(descriptors, image_ids, cfg.agents, wd, features)
        port = free_port()
        endpoint = f"{'tls' if secure else 'tcp'}/127.0.0.1:{port}"
        router_extra: List[str] = []
        identity: Callable[[int], List[str]] = lambda a: []  # noqa: E731
        if secure:
            certs = make_certs(wd / "certs", ["127.0.0.1"], ["coordinator"] + [f"agent{a}" for a in range(cfg.agents)])
            router_extra = secure_router_args(wd, cfg, certs)
            identity = lambda a: tls_options(certs, "coordinator" if a < 0 else f"agent{a}")  # noqa: E731
        env = dict(os.environ if env is None else env)
        # balanced (and auto, which may pick it): all agents compute at once: share this host's cores instead of
        # oversubscribing them. lean / paper: every agent may use all cores, the hand-down cascade runs one agent
        # at a time (measured: M = 8 on graf 5.9 s with one thread per agent, 4.8 s with two)
        share = max(1, (os.cpu_count() or 1) // cfg.agents) if cfg.mode in ("balanced", "auto") else None
        tty = os.dup(2) if progress and sys.stderr.isatty() else None
        router = procs.start(["router", "--listen", endpoint, *router_extra], wd / "router.log", env)
        wait_listening("127.0.0.1", port, 10.0, router)
        coordinator_extra = ["--tcp-port", str(port)] + (["--progress-fd", str(tty)] if tty is not None else [])
        job = start_job(procs, cfg, files, wd, connect=lambda a: endpoint,
                        client_args=lambda a: identity(a) + (coordinator_extra if a < 0 else list(agent_args or [])),
                        env=env, limits=limits, threads_per_agent=share,
                        clusters=None if clusters is None else Path(clusters).resolve(),
                        pass_fds=[tty] if tty is not None else [],
                        host_cores=_local_host_cores(cfg.agents) if cfg.mode == "auto" else None)
        if on_started is not None:
            on_started({"router": router, "agents": job.agents, "coordinator": job.coordinator, "workdir": wd,
                        "port": port})
        report = finish_job(job, limits.job_timeout_s + 15)
        del report["wall_s"], report["coordinator_s"]
        return report
    finally:
        if tty is not None:
            os.close(tty)
        procs.stop_all()
        if not keep_logs and workdir is None:
            shutil.rmtree(tmp, ignore_errors=True)
