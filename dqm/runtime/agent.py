"""A Distributed QuickMatch agent: one OS process, message-driven.

It starts with the features of its own images, declares its inbox and its
liveliness token, waits for the coordinator's seed integer, and then runs the
protocol of dqm.distributed.protocol with the same code the simulator runs:
the set-up of dqm.distributed.seeding, then the balanced rounds
(dqm.distributed.balanced.BalancedCore) or the lean / paper cascade
(dqm.distributed.cascade.CascadeCore). All waiting is bounded; a vanished
coordinator or an abort message ends the process with a clear error.
"""
from __future__ import annotations

import os
import signal
import sys
import time
from collections import defaultdict, deque
from typing import Deque, Dict, List, Optional, Tuple

import numpy as np

from ..distributed import cascade, messages, partition, protocol, seeding, sources
from ..distributed.balanced import ROUNDS, BalancedCore
from ..distributed.config import DQMConfig, differing_param, params_hash
from ..distributed.shard import Shard
from ..distributed import keys
from .bus import Bus, check_job_free, open_client

LEADER = seeding.LEADER


class JobAborted(RuntimeError):
    pass


def _fault_hook(me: int, state: str) -> None:
    """Test hook: with DQM_FAULT_PAUSE="<agent>:<state>" the agent stops when it enters that state,
    writing its pid to the file named by DQM_FAULT_MARKER, so that a test can kill it there. It goes on
    after DQM_FAULT_SECONDS (default 60), or as soon as the test deletes the marker file."""
    spec = os.environ.get("DQM_FAULT_PAUSE")
    if not spec or spec != f"{me}:{state}":
        return
    marker = os.environ.get("DQM_FAULT_MARKER")
    if marker:
        with open(marker, "w") as fh:
            fh.write(f"{os.getpid()}\n")
    end = time.monotonic() + float(os.environ.get("DQM_FAULT_SECONDS", "60"))
    while time.monotonic() < end and (not marker or os.path.exists(marker)):
        time.sleep(0.05)


class Terminated(BaseException):
    """SIGTERM received: leave the loop, close the session."""


def _on_sigterm(signum, frame):  # pragma: no cover - exercised by process tests
    raise Terminated()


#: message kinds that arrive once per sender and step (kept in arrival order per sender)
_SINGLE = ("sample", "seeds", "fill", "counts", "weights", "minima")


class AgentProcess:
    """The message loop around one agent's cores. States (for logs and fault tests):
    ``wait_start``, ``wait_seeds``, ``wait_fill``, ``wait_weights``, ``wait_routed``, then
    ``wait_<round>`` for every balanced round (or ``wait_minima``, ``wait_handdown`` in the
    cascade), ``wait_acks``, ``wait_finish``."""

    def __init__(self, me: int, cfg: DQMConfig, bus: Bus, ids: np.ndarray, image_ids: np.ndarray,
                 descriptors: np.ndarray, phase_timeout_s: float = 120.0, log=None, epoch: int = 0,
                 home: Optional[int] = None, catalog: Optional[Dict[str, np.ndarray]] = None):
        self.me = me
        self.catalog = catalog  # sent to the coordinator with the result when the job asked for it
        self.epoch = epoch
        self.home = me if home is None else home
        self.cfg = cfg
        self.m = cfg.agents
        self.bus = bus
        self.desc = protocol.wire_descriptors(descriptors)
        self.dim = self.desc.shape[1]
        self.ids = np.asarray(ids, np.int64)
        self.image_ids = np.asarray(image_ids, np.int64)
        self.state = "wait_start"
        self.phase_timeout_s = phase_timeout_s
        self.phase_started = time.monotonic()
        self.log = log or (lambda text: print(f"[agent {me}] {text}", file=sys.stderr, flush=True))
        self.seed: Optional[int] = None
        self.core = None
        self.source: Optional[seeding.SourceSide] = None
        self.leader: Optional[seeding.Leader] = None
        self.singles: Dict[Tuple[str, int], Deque[dict]] = defaultdict(deque)
        self.parts: Dict[Tuple[str, int], Dict[int, dict]] = defaultdict(dict)
        self.chunks: Dict[Tuple[int, str], List[dict]] = defaultdict(list)
        self.ends: Dict[Tuple[int, str], dict] = {}
        self.times: Dict[str, float] = {}
        self.cpu0 = time.process_time()
        self.stats: Dict[str, float] = {}
        self._hook("wait_start")

    def _hook(self, state: str) -> None:
        if self.me == self.home and self.epoch == 0:  # faults are injected into the first run only
            _fault_hook(self.me, state)

    # ------------------------------------------------------------------ messages
    def begin(self, seed: int) -> None:
        """The coordinator said go: run the protocol with this seed integer."""
        self.seed = partition.check_seed(seed)

    def handle(self, msg: dict) -> None:
        kind, src = msg["kind"], msg["src"]
        if kind in _SINGLE and src >= 0:
            self.singles[(kind, src)].append(msg)
        elif "parts" in msg and src >= 0:
            self.parts[(kind, src)][msg["part"]] = msg
        elif kind == "features" and src >= 0:
            self.chunks[(src, msg["phase"])].append(msg)
        elif kind == "phase_end" and src >= 0 and msg["dst"] == self.me:
            self.ends[(src, msg["phase"])] = msg

    def _have(self, kind: str, senders) -> bool:
        return all(self.singles[(kind, a)] for a in senders)

    def _take(self, kind: str, senders) -> Dict[int, dict]:
        return {a: self.singles[(kind, a)].popleft() for a in senders}

    def _have_parts(self, kind: str, senders) -> bool:
        for a in senders:
            got = self.parts.get((kind, a))
            if not got or len(got) != next(iter(got.values()))["parts"]:
                return False
        return True

    def _take_parts(self, kind: str, senders) -> Dict[int, dict]:
        """The merged messages of a round; one whose parts do not fit together is refused and counted
        (the core counts the missing sender as a failure)."""
        out = {}
        for a in senders:
            try:
                out[a] = protocol.merge_parts(kind, list(self.parts.pop((kind, a)).values()))
            except messages.MessageError as exc:
                self.bus.meter.reject(str(exc))
        return out

    def _send_numbered(self, dst: int, kind: str, count: int, build) -> int:
        """Send ``count`` messages numbered from the link's next sequence number (kept until acknowledged)."""
        seq0 = self.bus.next_seq(self.me, dst, count)
        msgs = build(seq0)
        for j, msg in enumerate(msgs):
            self.bus.send(self.me, dst, kind, msg, seq=seq0 + j)
        return len(msgs)

    def _send_parts(self, kind: str, dst: int, payload: dict) -> None:
        self._send_numbered(dst, kind, protocol.part_count(kind, payload), lambda seq0: protocol.data_messages(
            kind, self.cfg.job, self.me, payload, seq0=seq0, epoch=self.epoch))

    def _send_single(self, kind: str, dst: int, **fields) -> None:
        self.bus.send_single(self.me, dst, kind, **fields)

    def _phase_end(self, dst: int, phase: str, n_messages: int, n_features: int, moved=None) -> None:
        seq = self.bus.next_seq(self.me, dst)
        self.bus.send(self.me, dst, "phase_end", protocol.phase_end(self.cfg.job, self.me, dst, phase, n_messages,
                                                                    n_features, moved, seq=seq, epoch=self.epoch))

    def _complete(self, src: int, phase: str) -> bool:
        end = self.ends.get((src, phase))
        return end is not None and len(self.chunks[(src, phase)]) == end["messages"]

    def _shard_from(self, src: int, phase: str) -> Tuple[Shard, np.ndarray]:
        ch = sorted(self.chunks[(src, phase)], key=lambda c: c["seq"])
        if not ch:
            return Shard.empty(self.dim, self.desc.dtype), np.zeros(0, np.int64)
        ids = np.concatenate([c["ids"] for c in ch])
        desc = np.concatenate([c["descriptors"] for c in ch])
        if desc.dtype != self.desc.dtype:
            raise JobAborted(f"agent {src} sent {desc.dtype} descriptors, this agent holds {self.desc.dtype}")
        # routed features are in this cell by construction; handed-down ones keep their own cell
        cells = np.full(len(ids), self.me, np.int64) if phase == "route" else \
            partition.route(desc.astype(np.float64), self.source.seeds, self.source.weights)
        shard = Shard(ids, np.concatenate([c["image_ids"] for c in ch]), desc,
                      np.concatenate([c["sigma"] for c in ch]), cells)
        return shard, np.concatenate([c["unit"] if len(c["unit"]) else np.full(len(c["ids"]), -1) for c in ch])

    def _send_features(self, dst: int, phase: str, shard: Shard, units: Optional[np.ndarray]) -> int:
        return self._send_numbered(dst, "features", protocol.chunk_count(len(shard)), lambda seq0: (
            protocol.feature_messages(self.cfg.job, self.me, phase, shard.ids, shard.image_ids, shard.descriptors,
                                      shard.sigma, units, seq0=seq0, epoch=self.epoch)))

    def _enter(self, state: str) -> None:
        now = time.monotonic()
        self.times[f"time_{self.state}"] = self.times.get(f"time_{self.state}", 0.0) + now - self.phase_started
        self.state = state
        self.phase_started = now
        sent = self.bus.meter.snapshot()[0]
        self.bus.send(self.me, -1, "progress", messages.encode(
            "progress", self.cfg.job, self.me, epoch=self.epoch, state=state,
            features=int(len(self.ids) if self.core is None else self.core_features()),
            bytes=int(sum(b for (src, _, _), (b, _) in sent.items() if src == self.me))))
        self._hook(state)

    def _others(self) -> List[int]:
        return [b for b in range(self.m) if b != self.me]

    # ------------------------------------------------------------------ set-up (dqm.distributed.seeding)
    def _after_seeds(self) -> None:
        src = self.source
        if src.need_fill:
            if self.me != LEADER:
                self._send_parts("sigmas", LEADER, src.sigmas_payload())
            self._enter("wait_fill")
        else:
            self._after_fill()

    def _after_fill(self) -> None:
        if self.source.final:
            self._route()
            return
        self.own["counts"] = self.source.counts_payload()
        if self.me != LEADER:
            self._send_single("counts", LEADER, **self.own["counts"])
        self._enter("wait_weights")

    def _route(self) -> None:
        parts = self.source.route()
        self.own_part = parts[self.me]
        for b in self._others():
            k = self._send_features(b, "route", parts[b], None)
            self._phase_end(b, "route", k, len(parts[b]))
        self._enter("wait_routed")

    def _leader_round(self, collect: str, reply: str, own: dict, compute, apply, then, parts: bool = False) -> bool:
        """One set-up round: agent 0 gathers ``collect`` from every other agent (its own is ``own``),
        computes the reply, broadcasts it as ``reply`` and applies it; the others wait for it."""
        if self.me == LEADER:
            others = self._others()
            if not (self._have_parts(collect, others) if parts else self._have(collect, others)):
                return False
            got = self._take_parts(collect, others) if parts else self._take(collect, others)
            got[LEADER] = own
            payload = compute(got)
            for b in others:
                self._send_single(reply, b, **payload)
        else:
            if not self._have(reply, [LEADER]):
                return False
            payload = self._take(reply, [LEADER])[LEADER]
        apply(payload)
        then()
        return True

    def _setup_step(self) -> bool:
        s = self.state
        if s == "wait_start" and self.seed is not None:
            self.cfg = self.cfg.but(seed=self.seed)  # the one integer comes from the coordinator
            if self.me == LEADER:
                self.leader = seeding.Leader(self.cfg, self.dim)
            self.source = seeding.SourceSide(self.me, self.cfg, self.ids, self.image_ids, self.desc)
            self.own = {"sample": self.source.sample_payload()}
            if self.me != LEADER:
                self._send_single("sample", LEADER, **self.own["sample"])
            self._enter("wait_seeds")
            return True
        leader, source = self.leader, self.source
        if s == "wait_seeds":
            return self._leader_round("sample", "seeds", self.own["sample"], lambda got: leader.seeds_payload(got),
                                      source.on_seeds, self._after_seeds)
        if s == "wait_fill":
            return self._leader_round("sigmas", "fill", source.sigmas_payload(),
                                      lambda got: {"value": leader.fill_value(got)},
                                      lambda p: source.on_fill(p["value"]), self._after_fill, parts=True)
        if s == "wait_weights":
            return self._leader_round("counts", "weights", self.own["counts"], lambda got: leader.weights_payload(got),
                                      source.on_weights, self._after_fill)
        return False

    # ------------------------------------------------------------------ after routing
    def _routed(self) -> None:
        parts = [self.own_part] + [self._shard_from(b, "route")[0] for b in self._others()]
        seeds, weights = self.source.seeds, self.source.weights
        if self.cfg.mode == "balanced":
            self.core = BalancedCore(self.me, self.cfg, self.source.sketch_space())
            self.core.set_shard(parts, seeds, weights)
            self._balanced_step({})
            return
        self.core = cascade.CascadeCore(self.me, self.cfg)
        self.core.set_shard(parts, seeds, weights)
        row = self.core.local_step()
        self.minima_rows = {self.me: row}
        for b in self._others():
            self._send_single("minima", b, values=row)
        self._enter("wait_minima")

    def _balanced_step(self, inputs: Dict[int, dict]) -> None:
        r = self.core.round
        if r == len(ROUNDS):
            ids, labels = self.core.finish(inputs)
            self._result(ids, labels, self.core.stats)
            return
        name = ROUNDS[r]
        for dst, payload in self.core.step(inputs).items():
            self._send_parts(name, dst, payload)
        self._enter(f"wait_{name}")

    def _result(self, ids: np.ndarray, labels: np.ndarray, stats: Dict[str, float]) -> None:
        if self.catalog is not None:
            self._send_parts("catalog", -1, self.catalog)
        self._send_single("result", -1, ids=ids, labels=labels.astype(np.int64))
        self.stats.update({k: float(v) for k, v in stats.items()})
        self._enter("wait_acks")

    def advance(self) -> None:
        s = self.state
        if self._setup_step():
            return
        if s == "wait_routed" and all(self._complete(b, "route") for b in self._others()):
            self._routed()
        elif s.startswith("wait_") and s[5:] in ROUNDS and self.cfg.mode == "balanced":
            name = s[5:]
            senders = self.core.senders(name)
            if self._have_parts(name, senders):
                self._balanced_step(self._take_parts(name, senders))
        elif s == "wait_minima" and self._have("minima", self._others()):
            for a, msg in self._take("minima", self._others()).items():
                self.minima_rows[a] = np.array(msg["values"], dtype=np.float64)
            self.core.set_minima(np.stack([self.minima_rows[a] for a in range(self.m)]))
            self._enter("wait_handdown")
        elif s == "wait_handdown" and all(self._complete(b, "handdown") for b in range(self.me + 1, self.m)):
            received, moves = [], {}
            for b in range(self.m - 1, self.me, -1):
                shard, units = self._shard_from(b, "handdown")
                if len(shard):
                    received.append((b, shard, units))
                moves[b] = protocol.unpack_moved(self.ends[(b, "handdown")]["moved"]).reshape(-1)
            out = self.core.cascade(received, moves)
            for b in range(self.me):
                sh, units = out.sends.get(b, (None, None))
                k = self._send_features(b, "handdown", sh, units) if sh is not None else 0
                self._phase_end(b, "handdown", k, len(sh) if sh is not None else 0, out.moved)
            labels = out.final_result.labels if out.final_result is not None else np.zeros(0, np.int64)
            self._result(out.final.ids, labels, {
                "features_routed": float(len(self.core.shard)), "features_final": float(len(out.final)),
                "time_cluster": self.core.time_cluster, "time_boundary": self.core.time_boundary,
                "arrival_check_failures": float(out.arrival_failures),
                "handed_down": float(sum(len(v[0]) for v in out.sends.values())),
            })
        elif s == "wait_acks" and self.bus.unacknowledged(self.me) == 0:
            stats = dict(self.stats)
            stats.update(self.times)
            stats["cpu_s"] = time.process_time() - self.cpu0
            stats["host"] = float(self.home)
            sent, rejected, duplicates, resent = self.bus.meter.snapshot()
            if self.me == self.home:  # the process's counters, reported once
                for reason, count in rejected.items():
                    stats[f"rejected:{reason}"] = float(count)
                stats["duplicates"] = float(duplicates)
                stats["resent"] = float(resent)
            for (src, dst, kind), (b, c) in sent.items():
                if src == self.me:
                    stats[f"sent:{dst}:{kind}:bytes"] = float(b)
                    stats[f"sent:{dst}:{kind}:messages"] = float(c)
            self._send_single("stats", -1, values=stats)
            self._enter("wait_finish")

    def core_features(self) -> int:
        """Features this agent's cell holds (after routing)."""
        for name in ("own", "shard"):
            held = getattr(self.core, name, None)
            if held is not None:
                return len(held)
        return 0

    def settle(self) -> None:
        """Advance as far as the messages received allow."""
        before = None
        while before != self.state:
            before = self.state
            self.advance()

    def check_timeout(self) -> None:
        if self.state != "wait_finish" and time.monotonic() - self.phase_started > self.phase_timeout_s:
            raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s in state "
                               f"{self.state!r}")


def load_agent_features(paths, me: int) -> sources.AgentFeatures:
    """Own features from FEATURES files (each read once): global ids from ``feature_ids`` or
    (agent << 32) + row, images named by their source (:func:`dqm.distributed.sources.agent_features`)."""
    from ..io import load_features

    return sources.agent_features([load_features(p) for p in paths], me, [str(p) for p in paths])


class Refused(RuntimeError):
    """This process will not take part in the job (a parameter differs, a takeover is impossible)."""


class CoordinatorLost(RuntimeError):
    """The coordinator's liveliness token vanished."""


class AgentHost:
    """One agent process: its own agent (``home``) and any lost agents' cells the coordinator gave it.

    Control messages (``start``, ``go``, ``abort``, ``finish``) come from the
    coordinator; each ``start`` opens an epoch with a fresh :class:`AgentProcess`
    for every agent this process hosts (its own features, and the features of
    a lost agent re-read from that agent's files).
    """

    def __init__(self, home: int, cfg: DQMConfig, bus: Bus, paths: Dict[int, List[str]],
                 phase_timeout_s: float = 120.0, log=None, own: Optional[sources.AgentFeatures] = None):
        self.home = home
        self.cfg = cfg
        self.bus = bus
        self.paths = paths
        self.phase_timeout_s = phase_timeout_s
        self.log = log or (lambda text: print(f"[agent {home}] {text}", file=sys.stderr, flush=True))
        self.features: Dict[int, sources.AgentFeatures] = {
            home: own if own is not None else load_agent_features(paths[home], home)}
        bus.dim = self.features[home].descriptors.shape[1]
        self.slots: Dict[int, AgentProcess] = {}
        self.epoch = -1
        self.seed: Optional[int] = None
        self.done = False
        self.t0 = time.monotonic()

    @property
    def phase(self) -> str:
        """Where this process is, for messages: its own agent's state."""
        slot = self.slots.get(self.home)
        return slot.state if slot is not None else "wait_start"

    def _load(self, agent: int):
        if agent not in self.features:
            if agent not in self.paths:
                raise Refused(f"cannot take over agent {agent}: this process has no path to its FEATURES files "
                              f"(start agents with --peer-features {agent}=FILE)")
            try:
                self.features[agent] = load_agent_features(self.paths[agent], agent)
            except (OSError, ValueError) as exc:
                raise Refused(f"cannot take over agent {agent}: {exc}") from None
        return self.features[agent]

    def _refuse(self, reason: str, param: str = "") -> None:
        self.bus.send_single(self.home, -1, "refuse", reason=reason, param=param)
        raise Refused(reason)

    def control(self, msg: dict) -> None:
        kind = msg["kind"]
        if kind == "start":
            if msg["epoch"] <= self.epoch:
                return  # a repeated start of this epoch
            self.bus.set_epoch(msg["epoch"])
            mine = self.cfg.params_text()
            if msg["params_hash"] != params_hash(mine) or msg["agents"] != self.cfg.agents:
                name, ours, theirs = differing_param(mine, msg["params"]) or ("params", "?", "?")
                self._refuse(f"parameter {name} differs: this agent has {name}={ours}, the coordinator "
                             f"{name}={theirs}; start every process of a job with the same algorithm options", name)
            hosted = [int(a) for a in np.flatnonzero(msg["owners"] == self.home)]
            if self.home not in hosted:
                self._refuse(f"the coordinator gave this process's own agent {self.home} to another process")
            try:
                feats = {a: self._load(a) for a in hosted}
            except Refused as exc:
                self._refuse(str(exc))
            dims = {f.descriptors.shape[1] for f in feats.values()}  # the home agent is among them
            if len(dims) != 1:
                self._refuse(f"the FEATURES files of agents {hosted} have different dimensions {sorted(dims)}",
                             "dimension")
            self.bus.dim = dims.pop()
            self.bus.host(hosted)
            self.epoch = msg["epoch"]
            self.seed = msg["seed"]
            self.slots = {a: AgentProcess(a, self.cfg, self.bus, f.ids, f.image_ids, f.descriptors,
                                          phase_timeout_s=self.phase_timeout_s, log=self.log, epoch=self.epoch,
                                          home=self.home, catalog=f.catalog if msg["catalog"] else None)
                          for a, f in feats.items()}
            if self.epoch > 0:
                self.log(f"epoch {self.epoch}: hosting agents {hosted}")
            own = self.features[self.home].descriptors
            self.bus.send_single(self.home, -1, "ready", dim=int(own.shape[1]), dtype=own.dtype.str,
                                 hosted=np.asarray(hosted, np.int64),
                                 features=int(sum(len(f) for f in feats.values())))
        elif kind == "go" and msg["epoch"] == self.epoch:
            for slot in self.slots.values():
                slot.begin(self.seed)
        elif kind == "abort":
            raise JobAborted(f"the coordinator aborted the job: {msg['reason']}")
        elif kind == "finish":
            self.done = True

    def run(self) -> None:
        while not self.done:
            item = self.bus.receive(timeout=0.05)
            if item is not None:
                dst, msg = item
                if msg["src"] == -1:
                    self.control(msg)
                elif dst in self.slots:
                    self.slots[dst].handle(msg)
            for a in sorted(self.slots):
                self.slots[a].settle()
            self.bus.resend_due()
            if self.epoch >= 0 and self.bus.coordinator_alive() is False:
                raise CoordinatorLost(f"the coordinator vanished (its liveliness token was lost) while this agent was "
                                      f"in phase {self.phase}")
            for slot in self.slots.values():
                slot.check_timeout()
            if self.epoch < 0 and time.monotonic() - self.t0 > self.phase_timeout_s:
                raise TimeoutError(f"no start from a coordinator within {self.phase_timeout_s:.0f} s")


def parse_peer_features(specs: Optional[List[str]]) -> Dict[int, List[str]]:
    """``["2=/data/a2.npz,/data/a2b.npz", ...]`` -> {2: [...]}: where a lost agent's images can be re-read."""
    from ..validation import InputError

    out: Dict[int, List[str]] = {}
    for spec in specs or []:
        agent, sep, paths = spec.partition("=")
        if not sep or not agent.strip().isdigit() or not paths:
            raise InputError(f"--peer-features must look like AGENT=FILE[,FILE...], got {spec!r}")
        out[int(agent)] = [p for p in paths.split(",") if p]
    return out


#: exit codes of ``dqm agent`` (docs/runtime.md)
EXIT_OK, EXIT_FAILED, EXIT_REFUSED, EXIT_COORDINATOR_LOST, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 3, 4, 5, 130, 143


def main_agent(me: int, cfg: DQMConfig, endpoint: str, paths, tls: Optional[dict] = None,
               connect_timeout_s: float = 5.0, phase_timeout_s: float = 120.0,
               max_message_bytes: int = messages.MAX_MESSAGE_BYTES,
               peers: Optional[Dict[int, List[str]]] = None) -> int:
    """Entry point of ``dqm agent``: returns the process exit code."""
    from .lifeline import watch_parent

    signal.signal(signal.SIGTERM, _on_sigterm)
    watch_parent()
    keys.check_job(cfg.job)
    files = dict(peers or {})
    files[me] = list(paths)
    log = lambda text: print(f"[agent {me}] {text}", file=sys.stderr, flush=True)  # noqa: E731
    own = load_agent_features(paths, me)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    check_job_free(session, keys.alive_agent(cfg.job, me), f"agent {me}", cfg.job, endpoint)
    host = None
    bus = None
    try:
        bus = Bus(session, cfg.job, me, cfg.agents, max_bytes=max_message_bytes)
        host = AgentHost(me, cfg, bus, files, phase_timeout_s=phase_timeout_s, log=log, own=own)
        host.run()
        return EXIT_OK
    except Refused as exc:
        log(f"refused: {exc}")
        time.sleep(0.3)  # let the refusal reach the coordinator before the token goes
        return EXIT_REFUSED
    except CoordinatorLost as exc:
        log(f"error: {exc}. This agent leaves; to run the job again, start the coordinator and every agent again "
            "with the same options (a job restarts from the beginning).")
        return EXIT_COORDINATOR_LOST
    except (JobAborted, TimeoutError) as exc:
        log(f"error: {exc}")
        return EXIT_FAILED
    except KeyboardInterrupt:
        log("interrupted, leaving")
        return EXIT_INTERRUPTED
    except Terminated:
        log("terminated, leaving")
        return EXIT_TERMINATED
    finally:
        if bus is not None:
            bus.close()
        else:
            session.close()
