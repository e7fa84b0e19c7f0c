"""A Distributed QuickMatch agent process: the zenoh shell around the one process host.

It starts with the features of its own images, declares its inbox and its
liveliness token, and waits for the coordinator's ``start``. The control plane
(start, go, abort, finish; a driver per hosted agent in each epoch) is
:class:`dqm.distributed.hosting.ProcessHost`, which the in-process simulator
runs too; here it is fed from the bus. This module holds the re-reading of a
lost agent's files, the link probes' answers, the bounded waiting and the exit
codes. All waiting is bounded; a vanished coordinator or an abort message ends
the process with a clear error.
"""
from __future__ import annotations

import logging
import math
import os
import time
from typing import Callable, Dict, List, Optional

from .. import signals
from ..distributed import keys, messages, sources
from ..distributed.config import DQMConfig
from ..distributed.driver import JobAborted
from ..distributed.hosting import ProcessHost, Refused
from ..distributed.ledger import COORDINATOR
from ..logging_config import tag_lines
from .bus import Bus, check_job_free, open_client
from .limits import RuntimeLimits
from .measure import host_cores, probe_answer

log = logging.getLogger("dqm.runtime")

__all__ = ["AgentHost", "CoordinatorLost", "JobAborted", "Refused", "RouterLost",
           "fault_pause_from_env", "main_agent", "parse_peer_features"]


def fault_pause_from_env() -> Optional[Callable[[int, str], None]]:
    """The test hook, read once at start-up: with DQM_FAULT_PAUSE="<agent>:<state>" the agent stops when
    it enters that state, writing its pid to the file named by DQM_FAULT_MARKER, so that a test can kill
    it there. It goes on after DQM_FAULT_SECONDS (default 60), or as soon as the test deletes the marker
    file. Returns the ``on_state`` callback for :class:`~dqm.distributed.driver.AgentDriver`, or None."""
    spec = os.environ.get("DQM_FAULT_PAUSE")
    if not spec:
        return None
    marker = os.environ.get("DQM_FAULT_MARKER")
    seconds = float(os.environ.get("DQM_FAULT_SECONDS", "60"))

    def pause(agent: int, state: str) -> None:
        if spec != f"{agent}:{state}":
            return
        if marker:  # written whole, then renamed: a test that sees the file reads the pid, never an empty file
            part = f"{marker}.{os.getpid()}.part"
            with open(part, "w") as fh:
                fh.write(f"{os.getpid()}\n")
            os.replace(part, marker)
        end = time.monotonic() + seconds
        while time.monotonic() < end and (not marker or os.path.exists(marker)):
            time.sleep(0.05)

    return pause


class CoordinatorLost(RuntimeError):
    """The coordinator's liveliness token vanished."""


class RouterLost(RuntimeError):
    """The session's router is gone: nothing can arrive or leave any more."""


def gather_threads() -> int:
    """Threads of this process's match when its agent gathers (gather mode): every core it may use
    (:func:`dqm.runtime.measure.host_cores`, a partial core of a quota counted whole), at most 8.
    ``DQM_THREADS`` (a share of the host's cores, when agents compute side by side) does not apply: in a gather
    job the other agents only send."""
    return max(1, min(8, math.ceil(host_cores())))


class AgentHost:
    """One agent process: the zenoh shell around :class:`~dqm.distributed.hosting.ProcessHost` (its own
    agent ``home`` and any lost agents' cells the coordinator gave it, whose features it re-reads from
    ``paths``). It receives from the bus, answers the coordinator's link probes, resends what is overdue
    and bounds every wait: a vanished coordinator or router, or a phase that takes too long, ends it.
    ``on_state(agent, state)`` is handed to the driver of this process's own agent in the first epoch
    (a test's fault injection)."""

    def __init__(self, home: int, cfg: DQMConfig, bus: Bus, paths: Dict[int, List[str]],
                 phase_timeout_s: float = 120.0, own: Optional[sources.AgentFeatures] = None,
                 on_state: Optional[Callable[[int, str], None]] = None):
        self.home = home
        self.bus = bus
        self.paths = paths
        self.phase_timeout_s = phase_timeout_s
        own = own if own is not None else sources.load_agent_features(paths[home], home)
        self.host = ProcessHost(home, cfg, bus, own, self._load, phase_timeout_s=phase_timeout_s,
                                on_state=on_state, gather_threads=gather_threads())
        self.t0 = time.monotonic()
        self._router_checked = self.t0

    @property
    def phase(self) -> str:
        return self.host.phase

    def _load(self, agent: int) -> sources.AgentFeatures:
        if agent not in self.paths:
            raise Refused(f"cannot take over agent {agent}: this process has no path to its FEATURES files "
                          f"(start agents with --peer-features {agent}=FILE)")
        try:
            return sources.load_agent_features(self.paths[agent], agent)
        except (OSError, ValueError) as exc:
            raise Refused(f"cannot take over agent {agent}: {exc}") from None

    def control(self, msg: dict) -> None:
        if not self.host.control(msg) and msg["kind"] == "probe":
            # --mode auto: the coordinator times its link to this process; answer at once
            self.bus.send(self.home, COORDINATOR, "probe", messages.encode(
                "probe", self.host.cfg.job, self.home, epoch=msg["epoch"], token=msg["token"], reply=0,
                data=probe_answer(msg["reply"], msg["_t"])))

    def run(self) -> None:
        host = self.host
        while not host.done:
            item = self.bus.receive(timeout=0.05)
            if item is not None:
                dst, msg = item
                if msg["src"] == COORDINATOR:
                    self.control(msg)
                else:
                    host.deliver(dst, msg)
            host.settle()
            self.bus.resend_due()
            self._check_router()
            if host.epoch >= 0 and self.bus.coordinator_alive() is False:
                raise CoordinatorLost(f"the coordinator vanished (its liveliness token was lost) while this agent was "
                                      f"in phase {self.phase}")
            host.check_timeouts()
            if host.epoch < 0 and time.monotonic() - self.t0 > self.phase_timeout_s:
                raise TimeoutError(f"no start from a coordinator within {self.phase_timeout_s:.0f} s")

    def _check_router(self) -> None:
        """Every 0.25 s: the router must still be there (else the agent would wait out its phase timeout and
        blame the coordinator)."""
        now = time.monotonic()
        if now - self._router_checked < 0.25:
            return
        self._router_checked = now
        if not self.bus.router_connected():
            where = "waiting for its coordinator" if self.host.epoch < 0 else f"in phase {self.phase}"
            raise RouterLost(f"the zenoh router is gone (the session to it closed) while this agent was {where}")


def parse_peer_features(specs: Optional[List[str]]) -> Dict[int, List[str]]:
    """``["2=/data/a2.npz,/data/a2b.npz", ...]`` -> {2: [...]}: where a lost agent's images can be re-read."""
    return dict(sources.agent_files(spec, "--peer-features") for spec in specs or [])


#: exit codes of ``dqm agent`` (docs/runtime.md)
EXIT_OK, EXIT_FAILED, EXIT_REFUSED, EXIT_COORDINATOR_LOST = 0, 3, 4, 5  # 130 / 143: dqm.signals


def main_agent(me: int, cfg: DQMConfig, endpoint: str, paths, tls: Optional[dict] = None,
               limits: Optional[RuntimeLimits] = None, peers: Optional[Dict[int, List[str]]] = None) -> int:
    """Entry point of ``dqm agent``: returns the process exit code (``limits``: the connect and phase timeouts,
    the lease, the largest message; None: the defaults)."""
    from .lifeline import watch_parent

    signals.install_sigterm(force=True)
    watch_parent()
    keys.check_job(cfg.job)
    files = dict(peers or {})
    files[me] = list(paths)
    tag_lines(f"agent {me}")
    own = sources.load_agent_features(paths, me)
    limits = limits or RuntimeLimits()
    session = open_client(endpoint, tls, deadline_s=limits.connect_timeout_s, lease_ms=limits.lease_ms)
    check_job_free(session, keys.alive_agent(cfg.job, me), f"agent {me}", cfg.job, endpoint)
    host = None
    bus = None
    try:
        bus = Bus(session, cfg.job, me, cfg.agents, max_bytes=limits.max_message_bytes)
        bus.check_access(endpoint, tls, f"agent process {me} of job {cfg.job!r}")
        host = AgentHost(me, cfg, bus, files, phase_timeout_s=limits.phase_timeout_s, own=own,
                         on_state=fault_pause_from_env())
        log.info("connected to the router at %s; waiting for the coordinator of job %r", endpoint, cfg.job)
        host.run()
        return EXIT_OK
    except Refused as exc:
        log.error("refused: %s", exc)
        time.sleep(0.3)  # let the refusal reach the coordinator before the token goes
        return EXIT_REFUSED
    except (CoordinatorLost, RouterLost) as exc:
        where = f" (router: {endpoint})" if isinstance(exc, RouterLost) else ""
        log.error("error: %s%s. This agent leaves; to run the job again, start %sthe coordinator and every agent "
                  "again with the same options (a job restarts from the beginning).", exc, where,
                  "the router, " if isinstance(exc, RouterLost) else "")
        return EXIT_COORDINATOR_LOST
    except (JobAborted, TimeoutError) as exc:
        log.error("error: %s", exc)
        return EXIT_FAILED
    except KeyboardInterrupt as exc:  # Ctrl-C, and SIGTERM as signals.Terminated
        log.warning("%s, leaving", signals.word(exc))
        return signals.exit_code(exc)
    finally:
        if bus is not None:
            bus.close()
        else:
            session.close()
