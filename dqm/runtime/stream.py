"""``dqm stream``: online QuickMatch fed by camera nodes over zenoh.

Camera nodes put ``image`` messages (one image each; :mod:`dqm.distributed.messages`)
on ``dqm/<job>/stream/images``; the stream adds every valid image to an
:class:`dqm.core.online.OnlineQuickMatch` and publishes what changed (a
``changes`` message per add or remove) on ``dqm/<job>/stream/changes``
(:mod:`dqm.distributed.keys`). The liveliness token ``dqm/<job>/alive/stream``
appears once the stream subscribes: a camera node waits for it before its first
put (zenoh loses puts made before the subscriber is known).

The shape follows the runtime's rules (docs/runtime.md): a zenoh client of one
router, a subscriber callback that only queues the payload, all work on the
main thread, puts with CongestionControl.BLOCK, and the session closed in
``finally``. A message that cannot be used -- undecodable, wrong version, kind
or job, non-finite or mis-shaped arrays, a dimension other than the stream's,
an image id received before, an image without features, anything ``add``
refuses -- is dropped and counted by reason (the reason is logged the first
few times), and the stream goes on.

:class:`StreamEngine` is the transport-free part (payload in, messages to
publish out); :func:`main_stream` is the zenoh shell around it.
"""
from __future__ import annotations

import queue
import re
import signal
import sys
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional

import numpy as np

from ..distributed import keys, messages
from ..validation import InputError

#: exit codes of ``dqm stream``: done (--images reached, idle, or nothing more to do), interrupted, terminated
EXIT_OK, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 130, 143
#: the reason of a rejected message is logged this many times, then only counted
LOG_PER_REASON = 3
#: seconds left for the last puts to leave before the session closes
LINGER_S = 0.3


def reason_key(reason: str) -> str:
    """A rejection reason as counted: numbers replaced by N (so that reasons group), at most 80 characters."""
    return re.sub(r"\d+", "N", str(reason).split("\n")[0])[:80]


@dataclass
class Output:
    """One change set to publish: the encoded ``changes`` message and what it describes."""

    payload: bytes
    op: str
    image_id: int
    camera: int
    changeset: object
    n_features: int
    n_clusters: int
    n_images: int
    seconds: float


@dataclass
class StreamEngine:
    """Online QuickMatch behind a message interface (no transport).

    :meth:`handle` takes one payload and returns the ``changes`` messages to
    publish, in order (with a window: the removal of the oldest image first,
    then the add); a bad payload returns nothing and is counted in
    :attr:`rejected` by reason.
    """

    job: str
    rho: float = 0.9
    window: Optional[int] = None
    max_bytes: int = messages.MAX_MESSAGE_BYTES
    log: Callable[[str], None] = lambda text: None
    src: int = 0
    rejected: Counter = field(default_factory=Counter)
    events: Counter = field(default_factory=Counter)
    accepted: int = 0
    removed_images: int = 0
    published: int = 0
    received: int = 0

    def __post_init__(self):
        from ..core.online import OnlineQuickMatch

        if self.window is not None and self.window < 1:
            raise InputError(f"--window must be at least 1 image, got {self.window}")
        self.om = OnlineQuickMatch(rho=self.rho, kernel="quadratic")
        self.dim: Optional[int] = None
        self.present: "OrderedDict[int, int]" = OrderedDict()  # image id -> camera, in arrival order
        self.seen: set = set()  # every image id ever accepted (a resent image is refused, even after removal)
        self.keypoints: Dict[int, np.ndarray] = {}  # image id -> keypoints (n, c) of its features (in add order)
        self._seq = 0

    # ------------------------------------------------------------------ rejections
    def reject(self, reason: str) -> None:
        key = reason_key(reason)
        self.rejected[key] += 1
        n = self.rejected[key]
        if n <= LOG_PER_REASON:
            more = " (further messages of this kind are only counted)" if n == LOG_PER_REASON else ""
            self.log(f"rejected a message: {reason}{more}")

    @property
    def n_rejected(self) -> int:
        return int(sum(self.rejected.values()))

    # ------------------------------------------------------------------ messages
    def handle(self, payload: bytes) -> List[Output]:
        """Decode, validate and apply one payload; the change sets to publish (none if it was refused)."""
        self.received += 1
        try:
            msg = messages.decode(payload, job=self.job, max_bytes=self.max_bytes, dim=self.dim)
        except messages.MessageError as exc:
            self.reject(str(exc))
            return []
        if msg["kind"] != "image":
            self.reject(f"a {msg['kind']} message on the images key (only image messages are accepted)")
            return []
        image = int(msg["image_id"])
        desc = msg["descriptors"]
        if image in self.seen:
            self.reject(f"image {image} was received before")
            return []
        if len(desc) == 0:
            self.reject(f"image {image} has no features")
            return []
        out: List[Output] = []
        if self.window is not None:
            while len(self.present) >= self.window:
                out.append(self._remove(next(iter(self.present)), msg["time"]))
        t0 = time.perf_counter()
        try:
            cs = self.om.add(desc, np.full(len(desc), image, np.int64))
        except InputError as exc:
            self.reject(str(exc))
            return out
        self.seen.add(image)
        self.present[image] = int(msg["src"])
        self.dim = int(desc.shape[1])
        if len(msg["keypoints"]):
            self.keypoints[image] = msg["keypoints"]
        self.accepted += 1
        out.append(self._output(cs, "add", image, int(msg["src"]), msg["time"], time.perf_counter() - t0))
        return out

    def _remove(self, image: int, sent: float) -> Output:
        t0 = time.perf_counter()
        cs = self.om.remove(image)
        camera = self.present.pop(image)
        self.keypoints.pop(image, None)
        self.removed_images += 1
        return self._output(cs, "remove", image, camera, sent, time.perf_counter() - t0)

    def n_clusters(self) -> int:
        return int(len(np.unique(np.asarray(self.om.cluster_ids)))) if self.om.n_features else 0

    def _output(self, cs, op: str, image: int, camera: int, sent: float, seconds: float) -> Output:
        for e in cs.events:
            self.events[e.kind] += 1
        n_features, n_clusters, n_images = int(self.om.n_features), self.n_clusters(), len(self.present)
        payload = messages.changes_message(self.job, cs, op, image, sent=sent, n_images=n_images,
                                           n_features=n_features, n_clusters=n_clusters, rejected=self.n_rejected,
                                           seq=self._seq, src=self.src)
        self._seq += 1
        self.published += 1
        return Output(payload, op, image, camera, cs, n_features, n_clusters, n_images, seconds)

    # ------------------------------------------------------------------ results
    def all_keypoints(self) -> Optional[np.ndarray]:
        """Keypoints of the present features in the online order, if every present image sent some
        (with the same number of columns); else None."""
        if not self.present or any(i not in self.keypoints for i in self.present):
            return None
        cols = {self.keypoints[i].shape[1] for i in self.present}
        if len(cols) != 1:
            return None
        ids = np.asarray(self.om.image_ids, np.int64)
        out = np.zeros((len(ids), cols.pop()), np.float32)
        for i in self.present:  # an image's features keep their order among the present features
            out[ids == i] = self.keypoints[i]
        return out

    def save(self, path) -> None:
        """Write the present features and their clusters as a CLUSTERS file (dqm.io.save_clusters)."""
        from .. import io

        fs = io.FeatureSet(np.asarray(self.om.descriptors), np.asarray(self.om.image_ids, np.int64),
                           keypoints=self.all_keypoints())
        extra = {"stream": True, "job": self.job, "window": self.window, "images_accepted": self.accepted,
                 "images_removed": self.removed_images}
        io.save_clusters(path, fs, self.om.result(), extra)

    def summary(self) -> List[str]:
        """The end-of-stream lines: images, features, clusters, rejected messages by reason, events by kind."""
        lines = [f"{self.accepted} images accepted ({len(self.present)} present, {self.removed_images} removed by "
                 f"the window), {self.om.n_features} features, {self.n_clusters()} clusters; "
                 f"{self.received} messages received, {self.published} change sets published"]
        if self.rejected:
            lines.append(f"rejected {self.n_rejected} messages: " + "; ".join(
                f"{r}: {n}" for r, n in sorted(self.rejected.items(), key=lambda kv: (-kv[1], kv[0]))))
        else:
            lines.append("rejected 0 messages")
        from ..core.events import EVENT_KINDS

        kinds = ", ".join(f"{self.events[k]} {k}" for k in EVENT_KINDS if self.events[k]) or "none"
        lines.append(f"events: {kinds}")
        return lines


# ---------------------------------------------------------------------- the zenoh shell
class _Stop:
    """Ctrl-C / SIGTERM set a flag (the current image is finished first); a second Ctrl-C interrupts."""

    def __init__(self):
        self.signal: Optional[int] = None

    def __call__(self, signum, frame):
        if self.signal == signal.SIGINT and signum == signal.SIGINT:
            raise KeyboardInterrupt
        self.signal = signum


def main_stream(endpoint: str, job: str, *, rho: float = 0.9, window: Optional[int] = None,
                max_images: Optional[int] = None, idle_s: Optional[float] = None, out: Optional[str] = None,
                lines: bool = False, tls: Optional[dict] = None, connect_timeout_s: float = 5.0,
                max_bytes: int = messages.MAX_MESSAGE_BYTES) -> int:
    """Entry point of ``dqm stream``; returns the exit code. Raises RouterUnreachable when no router answers."""
    import zenoh

    from .bus import open_client
    from .lifeline import watch_parent

    keys.check_job(job)
    log = lambda text: print(f"[stream] {text}", file=sys.stderr, flush=True)  # noqa: E731
    engine = StreamEngine(job, rho=rho, window=window, max_bytes=max_bytes, log=log)
    stop = _Stop()
    old = {s: signal.signal(s, stop) for s in (signal.SIGINT, signal.SIGTERM)}
    watch_parent()
    inbox: "queue.Queue" = queue.Queue()
    session = open_client(endpoint, tls, deadline_s=connect_timeout_s)
    sub = token = None
    why = "stopped"
    try:
        sub = session.declare_subscriber(keys.stream_images(job),
                                         lambda sample: inbox.put(bytes(sample.payload.to_bytes())))
        token = session.liveliness().declare_token(keys.alive_stream(job))
        log(f"listening on {keys.stream_images(job)}, publishing on {keys.stream_changes(job)}"
            + (f", window of {window} images" if window else ""))
        changes_key = keys.stream_changes(job)
        last = time.monotonic()
        while True:
            if stop.signal is not None:
                why = "interrupted" if stop.signal == signal.SIGINT else "terminated"
                break
            if max_images is not None and engine.accepted >= max_images:
                why = f"{engine.accepted} images accepted"
                break
            try:
                payload = inbox.get(timeout=0.1)
            except queue.Empty:
                if idle_s is not None and time.monotonic() - last >= idle_s:
                    why = f"no message for {idle_s:g} s"
                    break
                continue
            last = time.monotonic()
            for o in engine.handle(payload):
                session.put(changes_key, o.payload, congestion_control=zenoh.CongestionControl.BLOCK)
                if lines:
                    print(f"{o.op} image {o.image_id} (camera {o.camera}): {o.changeset.summary()}; now "
                          f"{o.n_features} features, {o.n_clusters} clusters in {o.n_images} images "
                          f"({o.seconds * 1e3:.0f} ms)", flush=True)
        time.sleep(LINGER_S)
    finally:
        for obj in (token, sub):
            if obj is not None:
                try:
                    obj.undeclare()
                except Exception:  # noqa: BLE001 - closing anyway
                    pass
        session.close()
        for s, h in old.items():
            signal.signal(s, h)
    unread = inbox.qsize()
    print(f"stream ({why}): " + engine.summary()[0], flush=True)
    for line in engine.summary()[1:]:
        print(f"  {line}", flush=True)
    if unread:
        print(f"  {unread} messages arrived after the stop and were not read", flush=True)
    if out:
        if engine.om.n_features:
            engine.save(out)
            print(f"wrote {out}", flush=True)
        else:
            print(f"no image accepted: {out} not written", flush=True)
    if stop.signal is not None:
        return EXIT_INTERRUPTED if stop.signal == signal.SIGINT else EXIT_TERMINATED
    return EXIT_OK
