"""The one agent driver: the protocol's choreography around one agent's cores, sans I/O.

:class:`AgentDriver` takes decoded messages (:meth:`AgentDriver.handle`) and
advances through explicit states (:data:`STATES`) as far as they allow
(:meth:`AgentDriver.settle`), sending through a :class:`Transport`. It runs the
set-up of :mod:`dqm.distributed.seeding`, routing, then the balanced rounds
(:class:`~dqm.distributed.balanced.BalancedCore`) or the lean / paper cascade
(:class:`~dqm.distributed.cascade.CascadeCore`), and reports its result and
statistics to the coordinator.

Two transports feed the same driver:

* the simulator's in-memory network (:class:`dqm.distributed.network.MemoryBus`, one per
  process): messages are encoded, metered, decoded and queued, all in one process, through the
  same delivery layer (:mod:`dqm.distributed.delivery`) on a virtual clock;
* the runtime's zenoh bus (:class:`dqm.runtime.bus.Bus`), one OS process per
  agent (or per process hosting several agents after a takeover).

So the order of the messages on every link, and every metered byte, are the
same in both by construction. The start of an epoch (the coordinator's
``start``, the agents' ``ready``, the coordinator's ``go``) uses
:func:`start_fields` and :func:`ready_fields` on both sides as well.
"""
from __future__ import annotations

import time
from collections import defaultdict, deque
from typing import Callable, Deque, Dict, List, Optional, Protocol, Sequence, Tuple

import numpy as np

from . import cascade, messages, partition, protocol, seeding
from .balanced import ROUNDS, BalancedCore
from .config import DQMConfig, params_hash
from .ledger import COORDINATOR, Meter
from .seeding import LEADER
from .shard import Shard

#: the states of an agent, in the order a job passes them: set-up and routing, then the balanced
#: rounds or the cascade's minima and hand-down, then the end of the job
SETUP_STATES = ("wait_start", "wait_seeds", "wait_fill", "wait_weights", "wait_routed")
BALANCED_STATES = tuple(f"wait_{name}" for name in ROUNDS)
CASCADE_STATES = ("wait_minima", "wait_handdown")
END_STATES = ("wait_acks", "wait_finish")
STATES = SETUP_STATES + BALANCED_STATES + CASCADE_STATES + END_STATES

#: message kinds that arrive once per sender and step (kept in arrival order per sender)
SINGLE_KINDS = ("sample", "seeds", "fill", "counts", "weights", "minima")
#: windows of copies a balanced agent asks for before the first has arrived (two: one travels while
#: the agent meets the other with its own features)
PULL_WINDOWS = 2


def states_for(mode: str) -> Tuple[str, ...]:
    """The states an agent of a job in ``mode`` passes, in order."""
    return SETUP_STATES + (BALANCED_STATES if mode == "balanced" else CASCADE_STATES) + END_STATES


class JobAborted(RuntimeError):
    """The job cannot go on (the coordinator aborted it, or a peer sent what this agent cannot use)."""


class Transport(Protocol):
    """What the driver needs of a bus: numbered, metered sends and the count of unacknowledged ones."""

    meter: Meter

    def next_seq(self, src: int, dst: int, count: int = 1) -> int: ...

    def send(self, src: int, dst: int, kind: str, payload: bytes, seq: Optional[int] = None) -> None: ...

    def send_single(self, src: int, dst: int, kind: str, **fields) -> None: ...

    def unacknowledged(self, src: Optional[int] = None) -> int: ...


def start_fields(cfg: DQMConfig, owners: np.ndarray, catalog: bool) -> dict:
    """The coordinator's ``start`` of an epoch: the seed integer, the process hosting each agent and
    the parameters every process checks."""
    text = cfg.params_text()
    return dict(seed=cfg.seed, agents=cfg.agents, owners=np.asarray(owners, np.int64), params=text,
                params_hash=params_hash(text), catalog=int(catalog))


def ready_fields(descriptors: np.ndarray, hosted: Sequence[int], n_features: int) -> dict:
    """A process's ``ready``: its descriptors' dimension and type, the agents it hosts, their features."""
    return dict(dim=int(descriptors.shape[1]), dtype=descriptors.dtype.str, hosted=np.asarray(hosted, np.int64),
                features=int(n_features))


class AgentDriver:
    """One agent's side of the protocol. States: :data:`STATES` (``wait_start``, the set-up,
    ``wait_routed``, the balanced rounds or ``wait_minima`` / ``wait_handdown``, ``wait_acks``,
    ``wait_finish``).

    ``on_state(agent, state)`` is called on entering every state (a test's fault injection, a
    log); ``trace``: keep what the simulator reports beyond the labels (the cascade's initial
    contested flags and hand-down targets). After the job, :attr:`core_stats` holds the core's typed
    statistics and :attr:`core` the core itself; the labels travel in the ``result`` message.
    """

    def __init__(self, me: int, cfg: DQMConfig, transport: Transport, ids: np.ndarray, image_ids: np.ndarray,
                 descriptors: np.ndarray, phase_timeout_s: float = 120.0, epoch: int = 0,
                 home: Optional[int] = None, catalog: Optional[Dict[str, np.ndarray]] = None,
                 on_state: Optional[Callable[[int, str], None]] = None, trace: bool = False):
        self.me = me
        self.catalog = catalog  # sent to the coordinator with the result when the job asked for it
        self.epoch = epoch
        self.home = me if home is None else home
        self.cfg = cfg
        self.m = cfg.agents
        self.bus = transport
        self.desc = protocol.wire_descriptors(descriptors)
        self.dim = self.desc.shape[1]
        self.ids = np.asarray(ids, np.int64)
        self.image_ids = np.asarray(image_ids, np.int64)
        self.states = states_for(cfg.mode)
        self.state = "wait_start"
        self.phase_timeout_s = phase_timeout_s
        self.phase_started = time.monotonic()
        self.waiting_since = self.phase_started  # what the phase timeout measures: the last step forward
        self.on_state = on_state
        self.trace = trace
        self.seed: Optional[int] = None
        self.core = None
        self.source: Optional[seeding.SourceSide] = None
        self.leader: Optional[seeding.Leader] = None
        self.own: Dict[str, dict] = {}
        self.singles: Dict[Tuple[str, int], Deque[dict]] = defaultdict(deque)
        self.parts: Dict[Tuple[str, int], Dict[int, dict]] = defaultdict(dict)
        self.chunks: Dict[Tuple[int, str], List[dict]] = defaultdict(list)
        self.ends: Dict[Tuple[int, str], dict] = {}
        self.grants: Dict[int, Deque[dict]] = defaultdict(deque)  # balanced: windows other cells asked for
        self.windows_in: Dict[Tuple[int, int], Dict[int, dict]] = defaultdict(dict)  # (sender, offset) -> parts
        self.asked: Dict[Tuple[int, int], int] = {}  # windows asked for and not yet in: (sender, offset) -> count
        self.held_peak = 0  # the most feature rows this agent held at once (measured, see held_rows)
        self.times: Dict[str, float] = {}
        self.cpu0 = time.process_time()
        self.stats: Dict[str, float] = {}
        self.core_stats: Dict[str, float] = {}
        self.contested_initial: Optional[np.ndarray] = None  # trace, cascade
        self.handed: Dict[int, np.ndarray] = {}  # trace, cascade: target agent -> feature ids handed down
        if on_state is not None:
            on_state(me, self.state)

    @property
    def step_index(self) -> int:
        """How far this agent is: the index of its state in :attr:`states`."""
        return self.states.index(self.state)

    # ------------------------------------------------------------------ messages in
    def begin(self, seed: int) -> None:
        """The coordinator said go: run the protocol with this seed integer."""
        self.seed = partition.check_seed(seed)

    def handle(self, msg: dict) -> None:
        kind, src = msg["kind"], msg["src"]
        if kind == "grant" and src >= 0:
            self.grants[src].append(msg)
        elif kind == "ghost" and src >= 0:
            self.windows_in[(src, msg["offset"])][msg["part"]] = msg
        elif kind in SINGLE_KINDS and src >= 0:
            self.singles[(kind, src)].append(msg)
        elif "parts" in msg and src >= 0:
            self.parts[(kind, src)][msg["part"]] = msg
        elif kind == "features" and src >= 0:
            self.chunks[(src, msg["phase"])].append(msg)
        elif kind == "phase_end" and src >= 0 and msg["dst"] == self.me:
            self.ends[(src, msg["phase"])] = msg
        self._note_held()

    def held_rows(self) -> int:
        """Feature rows this agent holds now: its source's features until they are routed, its
        cell's, and every routed, handed-down or copied feature received and not yet let go."""
        if self.core is not None:
            rows = self.core_features()
        else:  # the cell's part of the source's own features counts once
            rows = len(self.desc) or len(getattr(self, "own_part", ()))
        rows += sum(len(c["ids"]) for chunks in self.chunks.values() for c in chunks)
        return rows + sum(len(p["ids"]) for got in self.windows_in.values() for p in got.values())

    def _note_held(self) -> None:
        self.held_peak = max(self.held_peak, self.held_rows())

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

    def _complete(self, src: int, phase: str) -> bool:
        end = self.ends.get((src, phase))
        return end is not None and len(self.chunks[(src, phase)]) == end["messages"]

    def _shard_from(self, src: int, phase: str) -> Tuple[Shard, np.ndarray]:
        ch = sorted(self.chunks.pop((src, phase), []), key=lambda c: c["seq"])
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

    # ------------------------------------------------------------------ messages out
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

    def _send_features(self, dst: int, phase: str, shard: Shard, units: Optional[np.ndarray]) -> int:
        return self._send_numbered(dst, "features", protocol.chunk_count(len(shard)), lambda seq0: (
            protocol.feature_messages(self.cfg.job, self.me, phase, shard.ids, shard.image_ids, shard.descriptors,
                                      shard.sigma, units, seq0=seq0, epoch=self.epoch)))

    def _enter(self, state: str) -> None:
        if state not in self.states:
            raise AssertionError(f"agent {self.me}: no state {state!r} in a {self.cfg.mode} job (a bug)")
        now = time.monotonic()
        self.times[f"time_{self.state}"] = self.times.get(f"time_{self.state}", 0.0) + now - self.phase_started
        self.state = state
        self.phase_started = self.waiting_since = now
        self.bus.send(self.me, COORDINATOR, "progress", messages.encode(
            "progress", self.cfg.job, self.me, epoch=self.epoch, state=state,
            features=int(len(self.ids) if self.core is None else self.core_features()),
            bytes=int(self.bus.meter.sent_by(self.me))))
        if self.on_state is not None:
            self.on_state(self.me, state)

    def _others(self) -> List[int]:
        return [b for b in range(self.m) if b != self.me]

    # ------------------------------------------------------------------ set-up (dqm.distributed.seeding)
    def _start(self) -> None:
        self.cfg = self.cfg.but(seed=self.seed)  # the one integer comes from the coordinator
        if self.me == LEADER:
            self.leader = seeding.Leader(self.cfg, self.dim)
        self.source = seeding.SourceSide(self.me, self.cfg, self.ids, self.image_ids, self.desc)
        self.own = {"sample": self.source.sample_payload()}
        if self.me != LEADER:
            self._send_single("sample", LEADER, **self.own["sample"])
        self._enter("wait_seeds")

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
        # the source's features are on their way (the delivery layer keeps what it must resend):
        # the driver lets them go (the process keeps its input arrays for a restart)
        self._note_held()
        self.source.descriptors = self.source.X = None
        self.desc = self.desc[:0]
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
        if s == "wait_start":
            if self.seed is None:
                return False
            self._start()
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

    def _serve_grants(self) -> None:
        """Send the windows of copies other cells asked for (balanced); grants that come before
        this agent has decided its copies wait for it, and are answered in the order they came."""
        core = self.core
        if not isinstance(core, BalancedCore) or core.round <= ROUNDS.index("offer"):
            return
        for b, queue in self.grants.items():
            while queue:
                g = queue.popleft()
                self._send_parts("ghost", b, core.copies(b, g["offset"], g["count"]))

    def _pull(self) -> None:
        """``wait_ghost``: ask for windows of copies (at most :data:`PULL_WINDOWS` out), meet the own
        features with each other while they travel, meet each window as it comes and let it go."""
        core = self.core
        self._ask()
        if core.meet_own():
            self.waiting_since = time.monotonic()
        while self._absorb_ready():
            self._ask()
        if core.pulled() and not self.asked:
            self._balanced_step({})  # the sums round: the copies came window by window

    def _absorb_ready(self) -> int:
        """Absorb every window that was asked for and has all its parts; returns how many."""
        done = 0
        for key in sorted(self.windows_in):
            got = self.windows_in[key]
            # a window not asked for yet waits (after a takeover, senders replay what they had sent)
            if key not in self.asked or len(got) != next(iter(got.values()))["parts"]:
                continue  # (what it holds was noted when the window's last part came: handle)
            del self.windows_in[key]
            expected = self.asked.pop(key)
            try:
                payload = protocol.merge_parts("ghost", list(got.values()))
            except messages.MessageError as exc:
                self.bus.meter.reject(str(exc))
                payload = None
            self.core.absorb(key[0], payload, expected)
            self.waiting_since = time.monotonic()  # a window met is a step forward (the timeout is for waits)
            done += 1
        return done

    def _ask(self) -> None:
        """Grant the next windows of copies until :data:`PULL_WINDOWS` are out."""
        while len(self.asked) < PULL_WINDOWS:
            g = self.core.next_grant()
            if g is None:
                return
            a, offset, count = g
            self.asked[(a, offset)] = count
            self._send_parts("grant", a, {"offset": offset, "count": count})

    def _minima(self) -> None:
        for a, msg in self._take("minima", self._others()).items():
            self.minima_rows[a] = np.array(msg["values"], dtype=np.float64)
        self.core.set_minima(np.stack([self.minima_rows[a] for a in range(self.m)]))
        if self.trace:
            self.contested_initial = self.core.contested_now()
        self._enter("wait_handdown")

    def _handdown(self) -> None:
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
            if self.trace and sh is not None:
                self.handed[b] = sh.ids
        labels = out.final_result.labels if out.final_result is not None else np.zeros(0, np.int64)
        self._result(out.final.ids, labels, self.core.outcome_stats(out))

    def _result(self, ids: np.ndarray, labels: np.ndarray, stats: Dict[str, float]) -> None:
        labels = np.asarray(labels).astype(np.int64)
        if self.catalog is not None:
            self._send_parts("catalog", COORDINATOR, self.catalog)
        self._send_single("result", COORDINATOR, ids=ids, labels=labels)
        self.core_stats = {k: float(v) for k, v in stats.items()}
        self._note_held()
        self.core_stats["held_peak"] = float(self.held_peak)
        self.stats.update(self.core_stats)
        self._enter("wait_acks")

    def _report(self) -> None:
        """Everything acknowledged: send this agent's statistics (with what it sent) and wait for the end."""
        stats = dict(self.stats)
        stats.update(self.times)
        stats["cpu_s"] = time.process_time() - self.cpu0
        stats["host"] = float(self.home)
        if self.me == self.home:  # the process's counters, reported once
            stats.update(self.bus.meter.counter_stats())
        stats.update(self.bus.meter.as_stats(src=self.me))
        self._send_single("stats", COORDINATOR, values=stats)
        self._enter("wait_finish")

    def advance(self) -> None:
        s = self.state
        self._serve_grants()
        if self._setup_step():
            return
        if s == "wait_ghost" and self.cfg.mode == "balanced":
            self._pull()
        elif s == "wait_routed" and all(self._complete(b, "route") for b in self._others()):
            self._routed()
        elif s in BALANCED_STATES and self.cfg.mode == "balanced":
            name = s[5:]
            senders = self.core.senders(name)
            if self._have_parts(name, senders):
                self._balanced_step(self._take_parts(name, senders))
        elif s == "wait_minima" and self._have("minima", self._others()):
            self._minima()
        elif s == "wait_handdown" and all(self._complete(b, "handdown") for b in range(self.me + 1, self.m)):
            self._handdown()
        elif s == "wait_acks" and self.bus.unacknowledged(self.me) == 0:
            self._report()

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
        if self.state != "wait_finish" and time.monotonic() - self.waiting_since > self.phase_timeout_s:
            raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s in state "
                               f"{self.state!r}")
