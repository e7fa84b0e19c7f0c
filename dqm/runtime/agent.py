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

from ..distributed import cascade, messages, partition, protocol, seeding
from ..distributed.balanced import ROUNDS, BalancedCore
from ..distributed.config import DQMConfig
from ..distributed.shard import Shard
from ..distributed import keys
from .bus import Bus, open_client

LEADER = seeding.LEADER


class JobAborted(RuntimeError):
    pass


def _fault_hook(me: int, state: str) -> None:
    """Test hook: with DQM_FAULT_PAUSE="<agent>:<state>" the agent stops (writing the
    file named by DQM_FAULT_MARKER) when it enters that state, so a test can kill it there."""
    spec = os.environ.get("DQM_FAULT_PAUSE")
    if not spec or spec != f"{me}:{state}":
        return
    marker = os.environ.get("DQM_FAULT_MARKER")
    if marker:
        with open(marker, "w") as fh:
            fh.write(f"{os.getpid()}\n")
    time.sleep(float(os.environ.get("DQM_FAULT_SECONDS", "60")))


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
                 descriptors: np.ndarray, phase_timeout_s: float = 120.0, log=None):
        self.me = me
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
        self.source: Optional[seeding.SourceSide] = None
        self.leader: Optional[seeding.Leader] = None
        self.singles: Dict[Tuple[str, int], Deque[dict]] = defaultdict(deque)
        self.parts: Dict[Tuple[str, int], Dict[int, dict]] = defaultdict(dict)
        self.chunks: Dict[Tuple[int, str], List[dict]] = defaultdict(list)
        self.ends: Dict[Tuple[int, str], dict] = {}
        self.finished = False
        self.times: Dict[str, float] = {}
        self.cpu0 = time.process_time()
        self.stats: Dict[str, float] = {}
        _fault_hook(me, "wait_start")

    # ------------------------------------------------------------------ messages
    def handle(self, msg: dict) -> None:
        kind, src = msg["kind"], msg["src"]
        if kind == "start" and src == -1:
            if msg["agents"] != self.m:
                raise JobAborted(f"coordinator runs {msg['agents']} agents, this agent was started with {self.m}")
            if msg["mode"] != self.cfg.partition:
                raise JobAborted(f"coordinator uses partition {msg['mode']!r}, this agent {self.cfg.partition!r}")
            self.seed = partition.check_seed(msg["seed"])
        elif kind in _SINGLE and src >= 0:
            self.singles[(kind, src)].append(msg)
        elif "parts" in msg and src >= 0:
            self.parts[(kind, src)][msg["part"]] = msg
        elif kind == "features" and src >= 0:
            self.chunks[(src, msg["phase"])].append(msg)
        elif kind == "phase_end" and src >= 0 and msg["dst"] == self.me:
            self.ends[(src, msg["phase"])] = msg
        elif kind == "abort" and src == -1:
            raise JobAborted(f"coordinator aborted the job: {msg['reason']}")
        elif kind == "finish" and src == -1:
            self.finished = True

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
        seq0 = self.bus.next_seq(dst, count)
        msgs = build(seq0)
        for j, msg in enumerate(msgs):
            self.bus.send(dst, kind, msg, seq=seq0 + j)
        return len(msgs)

    def _send_parts(self, kind: str, dst: int, payload: dict) -> None:
        self._send_numbered(dst, kind, protocol.part_count(kind, payload),
                            lambda seq0: protocol.data_messages(kind, self.cfg.job, self.me, payload, seq0=seq0))

    def _send_single(self, kind: str, dst: int, **fields) -> None:
        self.bus.send(dst, kind, messages.encode(kind, self.cfg.job, self.me, **fields))

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
                                      shard.sigma, units, seq0=seq0)))

    def _enter(self, state: str) -> None:
        now = time.monotonic()
        self.times[f"time_{self.state}"] = self.times.get(f"time_{self.state}", 0.0) + now - self.phase_started
        self.state = state
        self.phase_started = now
        _fault_hook(self.me, state)

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
            self.bus.send(b, "phase_end", protocol.phase_end(self.cfg.job, self.me, b, "route", k, len(parts[b])))
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
        self.bus.send(-1, "result", messages.encode("result", self.cfg.job, self.me, ids=ids,
                                                    labels=labels.astype(np.int64)))
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
                self.bus.send(b, "phase_end", protocol.phase_end(
                    self.cfg.job, self.me, b, "handdown", k, len(sh) if sh is not None else 0, out.moved))
            labels = out.final_result.labels if out.final_result is not None else np.zeros(0, np.int64)
            self._result(out.final.ids, labels, {
                "features_routed": float(len(self.core.shard)), "features_final": float(len(out.final)),
                "time_cluster": self.core.time_cluster, "time_boundary": self.core.time_boundary,
                "arrival_check_failures": float(out.arrival_failures),
                "handed_down": float(sum(len(v[0]) for v in out.sends.values())),
            })
        elif s == "wait_acks" and self.bus.unacknowledged() == 0:
            stats = dict(self.stats)
            stats.update(self.times)
            stats["cpu_s"] = time.process_time() - self.cpu0
            sent, rejected, duplicates, resent = self.bus.meter.snapshot()
            for reason, count in rejected.items():
                stats[f"rejected:{reason}"] = float(count)
            stats["duplicates"] = float(duplicates)
            stats["resent"] = float(resent)
            for (src, dst, kind), (b, c) in sent.items():
                stats[f"sent:{dst}:{kind}:bytes"] = float(b)
                stats[f"sent:{dst}:{kind}:messages"] = float(c)
            self.bus.send(-1, "stats", messages.encode("stats", self.cfg.job, self.me, values=stats))
            self._enter("wait_finish")
        elif s == "wait_finish" and self.finished:
            self._enter("done")

    def run(self, overall_timeout_s: float = 600.0) -> None:
        t0 = time.monotonic()
        while self.state != "done":
            msg = self.bus.receive(timeout=0.05)
            if msg is not None:
                self.handle(msg)
            before = None
            while before != self.state:  # advance as far as possible
                before = self.state
                self.advance()
            self.bus.resend_due()
            if self.state not in ("wait_start",) and self.bus.coordinator_alive() is False:
                raise JobAborted("the coordinator vanished (liveliness token lost)")
            if time.monotonic() - self.phase_started > self.phase_timeout_s:
                raise TimeoutError(f"agent {self.me} waited more than {self.phase_timeout_s:.0f} s in state "
                                   f"{self.state!r}")
            if time.monotonic() - t0 > overall_timeout_s:
                raise TimeoutError(f"agent {self.me} exceeded the overall timeout of {overall_timeout_s:.0f} s")


def load_agent_features(paths, me: int):
    """Own features from FEATURES files; global ids from ``feature_ids`` or (agent << 32) + row."""
    from ..io import load_features

    ids, imgs, descs = [], [], []
    offset = 0
    for p in paths:
        fs = load_features(p)
        with np.load(p, allow_pickle=False) as z:
            fid = z["feature_ids"] if "feature_ids" in z.files else None
        if fid is None:
            fid = (np.int64(me) << np.int64(32)) + offset + np.arange(len(fs), dtype=np.int64)
        offset += len(fs)
        ids.append(np.asarray(fid, np.int64))
        imgs.append(np.asarray(fs.image_ids, np.int64))
        descs.append(protocol.wire_descriptors(fs.descriptors))
    if not descs:
        raise ValueError("no features files given")
    return np.concatenate(ids), np.concatenate(imgs), np.concatenate(descs)


def main_agent(me: int, cfg: DQMConfig, endpoint: str, paths, tls: Optional[dict] = None,
               connect_timeout_s: float = 5.0, phase_timeout_s: float = 120.0,
               max_message_bytes: int = messages.MAX_MESSAGE_BYTES) -> int:
    """Entry point of ``dqm agent``: returns the process exit code."""
    signal.signal(signal.SIGTERM, _on_sigterm)
    keys.check_job(cfg.job)
    ids, imgs, desc = load_agent_features(paths, me)
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    bus = Bus(session, cfg.job, me, cfg.agents, dim=desc.shape[1], max_bytes=max_message_bytes)
    agent = AgentProcess(me, cfg, bus, ids, imgs, desc, phase_timeout_s=phase_timeout_s)
    try:
        agent.run()
        return 0
    except (JobAborted, TimeoutError) as exc:
        agent.log(f"error: {exc}")
        return 3
    except (KeyboardInterrupt, Terminated):
        agent.log("interrupted, leaving")
        return 130
    finally:
        bus.close()
