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
import logging
import queue
import re
import threading
import time
from typing import Callable, Dict, List, Optional, Tuple

from ..distributed import keys, messages
from ..distributed.delivery import Delivery
from ..distributed.ledger import Meter
from ..wording import seconds
from .limits import DEFAULT_LEASE_S

LOG = logging.getLogger("dqm.runtime")
ROUTER_RETRY_S = 5.0


class RouterUnreachable(RuntimeError):
    """No zenoh router answered at the given endpoint within the retry deadline."""


#: the default liveliness lease (ms): :attr:`dqm.runtime.limits.RuntimeLimits.lease_s` (``--lease``)
LEASE_MS = int(DEFAULT_LEASE_S * 1000)
#: keep-alive messages per lease
KEEP_ALIVE = 4
#: how long (µs) a put under congestion control BLOCK may wait for room in a link's queue before zenoh
#: closes that link (zenoh's default, 5 s, closed healthy links to hosts on saturated 10 Mbit/s links)
BLOCK_BEFORE_CLOSE_US = 60_000_000


def _base_config(extra: Optional[dict] = None, lease_ms: Optional[int] = None) -> dict:
    cfg = {
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"shared_memory": {"enabled": False},
                      "link": {"tx": {"lease": lease_ms or LEASE_MS, "keep_alive": KEEP_ALIVE,
                                      "queue": {"congestion_control": {
                                          "block": {"wait_before_close": BLOCK_BEFORE_CLOSE_US}}}}}},
    }
    if extra:
        for k, v in extra.items():
            cfg[k] = v
    return cfg


def _secure(cfg: dict, tls: Optional[dict]) -> dict:
    """Put the security settings into a configuration: ``tls`` holds zenoh's ``transport/link/tls``
    settings (as :func:`dqm.commands.runtime_options.tls_from` makes them) and, under the key
    ``usrpwd``, its ``transport/auth/usrpwd`` settings (a username and password, or the router's
    dictionary file)."""
    if tls:
        tls = dict(tls)
        usrpwd = tls.pop("usrpwd", None)
        if tls:
            cfg["transport"]["link"]["tls"] = tls
        if usrpwd:
            cfg["transport"]["auth"] = {"usrpwd": usrpwd}
    return cfg


def client_config(endpoint: str, tls: Optional[dict] = None, open_timeout_s: Optional[float] = None,
                  lease_ms: Optional[int] = None) -> "object":
    """zenoh Config of a client connected to ``endpoint`` (tcp/HOST:PORT or tls/HOST:PORT). ``open_timeout_s``:
    how long one try may wait for the router's answer once the connection is made (zenoh's default, 10 s, held
    ``--connect-timeout`` up against a listener that never answers); ``lease_ms``: its liveliness lease (None:
    :data:`LEASE_MS`)."""
    import zenoh

    cfg = _base_config({"mode": "client", "connect": {"endpoints": [endpoint]}}, lease_ms)
    if open_timeout_s is not None:
        cfg["transport"]["unicast"] = {"open_timeout": max(100, int(open_timeout_s * 1000))}
    return zenoh.Config.from_json5(json.dumps(_secure(cfg, tls)))


def router_config(endpoints: List[str], tls: Optional[dict] = None, access_control: Optional[dict] = None) -> "object":
    """zenoh Config of a router listening on ``endpoints``; ``access_control``: the block
    :func:`dqm.runtime.roster.access_control` builds (None: everyone admitted may do anything)."""
    import zenoh

    cfg = _secure(_base_config({"mode": "router", "listen": {"endpoints": list(endpoints)}}), tls)
    if access_control:
        cfg["access_control"] = access_control
    return zenoh.Config.from_json5(json.dumps(cfg))


#: transports a zenoh endpoint may name (PROTOCOL/ADDRESS)
ENDPOINT_PROTOCOLS = ("tcp", "tls", "udp", "quic", "ws", "unixsock-stream", "unixpipe", "serial", "vsock")


def check_endpoint(endpoint: str, option: str = "--connect") -> str:
    """Refuse at once an endpoint that is not PROTOCOL/HOST:PORT (zenoh would retry it, then say 'unreachable')."""
    from ..validation import InputError

    proto, slash, addr = str(endpoint).partition("/")
    if not slash or proto not in ENDPOINT_PROTOCOLS or not addr:
        hint = f"; did you mean tcp/{endpoint}?" if not slash and ":" in str(endpoint) else ""
        raise InputError(f"{option} {endpoint!r} is not a zenoh endpoint: write PROTOCOL/HOST:PORT, "
                         f"e.g. tcp/127.0.0.1:7447{hint}")
    return endpoint


def live_tokens(session, key: str, timeout_s: float = 2.0) -> List[str]:
    """The liveliness tokens matching ``key`` that the router knows now (e.g. another process already
    serving this job id as coordinator or as this agent)."""
    replies = session.liveliness().get(key, timeout=timeout_s)
    return sorted(str(r.ok.key_expr) for r in replies if r.ok is not None)


class JobIdInUse(RuntimeError):
    """Another process already serves this job id on the router (as coordinator, or as this agent)."""


def check_job_free(session, key: str, what: str, job: str, endpoint: str) -> None:
    """Refuse to join a job whose coordinator (or this agent) is already live on the router: two jobs under
    one id would read each other's messages. Closes the session before raising :class:`JobIdInUse`."""
    if live_tokens(session, key):
        session.close()
        raise JobIdInUse(f"{what} of job {job!r} is already running on the router at {endpoint}: another job "
                         "uses this job id; give this one another --job (or wait for the other to finish)")


def zenoh_message(exc: BaseException) -> str:
    """A zenoh error without the Rust source location it ends with (a path in zenoh's build tree)."""
    text = re.sub(r"\s*(at\s+)?(/|[A-Za-z]:\\)?[\w./\\-]+\.rs:\d+(:\d+)?\.?", "", str(exc)).strip()
    return text or type(exc).__name__


def open_client(endpoint: str, tls: Optional[dict] = None, deadline_s: float = ROUTER_RETRY_S,
                check_stop: Optional[Callable[[], None]] = None, lease_ms: Optional[int] = None):
    """Open a client session, retrying until ``deadline_s``; RouterUnreachable names the endpoint.

    ``check_stop``: called between tries (every 50 ms while waiting); it raises to stop the retries
    (:meth:`dqm.signals.StopFlag.check`, for commands that catch Ctrl-C and SIGTERM themselves).
    """
    import zenoh

    check_endpoint(endpoint)

    t0 = time.monotonic()
    delay = 0.05
    last = None
    while True:
        if check_stop is not None:
            check_stop()
        left = deadline_s - (time.monotonic() - t0)
        try:
            return zenoh.open(client_config(endpoint, tls, open_timeout_s=min(10.0, max(0.2, left)), lease_ms=lease_ms))
        except Exception as exc:  # noqa: BLE001 - zenoh raises ZError (or others) when nothing listens
            if last is None:
                LOG.info("no zenoh router answers at %s yet; retrying for up to %s", endpoint, seconds(deadline_s))
            last = exc
        if time.monotonic() - t0 > deadline_s:
            raise RouterUnreachable(_unreachable_message(endpoint, deadline_s, last))
        end = time.monotonic() + delay
        while time.monotonic() < end:
            if check_stop is not None:
                check_stop()
            time.sleep(min(0.05, max(0.0, end - time.monotonic())))
        delay = min(0.5, delay * 2)


def _unreachable_message(endpoint: str, deadline_s: float, last) -> str:
    """Why ``open_client`` gave up: nothing listens, or something listens but refused the session (TLS)."""
    import socket

    base = f"no zenoh router reachable at {endpoint} after {seconds(deadline_s)} of retries ({zenoh_message(last)})"
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
    return (f"{base}; something listens at {addr} but did not open a {proto} zenoh session with this client: it "
            "is not a zenoh router, or a tls/ one, or one that admits only known usernames (--user and "
            "--password-file: check both)")


class AccessDenied(RuntimeError):
    """The router does not let this process's identity use its keys (its access control)."""


def denied_message(endpoint: str, who: str, what: str, denied: List[str], line: str, job: str,
                   hint: str = "") -> str:
    """Why the router's access control refused this process, and the roster lines that admit it."""
    return (f"the router at {endpoint} does not let identity {who!r} act as {what}: {' and '.join(denied)}. "
            f"Its roster (dqm router --acl) must hold the line '{line}'{hint}, and, if it has 'job' lines, the line "
            f"'job {job}' (a roster with job lines admits only the job ids they name)")


def check_token_admitted(endpoint: str, tls: Optional[dict], token_key: str, what: str, line: str, job: str,
                         deadline_s: float = 3.0) -> None:
    """With an identity, check through the router that this process's liveliness token is admitted (a second
    session of the same identity must see it within ``deadline_s``): the start-up check of processes whose
    messages nobody of their own identity can receive (``dqm stream``). :class:`AccessDenied` otherwise."""
    if not tls:
        return  # no identity: no access control possible
    probe = open_client(endpoint, tls, deadline_s=deadline_s)
    try:
        t0 = time.monotonic()
        while time.monotonic() - t0 < deadline_s:
            if live_tokens(probe, token_key, timeout_s=0.5):
                return
    finally:
        probe.close()
    raise AccessDenied(denied_message(endpoint, identity_of(tls) or "this client", what,
                                      [f"its liveliness token {token_key} is not admitted"], line, job))


def check_put_admitted(session, endpoint: str, tls: Optional[dict], key: str, what: str, line: str, job: str,
                       deadline_s: float = 3.0) -> None:
    """With an identity, check through the router that ``session``'s puts on ``key`` arrive: a second session
    of the same identity subscribes to ``key`` and must receive a nonce put there within ``deadline_s``. The
    start-up check of processes that only put (``dqm camera``, on its probe key). :class:`AccessDenied`
    otherwise."""
    import os

    if not tls:
        return  # no identity: no access control possible
    probe = open_client(endpoint, tls, deadline_s=deadline_s)
    nonce, arrived = os.urandom(16), threading.Event()

    def on_sample(sample) -> None:
        if bytes(sample.payload.to_bytes()) == nonce:
            arrived.set()

    try:
        sub = probe.declare_subscriber(key, on_sample)
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < deadline_s:
                session.put(key, nonce)
                if arrived.wait(0.2):
                    return
        finally:
            sub.undeclare()
    finally:
        probe.close()
    raise AccessDenied(denied_message(endpoint, identity_of(tls) or "this client", what,
                                      [f"its puts on {key} do not arrive"], line, job))


def identity_of(tls: Optional[dict]) -> str:
    """The identity a client presents: its certificate's common name, else its username ("" if none)."""
    import ssl

    tls = tls or {}
    cert = tls.get("connect_certificate")
    if cert:
        try:
            subject = ssl._ssl._test_decode_cert(cert).get("subject", ())  # the stdlib's own PEM reader
            for rdn in subject:
                for name, value in rdn:
                    if name == "commonName":
                        return value
        except Exception:  # noqa: BLE001 - an unreadable certificate is refused by zenoh already
            pass
        return f"the holder of {cert}"
    return str((tls.get("usrpwd") or {}).get("user", ""))


class Bus:
    """One process's view of the job's key space.

    ``home`` is the process's own index (-1: the coordinator); it declares the
    liveliness token ``alive/agent/<home>`` and receives on its process inbox
    (:func:`keys.process_inbox`), where every key names its sender. It starts out
    hosting agent ``home``; after a takeover it also hosts the lost agent's cell
    (:meth:`host`), and every process addresses that agent at its new process
    (:meth:`set_owners`, from the ``start`` of the epoch). Every message belongs to an
    epoch (:meth:`set_epoch`): older ones are refused and counted, and sequence
    numbers, acknowledgements and duplicate detection start afresh in each. A message
    whose key names another sender than the message, or that is for an agent this
    process does not host, is refused and counted.
    """

    def __init__(self, session, job: str, home: int, agents: int, dim: Optional[int] = None,
                 max_bytes: int = messages.MAX_MESSAGE_BYTES):
        import numpy as np
        import zenoh

        self._zenoh = zenoh
        self.session = session
        self.job = job
        self.home = home
        self.me = home
        self.agents = agents
        self.dim = dim
        self.max_bytes = max_bytes
        self.inbox: "queue.Queue" = queue.Queue()  # (inbox agent, decoded message) for the main thread
        self._raw: "queue.Queue" = queue.Queue()  # (key, payload) as they arrive
        self.meter = Meter()
        self.alive: Dict[str, bool] = {}
        self._alive_lock = threading.Lock()
        self._lock = threading.Lock()  # owners, hosted
        self._closed = False
        #: sequence numbers, acks, resends, duplicates and epochs (the one delivery layer)
        self.delivery = Delivery(job, self.meter)
        self._owners = np.arange(agents, dtype=np.int64)  # agent -> process hosting it (agent p on process p)
        self._hosted = frozenset([home]) if home >= 0 else frozenset()
        self._probes: Dict[bytes, threading.Event] = {}  # check_access: nonce -> arrived on the probe key
        self._probe_key = keys.probe_key(job, home)
        self._receiver = threading.Thread(target=self._receive_loop, name=f"dqm-bus-{home}", daemon=True)
        self._receiver.start()
        self._sub = session.declare_subscriber(keys.process_inbox(job, home), self._on_sample)
        self._live_sub = session.liveliness().declare_subscriber(keys.alive_all(job), self._on_alive, history=True)
        self.token_key = keys.alive_coordinator(job) if home < 0 else keys.alive_agent(job, home)
        self._token = session.liveliness().declare_token(self.token_key)

    # ------------------------------------------------------------------ inboxes and epochs
    def _key(self, dst: int) -> str:
        with self._lock:
            process = -1 if dst < 0 else int(self._owners[dst])
        return keys.message_key(self.job, self.home, process, dst)

    def host(self, agents) -> None:
        """Accept messages for exactly these agents (and the home agent)."""
        with self._lock:
            self._hosted = frozenset(int(a) for a in agents) | ({self.home} if self.home >= 0 else set())

    @property
    def owners(self):
        """The process hosting each agent, as this process addresses them now."""
        with self._lock:
            return self._owners

    def set_owners(self, owners) -> None:
        """The process hosting each agent in this epoch (the ``start`` message's ``owners``)."""
        import numpy as np

        with self._lock:
            self._owners = np.asarray(owners, dtype=np.int64).copy()

    def check_access(self, endpoint: str, tls: Optional[dict], what: str, deadline_s: float = 3.0) -> None:
        """With an identity (a certificate or a username) the router may enforce access control, which drops
        a denied subscription, put or token silently. Check through the router that this process may use its
        keys: a second session of the same identity (so that nothing is answered inside this one) must see
        the process's liveliness token and get a put through to its inbox. :class:`AccessDenied` names the
        identity and the key otherwise, within ``deadline_s``."""
        import os

        from .roster import Identity

        if not tls:
            return  # no identity: no access control possible
        probe = open_client(endpoint, tls, deadline_s=deadline_s)
        nonce = os.urandom(16)
        arrived = self._probes[nonce] = threading.Event()
        token = inbox = False
        try:
            t0 = time.monotonic()
            while time.monotonic() - t0 < deadline_s:
                token = token or bool(live_tokens(probe, self.token_key, timeout_s=0.5))
                probe.put(self._probe_key, nonce)
                inbox = inbox or arrived.wait(0.2)
                if token and inbox:
                    return
        finally:
            self._probes.pop(nonce, None)
            probe.close()
        who = identity_of(tls) or "this client"
        line = (Identity("coordinator", who) if self.home < 0 else Identity("agent", who, self.home)).as_line()
        denied = ([f"its liveliness token {self.token_key} is not admitted"] if not token else []) + (
            [f"messages to it on {keys.process_inbox(self.job, self.home)} do not arrive"] if not inbox else [])
        raise AccessDenied(denied_message(endpoint, who, what, denied, line, self.job,
                                          "" if self.home < 0 else
                                          " (or start this agent with the --id its certificate is for)"))

    @property
    def epoch(self) -> int:
        """The epoch this process is in."""
        return self.delivery.epoch

    def set_epoch(self, epoch: int) -> None:
        """Enter ``epoch``: numbering, pending acknowledgements and duplicate detection start afresh."""
        self.delivery.set_epoch(epoch)

    # ------------------------------------------------------------------ callbacks (tiny)
    def _on_sample(self, sample) -> None:
        self._raw.put((str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def _on_alive(self, sample) -> None:
        alive = str(sample.kind) == str(self._zenoh.SampleKind.PUT)
        with self._alive_lock:
            self.alive[str(sample.key_expr)] = alive
        self.inbox.put(None)  # wake the main loop

    # ------------------------------------------------------------------ liveliness
    def agent_alive(self, i: int) -> Optional[bool]:
        """Whether agent process ``i``'s token is present (None: never seen)."""
        with self._alive_lock:
            return self.alive.get(keys.alive_agent(self.job, i))

    def coordinator_alive(self) -> Optional[bool]:
        with self._alive_lock:
            return self.alive.get(keys.alive_coordinator(self.job))

    def router_connected(self) -> bool:
        """Whether the session still has its router (a router that stopped closes the link at once; a host or
        link that went away, within the lease)."""
        return bool(list(self.session.info.routers_zid()))

    # ------------------------------------------------------------------ sending
    def next_seq(self, src: int, dst: int, count: int = 1) -> int:
        """The first of ``count`` sequence numbers on the link ``src -> dst`` in this epoch."""
        return self.delivery.next_seq(src, dst, count)

    def _put(self, src: int, dst: int, kind: str, payload: bytes) -> None:
        key = self._key(dst)
        self.session.put(key, payload, congestion_control=self._zenoh.CongestionControl.BLOCK)
        self.meter.add(src, dst, kind, len(payload) + len(key))

    def send(self, src: int, dst: int, kind: str, payload: bytes, seq: Optional[int] = None) -> None:
        """Put a message from hosted agent ``src`` to agent ``dst`` (or the coordinator, dst = -1), metered.

        Kinds in :data:`protocol.ACKED` (pass their ``seq``) are kept until
        acknowledged and resent by :meth:`resend_due`.
        """
        kept = self.delivery.sending(src, dst, kind, payload, seq, time.monotonic())
        self._put(src, dst, kind, payload)
        if kept:
            self.delivery.put_returned(src, dst, seq, time.monotonic())

    def send_single(self, src: int, dst: int, kind: str, **fields) -> None:
        """Encode and send one message of this epoch, numbered on its link (``src -> dst``)."""
        epoch = self.delivery.epoch
        seq = 0 if kind in messages.UNNUMBERED else self.next_seq(src, dst)
        self.send(src, dst, kind, messages.encode(kind, self.job, src, seq=seq, epoch=epoch, **fields))

    def unacknowledged(self, src: Optional[int] = None) -> int:
        return self.delivery.unacknowledged(src)

    def resend_due(self) -> None:
        """Resend messages whose ack is overdue (:meth:`Delivery.due`)."""
        for r in self.delivery.due(time.monotonic()):
            self._put(r.src, r.dst, r.kind, r.payload)
            self.delivery.put_returned(r.src, r.dst, r.seq, time.monotonic())

    def forget(self, agents) -> None:
        """Stop waiting for the acks of these finished agents (:meth:`Delivery.forget`)."""
        self.delivery.forget(agents)

    def replay(self, agents) -> None:
        """Send these agents again everything this process sent them in this epoch (:meth:`Delivery.replay`)."""
        for r in self.delivery.replay(agents, time.monotonic()):
            self._put(r.src, r.dst, r.kind, r.payload)
            if r.seq >= 0:
                self.delivery.put_returned(r.src, r.dst, r.seq, time.monotonic())

    # ------------------------------------------------------------------ receiving
    def _receive_loop(self) -> None:
        """The receiver thread: decode, check the epoch, acknowledge, drop duplicates, hand over."""
        while not self._closed:
            try:
                item = self._raw.get(timeout=0.2)
            except queue.Empty:
                continue
            if item is None:  # close() wakes the thread at once
                continue
            key, raw = item
            if key == self._probe_key:
                probe = self._probes.get(raw)
                if probe is not None:
                    probe.set()
                continue
            try:
                item = self._accept(key, raw)
            except Exception as exc:  # noqa: BLE001 - never let one message stop the receiver
                self.meter.reject(f"receiver error {type(exc).__name__}")
                continue
            if item is not None:
                self.inbox.put(item)

    def _accept(self, key: str, raw: bytes) -> Optional[Tuple[int, dict]]:
        """``(agent, message)``: a valid new message for the main thread, or None (counted bad message,
        duplicate, ack)."""
        parsed = keys.parse_message_key(self.job, key)
        if parsed is None or parsed[1] != self.home:
            self.meter.reject("message on a key that is not this process's inbox")
            return None
        sender, _, dst = parsed
        with self._lock:
            owners, hosted = self._owners, self._hosted
        if self.home >= 0 and dst not in hosted:
            self.meter.reject("message for an agent this process does not host")
            return None
        try:
            msg = messages.decode(raw, job=self.job, agents=self.agents, max_bytes=self.max_bytes, dim=self.dim,
                                  sender=sender, owners=owners)
        except messages.MessageError as exc:
            self.meter.reject(str(exc).split(" (")[0])
            return None
        msg["_bytes"] = len(raw)
        msg["_key"] = key
        msg["_t"] = time.monotonic()  # when it was decoded here (a probe's answer is timed by it)
        verdict = self.delivery.receive(msg, dst, msg["_t"])
        if verdict.ack is not None:
            self._put(dst, msg["src"], "ack", verdict.ack)
        if not verdict.deliver:
            return None
        return dst, msg

    def receive(self, timeout: float = 0.2) -> Optional[Tuple[int, dict]]:
        """Next ``(inbox agent, message)``, or None on timeout / liveliness wake-up."""
        try:
            return self.inbox.get(timeout=timeout)
        except queue.Empty:
            return None

    # ------------------------------------------------------------------ shutdown
    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._raw.put(None)  # the receiver leaves now, not at its next 0.2-s poll (every process's exit waited for it)
        for obj in (self._token, self._live_sub, self._sub):
            try:
                obj.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
                pass
        self._receiver.join(timeout=2.0)
        self.session.close()
