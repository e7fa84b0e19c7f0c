"""A zenoh session for one dqm process: inbox, metered sends, liveliness, clean close.

Facts this relies on (docs/runtime.md, shared/notes/zenoh-facts.md):

* everyone but the router is a zenoh *client* of one router; multicast
  scouting and gossip are off; shared memory is off so that bytes on the wire
  are what we count;
* puts use CongestionControl.BLOCK (the default DROP loses messages silently);
  on top, every bulk message (``features`` chunks, the parts of the balanced
  rounds) carries a sequence number, is acknowledged and resent until
  acknowledged, and receivers drop duplicates;
* callbacks only push to a queue; a receiver thread decodes and validates each
  message, acknowledges it at once and drops duplicates (so a sender hears
  back within milliseconds even while this process computes a long round),
  and hands the rest to the process's main thread, where all other work happens;
* the session is closed in ``close()`` (called from ``finally``): a session
  with Python callbacks left open hangs the interpreter at exit.
"""
from __future__ import annotations

import json
import queue
import threading
import time
from collections import defaultdict
from typing import Dict, List, Optional, Tuple

from ..distributed import messages
from ..distributed import keys

ROUTER_RETRY_S = 5.0


class RouterUnreachable(RuntimeError):
    """No zenoh router answered at the given endpoint within the retry deadline."""


def _base_config(extra: Optional[dict] = None) -> dict:
    cfg = {
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": False}},
    }
    if extra:
        for k, v in extra.items():
            cfg[k] = v
    return cfg


def client_config(endpoint: str, tls: Optional[dict] = None) -> "object":
    """zenoh Config of a client connected to ``endpoint`` (tcp/HOST:PORT or tls/HOST:PORT)."""
    import zenoh

    cfg = _base_config({"mode": "client", "connect": {"endpoints": [endpoint]}})
    if tls:
        cfg["transport"]["link"] = {"tls": tls}
    return zenoh.Config.from_json5(json.dumps(cfg))


def router_config(endpoints: List[str], tls: Optional[dict] = None) -> "object":
    import zenoh

    cfg = _base_config({"mode": "router", "listen": {"endpoints": list(endpoints)}})
    if tls:
        cfg["transport"]["link"] = {"tls": tls}
    return zenoh.Config.from_json5(json.dumps(cfg))


def open_client(endpoint: str, tls: Optional[dict] = None, deadline_s: float = ROUTER_RETRY_S):
    """Open a client session, retrying until ``deadline_s``; RouterUnreachable names the endpoint."""
    import zenoh

    t0 = time.monotonic()
    delay = 0.05
    last = None
    while True:
        try:
            return zenoh.open(client_config(endpoint, tls))
        except Exception as exc:  # zenoh raises ZError (or others) when nothing listens
            last = exc
        if time.monotonic() - t0 > deadline_s:
            raise RouterUnreachable(_unreachable_message(endpoint, deadline_s, last))
        time.sleep(delay)
        delay = min(0.5, delay * 2)


def _unreachable_message(endpoint: str, deadline_s: float, last) -> str:
    """Why ``open_client`` gave up: nothing listens, or something listens but refused the session (TLS)."""
    import socket

    base = f"no zenoh router reachable at {endpoint} after {deadline_s:.0f} s of retries ({last})"
    proto, _, addr = endpoint.split("#")[0].split("?")[0].partition("/")
    host, _, port = addr.rpartition(":")
    try:
        with socket.create_connection((host.strip("[]"), int(port)), timeout=1.0):
            pass
    except (OSError, ValueError):
        return base  # nothing listens there (or the endpoint is not HOST:PORT)
    if proto == "tls":
        return (f"{base}; something listens at {addr} but refused the TLS session: check that --tls-ca is the CA "
                f"that signed the router's certificate, that the router's certificate names {host} "
                f"(subjectAltName), and that --tls-cert/--tls-key were issued by the CA the router trusts")
    return f"{base}; something listens at {addr} but refused a {proto} zenoh session (a tls/ router?)"


class Meter:
    """Bytes and messages sent per (src, dst, kind), and received messages rejected per reason.

    Updated from the main thread and from the receiver thread (acks): under a lock.
    """

    def __init__(self):
        self.sent: Dict[Tuple[int, int, str], List[int]] = defaultdict(lambda: [0, 0])
        self.rejected: Dict[str, int] = defaultdict(int)
        self.duplicates = 0
        self.resent = 0
        self.lock = threading.Lock()

    def add(self, src: int, dst: int, kind: str, nbytes: int) -> None:
        with self.lock:
            e = self.sent[(src, dst, kind)]
            e[0] += nbytes
            e[1] += 1

    def reject(self, reason: str) -> None:
        with self.lock:
            self.rejected[reason[:80]] += 1

    def snapshot(self) -> Tuple[Dict[Tuple[int, int, str], Tuple[int, int]], Dict[str, int], int, int]:
        """``(sent, rejected, duplicates, resent)`` copied under the lock."""
        with self.lock:
            return ({k: (v[0], v[1]) for k, v in self.sent.items()}, dict(self.rejected), self.duplicates,
                    self.resent)

    def as_dict(self) -> dict:
        return {"sent": [[s, d, k, b, c] for (s, d, k), (b, c) in sorted(self.sent.items())],
                "rejected": dict(self.rejected), "duplicates": self.duplicates, "resent": self.resent}


class Bus:
    """One process's view of the job's key space."""

    def __init__(self, session, job: str, me: int, n_agents: int, dim: Optional[int] = None,
                 max_bytes: int = messages.MAX_MESSAGE_BYTES):
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.job = job
        self.me = me
        self.n_agents = n_agents
        self.dim = dim
        self.max_bytes = max_bytes
        self.inbox: "queue.Queue" = queue.Queue()  # decoded messages for the main thread
        self._raw: "queue.Queue" = queue.Queue()  # payloads as they arrive
        self.meter = Meter()
        self.alive: Dict[str, bool] = {}
        self._alive_lock = threading.Lock()
        self._closed = False
        self._pending: Dict[Tuple[int, int], Tuple[float, int, bytes, str]] = {}  # (dst, seq) -> (t, tries, payload, kind)
        self._pending_lock = threading.Lock()
        self._seen: set = set()
        self._receiver = threading.Thread(target=self._receive_loop, name=f"dqm-bus-{me}", daemon=True)
        self._receiver.start()
        self._next_seq: Dict[int, int] = defaultdict(int)
        my_key = keys.coordinator_inbox(job) if me < 0 else keys.agent_inbox(job, me)
        self._sub = session.declare_subscriber(my_key, self._on_sample)
        self._live_sub = session.liveliness().declare_subscriber(keys.alive_all(job), self._on_alive, history=True)
        self._token = session.liveliness().declare_token(
            keys.alive_coordinator(job) if me < 0 else keys.alive_agent(job, me))

    # ------------------------------------------------------------------ callbacks (tiny)
    def _on_sample(self, sample) -> None:
        self._raw.put(bytes(sample.payload.to_bytes()))

    def _on_alive(self, sample) -> None:
        alive = str(sample.kind) == str(self._zenoh.SampleKind.PUT)
        with self._alive_lock:
            self.alive[str(sample.key_expr)] = alive
        self.inbox.put(None)  # wake the main loop

    # ------------------------------------------------------------------ liveliness
    def agent_alive(self, i: int) -> Optional[bool]:
        with self._alive_lock:
            return self.alive.get(keys.alive_agent(self.job, i))

    def coordinator_alive(self) -> Optional[bool]:
        with self._alive_lock:
            return self.alive.get(keys.alive_coordinator(self.job))

    # ------------------------------------------------------------------ sending
    def next_seq(self, dst: int, count: int = 1) -> int:
        s = self._next_seq[dst]
        self._next_seq[dst] += count
        return s

    def _put(self, dst: int, kind: str, payload: bytes) -> None:
        key = keys.coordinator_inbox(self.job) if dst < 0 else keys.agent_inbox(self.job, dst)
        self.session.put(key, payload, congestion_control=self._zenoh.CongestionControl.BLOCK)
        self.meter.add(self.me, dst, kind, len(payload) + len(key))

    def send(self, dst: int, kind: str, payload: bytes, seq: Optional[int] = None) -> None:
        """Put a message to agent ``dst`` (or the coordinator, dst = -1), metered.

        With ``seq`` the message is kept until acknowledged and resent by
        :meth:`resend_due`.
        """
        if seq is not None:
            with self._pending_lock:  # before the put: the ack may come back at once
                self._pending[(dst, seq)] = (time.monotonic(), 1, payload, kind)
        self._put(dst, kind, payload)

    def acknowledged(self, src: int, seq: int) -> None:
        with self._pending_lock:
            self._pending.pop((src, seq), None)

    def unacknowledged(self) -> int:
        with self._pending_lock:
            return len(self._pending)

    def resend_due(self, timeout_s: float = 2.0, max_tries: int = 5) -> None:
        """Resend chunks not acknowledged within ``timeout_s``; raise after ``max_tries``."""
        now = time.monotonic()
        with self._pending_lock:
            due = [(k, v) for k, v in self._pending.items() if now - v[0] >= timeout_s]
        for (dst, seq), (t, tries, payload, kind) in due:
            if tries >= max_tries:
                raise TimeoutError(f"agent {dst} did not acknowledge message {seq} after {tries} sends")
            with self._pending_lock:
                if (dst, seq) not in self._pending:
                    continue  # acknowledged meanwhile
                self._pending[(dst, seq)] = (now, tries + 1, payload, kind)
            self._put(dst, kind, payload)
            with self.meter.lock:
                self.meter.resent += 1

    # ------------------------------------------------------------------ receiving
    def _receive_loop(self) -> None:
        """The receiver thread: decode, acknowledge, drop duplicates, hand over."""
        while not self._closed:
            try:
                raw = self._raw.get(timeout=0.2)
            except queue.Empty:
                continue
            msg = self._accept(raw)
            if msg is not None:
                self.inbox.put(msg)

    def _accept(self, raw: bytes) -> Optional[dict]:
        """A valid new message for the main thread, or None (counted bad message, duplicate, ack)."""
        try:
            msg = messages.decode(raw, job=self.job, n_agents=self.n_agents, max_bytes=self.max_bytes, dim=self.dim)
        except messages.MessageError as exc:
            self.meter.reject(str(exc).split(" (")[0])
            return None
        msg["_bytes"] = len(raw)
        if "seq" in msg and msg["kind"] != "ack":
            key = (msg["src"], msg["seq"])
            # acknowledge every copy (the first ack may have been lost), process once
            self._put(msg["src"], "ack", messages.encode("ack", self.job, self.me, seq=msg["seq"], dst=msg["src"]))
            if key in self._seen:
                with self.meter.lock:
                    self.meter.duplicates += 1
                return None
            self._seen.add(key)
        elif msg["kind"] == "ack":
            self.acknowledged(msg["src"], msg["seq"])
            return None
        return msg

    def receive(self, timeout: float = 0.2) -> Optional[dict]:
        """Next valid message, or None on timeout / liveliness wake-up. Bad messages are counted and dropped."""
        try:
            return self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for obj in (self._token, self._live_sub, self._sub):
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self._receiver.join(timeout=2.0)
        self.session.close()
