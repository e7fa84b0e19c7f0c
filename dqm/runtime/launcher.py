"""``dqm run``: router, M agents and the coordinator as separate processes on this host.

The launcher writes each agent's own features (the images it owns) to a file,
starts the processes, waits with deadlines, and always cleans up: on success,
on failure and on Ctrl-C / SIGTERM no child is left behind.
"""
from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import List, Optional

import numpy as np

from ..distributed import protocol
from ..distributed.config import DQMConfig
from ..distributed.simulator import image_owners


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
    raise RuntimeError(f"the router did not listen on {host}:{port} within {deadline_s:.0f} s")


def write_agent_files(descriptors, image_ids, m: int, workdir: Path) -> List[Path]:
    """Split features by image ownership (image k -> agent k mod m); ids are the row numbers."""
    desc = protocol.wire_descriptors(descriptors)
    ids = np.asarray(image_ids, np.int64)
    owners = image_owners(ids, m)
    paths = []
    for a in range(m):
        sel = np.flatnonzero(owners == a)
        p = workdir / f"agent{a}.npz"
        np.savez(p, descriptors=desc[sel], image_ids=ids[sel], feature_ids=sel.astype(np.int64))
        paths.append(p)
    return paths


def algorithm_args(cfg: DQMConfig) -> List[str]:
    """Command-line options that give an agent process the same configuration."""
    args = ["--mode", cfg.mode, "--partition", cfg.partition, "--rho", repr(cfg.rho), "--kernel", cfg.kernel,
            "--halo", repr(cfg.halo), "--samples", str(cfg.samples_per_agent), "--seed-norm", repr(cfg.seed_norm),
            "--ghost-rule", cfg.ghost_rule, "--sketch-dims", str(cfg.sketch_dims),
            "--balance-rounds", str(cfg.balance_rounds), "--job", cfg.job]
    if cfg.cell_weights is not None:
        args.append("--cell-weights" if cfg.cell_weights else "--no-cell-weights")
    return args


class Processes:
    """Children started by the launcher; :meth:`stop_all` never leaves one behind."""

    def __init__(self):
        self.procs: List[subprocess.Popen] = []

    def start(self, args: List[str], log_path: Path, env=None, prefix: Optional[List[str]] = None) -> subprocess.Popen:
        fh = open(log_path, "w")
        p = subprocess.Popen((prefix or []) + [sys.executable, "-m", "dqm"] + args, stdout=fh, stderr=subprocess.STDOUT,
                             env=env, start_new_session=True)
        fh.close()
        self.procs.append(p)
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
                p.kill()
                p.wait(timeout=5)


def run_job(descriptors, image_ids, cfg: DQMConfig, workdir: Optional[str] = None, timeout_s: float = 600.0,
            env=None, keep_logs: bool = False, on_started=None, agent_args: Optional[List[str]] = None,
            ready_timeout_s: float = 30.0) -> dict:
    """Run a job as separate processes on this host; returns the coordinator's report.

    Raises RuntimeError with the coordinator's / agents' last log lines on failure.
    """
    cfg = cfg.validated(len(descriptors))
    tmp = tempfile.mkdtemp(prefix="dqm-run-") if workdir is None else workdir
    wd = Path(tmp)
    wd.mkdir(parents=True, exist_ok=True)
    files = write_agent_files(descriptors, image_ids, cfg.agents, wd)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    procs = Processes()
    env = dict(os.environ if env is None else env)
    if cfg.mode == "balanced":
        # all agents compute at once: share this host's cores instead of oversubscribing them
        share = str(max(1, (os.cpu_count() or 1) // cfg.agents))
        for var in ("DQM_THREADS", "OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
            env.setdefault(var, share)
    # lean / paper: every agent may use all cores, the hand-down cascade runs one agent at a
    # time (measured: M = 8 on graf 5.9 s with one thread per agent, 4.8 s with two)
    try:
        router = procs.start(["router", "--listen", endpoint], wd / "router.log", env)
        wait_listening("127.0.0.1", port, 10.0, router)
        agents = [procs.start(["agent", "--id", str(a), "--agents", str(cfg.agents), "--connect", endpoint,
                               *algorithm_args(cfg), *(agent_args or []), str(files[a])],
                              wd / f"agent{a}.log", env)
                  for a in range(cfg.agents)]
        report_path = wd / "report.json"
        coord = procs.start(["coordinator", "--agents", str(cfg.agents), "--seed", str(cfg.seed),
                             "--partition", cfg.partition, "--connect", endpoint, "--job", cfg.job,
                             "--out", str(report_path), "--tcp-port", str(port),
                             "--job-timeout", str(timeout_s), "--ready-timeout", str(ready_timeout_s)],
                            wd / "coordinator.log", env)
        if on_started is not None:
            on_started({"router": router, "agents": agents, "coordinator": coord, "workdir": wd, "port": port})
        try:
            rc = coord.wait(timeout=timeout_s + 15)
        except subprocess.TimeoutExpired:
            rc = None
        for p in agents:
            try:
                p.wait(timeout=10)
            except subprocess.TimeoutExpired:
                pass
        if rc != 0 or not report_path.exists():
            logs = "\n".join(f"--- {f.name}\n" + "".join(f.read_text().splitlines(True)[-5:])
                             for f in sorted(wd.glob("*.log")))
            raise RuntimeError(f"distributed job failed (coordinator exit code {rc}); last log lines:\n{logs}")
        report = json.loads(report_path.read_text())
        report["agent_exit_codes"] = [p.returncode for p in agents]
        report["workdir"] = str(wd)
        return report
    finally:
        procs.stop_all()
        if not keep_logs and workdir is None:
            import shutil

            shutil.rmtree(tmp, ignore_errors=True)
