"""``dqm stream``: online QuickMatch fed by camera nodes over zenoh.

Camera nodes put ``image`` messages (one image each; :mod:`dqm.distributed.messages`)
on ``dqm/<job>/stream/images/from/<camera>``; the stream adds every valid image to an
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

The camera node's side (``dqm camera``) is here too: :func:`main_camera` waits
for the stream's token (:class:`TokenWatch`, :func:`wait_for_token`) and puts
one ``image`` message per frame at a given rate, with image ids namespaced by
camera (:func:`camera_image_id`: camera * 10^9 + the node's image number).
"""
from __future__ import annotations

import contextlib
import logging
import queue
import re
import signal
import sys
import threading
import time
from collections import Counter, OrderedDict
from dataclasses import dataclass, field
from typing import Callable, Dict, Iterable, List, Optional, Tuple

import numpy as np

from .. import signals
from ..core.clustering import DEFAULT_RHO
from ..distributed import keys, messages
from ..validation import InputError
from ..wording import count

#: exit code of ``dqm stream``: done (--images reached, idle, or nothing more to do); 130 / 143: dqm.signals
EXIT_OK = 0
#: the reason of a rejected message is logged this many times, then only counted
LOG_PER_REASON = 3
#: seconds left for the last puts to leave before the session closes
LINGER_S = 0.3
#: the camera node's notes (waiting for the stream, the stream gone or back): info level
LOG = logging.getLogger("dqm.runtime")


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
    name: str
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
    rho: float = DEFAULT_RHO
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
        self.names: Dict[int, str] = {}  # image id -> the name it came with ("" = none), while present
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
    def handle(self, payload: bytes, key: Optional[str] = None) -> List[Output]:
        """Decode, validate and apply one payload; the change sets to publish (none if it was refused).
        ``key``: the key it came on, which names the camera node that may send it
        (:func:`keys.camera_images`); an image of another camera is refused."""
        self.received += 1
        try:
            msg = messages.decode(payload, job=self.job, max_bytes=self.max_bytes, dim=self.dim)
        except messages.MessageError as exc:
            self.reject(str(exc))
            return []
        if msg["kind"] != "image":
            self.reject(f"a {msg['kind']} message on the images key (only image messages are accepted)")
            return []
        if key is not None and keys.camera_of_key(self.job, key) != msg["src"]:
            self.reject(f"an image of camera {msg['src']} on the key {key}, which names another camera")
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
        self.names[image] = msg["name"]
        if len(msg["keypoints"]):
            self.keypoints[image] = msg["keypoints"]
        self.accepted += 1
        out.append(self._output(cs, "add", image, int(msg["src"]), msg["time"], time.perf_counter() - t0,
                                msg["name"]))
        return out

    def _remove(self, image: int, sent: float) -> Output:
        t0 = time.perf_counter()
        cs = self.om.remove(image)
        camera = self.present.pop(image)
        self.keypoints.pop(image, None)
        name = self.names.pop(image, "")
        self.removed_images += 1
        return self._output(cs, "remove", image, camera, sent, time.perf_counter() - t0, name)

    def n_clusters(self) -> int:
        return int(len(np.unique(np.asarray(self.om.cluster_ids)))) if self.om.n_features else 0

    def _output(self, cs, op: str, image: int, camera: int, sent: float, seconds: float, name: str) -> Output:
        for e in cs.events:
            self.events[e.kind] += 1
        n_features, n_clusters, n_images = int(self.om.n_features), self.n_clusters(), len(self.present)
        payload = messages.changes_message(self.job, cs, op, image, sent=sent, n_images=n_images,
                                           n_features=n_features, n_clusters=n_clusters, rejected=self.n_rejected,
                                           seq=self._seq, src=self.src, name=name)
        self._seq += 1
        self.published += 1
        return Output(payload, op, image, camera, name, cs, n_features, n_clusters, n_images, seconds)

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

    def all_names(self) -> Optional[np.ndarray]:
        """Names of the present images in arrival order, if every present image came with one; else None."""
        names = [self.names.get(i, "") for i in self.present]
        return np.array(names) if names and all(names) else None

    def file_image_ids(self) -> np.ndarray:
        """Image ids of the present features as the CLUSTERS file numbers them: 0..K-1, the present images in
        arrival order (the stream's own ids are in the file's params, ``stream_image_ids``)."""
        ids = np.asarray(self.om.image_ids, np.int64)
        if not len(ids):
            return ids
        rank = {image: k for k, image in enumerate(self.present)}
        uniq, inverse = np.unique(ids, return_inverse=True)
        return np.array([rank[int(i)] for i in uniq], np.int64)[inverse.ravel()]

    def save(self, path) -> None:
        """Write the present features and their clusters as a CLUSTERS file (dqm.io.save_clusters).

        Image ids are renumbered 0..K-1 (the present images in arrival order), as the format wants
        ``image_names`` row k to name image id k; params ``stream_image_ids`` lists the stream's id of each.
        ``image_names`` and ``keypoints`` are written when every present image sent them."""
        from .. import io

        fs = io.FeatureSet(np.asarray(self.om.descriptors), self.file_image_ids(), keypoints=self.all_keypoints(),
                           image_names=self.all_names())
        extra = {"stream": True, "job": self.job, "window": self.window, "images_accepted": self.accepted,
                 "images_removed": self.removed_images, "stream_image_ids": [int(i) for i in self.present]}
        io.save_clusters(path, fs, self.om.result(), extra)

    def summary(self) -> List[str]:
        """The end-of-stream lines: images, features, clusters, rejected messages by reason, events by kind."""
        lines = [f"{count(self.accepted, 'image')} accepted ({len(self.present)} present, {self.removed_images} "
                 f"removed by the window), {self.om.n_features} features, {self.n_clusters()} clusters; "
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
def main_stream(endpoint: str, job: str, *, rho: float = DEFAULT_RHO, window: Optional[int] = None,
                max_images: Optional[int] = None, idle_s: Optional[float] = None, out: Optional[str] = None,
                lines: bool = False, tls: Optional[dict] = None, connect_timeout_s: float = 5.0,
                max_bytes: int = messages.MAX_MESSAGE_BYTES) -> int:
    """Entry point of ``dqm stream``; returns the exit code. Raises RouterUnreachable when no router answers."""
    import zenoh

    from .bus import JobIdInUse, check_job_free, check_token_admitted, identity_of, open_client
    from .lifeline import watch_parent
    from .roster import Identity

    keys.check_job(job)

    def log(text: str) -> None:
        print(f"[stream] {text}", file=sys.stderr, flush=True)

    engine = StreamEngine(job, rho=rho, window=window, max_bytes=max_bytes, log=log)
    stop = signals.StopFlag()  # Ctrl-C / SIGTERM: the current image is finished first
    old = stop.install()
    watch_parent()
    inbox: "queue.Queue" = queue.Queue()
    try:
        session = open_client(endpoint, tls, deadline_s=connect_timeout_s, check_stop=stop.check)
    except BaseException:  # unreachable, or a signal while connecting (raised as the default handlers would)
        signals.restore(old)
        raise
    try:  # a second stream under this job id would split the cameras' images between two
        check_job_free(session, keys.alive_stream(job), "the stream", job, endpoint)
    except JobIdInUse:
        signals.restore(old)
        raise
    sub = token = None
    why = "stopped"
    try:
        sub = session.declare_subscriber(keys.stream_images(job),
                                         lambda sample: inbox.put((str(sample.key_expr),
                                                                   bytes(sample.payload.to_bytes()))))
        token = session.liveliness().declare_token(keys.alive_stream(job))
        check_token_admitted(endpoint, tls, keys.alive_stream(job), f"the stream of job {job!r}",
                             Identity("stream", identity_of(tls) or "NAME").as_line(), job)
        log(f"listening on {keys.stream_images(job)}, publishing on {keys.stream_changes(job)}"
            + (f", window of {window} images" if window else ""))
        changes_key = keys.stream_changes(job)
        last = time.monotonic()
        while True:
            if stop:
                why = "interrupted" if stop.signal == signal.SIGINT else "terminated"
                break
            if max_images is not None and engine.accepted >= max_images:
                why = f"{count(engine.accepted, 'image')} accepted"
                break
            try:
                key, payload = inbox.get(timeout=0.1)
            except queue.Empty:
                if idle_s is not None and time.monotonic() - last >= idle_s:
                    why = f"no message for {idle_s:g} s"
                    break
                continue
            last = time.monotonic()
            for o in engine.handle(payload, key):
                session.put(changes_key, o.payload, congestion_control=zenoh.CongestionControl.BLOCK)
                if lines:
                    named = f", {o.name}" if o.name else ""
                    print(f"{o.op} image {o.image_id} (camera {o.camera}{named}): {o.changeset.summary()}; now "
                          f"{o.n_features} features, {o.n_clusters} clusters in {count(o.n_images, 'image')} "
                          f"({o.seconds * 1e3:.0f} ms)", flush=True)
        time.sleep(LINGER_S)
    finally:
        for obj in (token, sub):
            if obj is not None:
                with contextlib.suppress(Exception):  # closing anyway
                    obj.undeclare()
        session.close()
        signals.restore(old)
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
    if stop:
        return stop.exit_code()
    return EXIT_OK


# ---------------------------------------------------------------------- camera nodes
#: a camera node numbers its images k = 0, 1, ...; image id = camera * IMAGES_PER_CAMERA + k, so that the
#: ids of several cameras on one stream never collide (camera 2's image 17 is 2000000017)
IMAGES_PER_CAMERA = 10 ** 9
#: the largest camera id (every image id then fits in an int64)
MAX_CAMERA = 2 ** 31 - 1
#: exit code of ``dqm camera`` when the stream went away and did not come back
EXIT_STREAM_LOST = 1


def camera_image_id(camera: int, index: int) -> int:
    """The image id of camera ``camera``'s image number ``index`` (both >= 0): ``camera * 10^9 + index``."""
    if not 0 <= camera <= MAX_CAMERA:
        raise InputError(f"camera id must be 0..{MAX_CAMERA}, got {camera}")
    if not 0 <= index < IMAGES_PER_CAMERA:
        raise InputError(f"image number must be 0..{IMAGES_PER_CAMERA - 1}, got {index}")
    return int(camera) * IMAGES_PER_CAMERA + int(index)


def split_image_id(image_id: int) -> Tuple[int, int]:
    """``(camera, index)`` of an image id made by :func:`camera_image_id`."""
    return int(image_id) // IMAGES_PER_CAMERA, int(image_id) % IMAGES_PER_CAMERA


class TokenWatch:
    """Whether a liveliness token (e.g. the stream's, ``keys.alive_stream``) is present now.

    A liveliness subscriber with history keeps :attr:`present` up to date (a token declared before the
    watch counts); its callback only sets or clears an event. :meth:`close` undeclares it (before the
    session closes)."""

    def __init__(self, session, key: str):
        import zenoh

        self._put = zenoh.SampleKind.PUT
        self._present = threading.Event()
        self._sub = session.liveliness().declare_subscriber(key, self._on_sample, history=True)

    def _on_sample(self, sample) -> None:
        if sample.kind == self._put:
            self._present.set()
        else:
            self._present.clear()

    @property
    def present(self) -> bool:
        """Whether the token is present now."""
        return self._present.is_set()

    def wait(self, timeout_s: float, stop: Optional[Callable[[], bool]] = None) -> bool:
        """Whether the token is present within ``timeout_s`` seconds (False at once when ``stop()`` says so)."""
        deadline = time.monotonic() + timeout_s
        while not self._present.is_set():
            left = deadline - time.monotonic()
            if left <= 0 or (stop is not None and stop()):
                return False
            self._present.wait(min(0.1, left))
        return True

    def close(self) -> None:
        """Undeclare the subscriber (errors ignored: the session closes anyway)."""
        with contextlib.suppress(Exception):
            self._sub.undeclare()


def wait_for_token(session, key: str, deadline_s: float) -> bool:
    """Whether the liveliness token ``key`` appeared within ``deadline_s`` seconds."""
    watch = TokenWatch(session, key)
    try:
        return watch.wait(deadline_s)
    finally:
        watch.close()


class StreamUnavailable(RuntimeError):
    """No ``dqm stream`` of the job answered (its liveliness token did not appear in time)."""


@dataclass
class Frame:
    """One image as a camera node sends it: its name ("" = none), descriptors and keypoints (n x 2..4 or None)."""

    name: str
    descriptors: np.ndarray
    keypoints: Optional[np.ndarray] = None


@dataclass
class CameraReport:
    """What a camera node did: images put (their ids), puts behind their slot, why it stopped, seconds."""

    camera: int
    sent: List[int] = field(default_factory=list)
    late: int = 0
    why: str = "done"
    seconds: float = 0.0

    def summary(self, job: str, rate: float) -> str:
        """One line: images put, their ids, the rate, how many were behind their slot."""
        ids = f" (ids {self.sent[0]}..{self.sent[-1]})" if self.sent else ""
        return (f"camera {self.camera} ({self.why}): put {len(self.sent)} images{ids} to job {job!r} at "
                f"{rate:g} Hz in {self.seconds:.1f} s; {self.late} behind their slot")


def _sleep_until(t: float, stop: signals.StopFlag) -> None:
    """Sleep until monotonic time ``t`` in short slices, returning early once a stop signal came."""
    while stop.signal is None:
        left = t - time.monotonic()
        if left <= 0:
            return
        time.sleep(min(0.05, left))


def main_camera(endpoint: str, job: str, camera: int, frames: Iterable[Frame], *, rate: float,  # noqa: C901 - one process's life
                first_index: int = 0, tls: Optional[dict] = None, connect_timeout_s: float = 5.0,
                wait_s: float = 30.0, progress: Optional[Callable[[int], None]] = None,
                lines: bool = False) -> int:
    """Entry point of ``dqm camera``: put one ``image`` message per frame at ``rate`` Hz; the exit code.

    Waits up to ``wait_s`` seconds for the stream's liveliness token (else raises StreamUnavailable), then
    puts frame k at ``k / rate`` seconds after the first was ready (frames are taken from ``frames`` -- where
    the SIFT runs -- before their slot; a frame ready after its slot is put at once and counted late), as image
    ``camera_image_id(camera, first_index + k)`` with ``seq`` its number. Before a put it checks the
    token: a stream gone for ``wait_s`` seconds ends the node (exit 1). Ctrl-C / SIGTERM stop it after the
    current image (exit 130 / 143; a second Ctrl-C at once). Raises RouterUnreachable when no router answers.
    ``progress(images put)`` is called after every put; ``lines``: a line per image on standard output.
    """
    import zenoh

    from .bus import check_put_admitted, identity_of, open_client
    from .lifeline import watch_parent
    from .roster import Identity

    keys.check_job(job)
    if not (0 < rate < float("inf")):
        raise InputError(f"--rate must be a positive number of images per second, got {rate}")
    camera_image_id(camera, first_index)
    report = CameraReport(camera)
    stop = signals.StopFlag()  # Ctrl-C / SIGTERM: the current image is finished first
    old = stop.install()
    watch_parent()

    def stopped() -> bool:
        return bool(stop)

    lost = ""
    t_start = time.monotonic()
    try:
        session = open_client(endpoint, tls, deadline_s=connect_timeout_s, check_stop=stop.check)
        watch = None
        try:
            line = Identity("camera", identity_of(tls) or "NAME", camera).as_line()
            check_put_admitted(session, endpoint, tls, keys.camera_probe(job, camera),
                               f"camera {camera} of job {job!r}", line, job)
            watch = TokenWatch(session, keys.alive_stream(job))
            if not watch.wait(min(0.5, wait_s), stopped) and not stopped():
                LOG.info("waiting up to %g s for the stream of job %r (its token %s)", wait_s, job,
                         keys.alive_stream(job))
            if not watch.wait(wait_s, stopped) and not stopped():
                raise StreamUnavailable(
                    f"no dqm stream of job {job!r} at {endpoint} within {wait_s:g} s (its liveliness token "
                    f"{keys.alive_stream(job)} did not appear); start `dqm stream --connect {endpoint} --job {job}` "
                    f"first, or wait longer with --wait" + (
                        f"; under access control the router's roster must also hold the line "
                        f"'{line}' (and 'job {job}' "
                        "if it has job lines), else the stream's token is hidden from this node" if tls else ""))
            key = keys.camera_images(job, camera)
            t0 = 0.0
            for k, frame in enumerate(() if stopped() else frames):
                if k == 0:
                    t0 = time.monotonic()  # the schedule starts when the first image is ready
                slot = t0 + k / rate
                if time.monotonic() > slot + 1e-3:
                    report.late += 1
                _sleep_until(slot, stop)
                if stopped():
                    break
                if not watch.present:
                    LOG.info("the stream of job %r went away; waiting up to %g s for it", job, wait_s)
                    if watch.wait(wait_s, stopped):
                        LOG.info("the stream of job %r is back", job)
                if not watch.present:
                    if not stopped():
                        lost = (f"the stream of job {job!r} went away and did not come back within {wait_s:g} s; "
                                f"stopped after {count(len(report.sent), 'image')}")
                    break
                image_id = camera_image_id(camera, first_index + k)
                payload = messages.image_message(job, camera, image_id, frame.descriptors, frame.keypoints,
                                                 seq=first_index + k, name=frame.name)
                session.put(key, payload, congestion_control=zenoh.CongestionControl.BLOCK)
                report.sent.append(image_id)
                LOG.debug("put image %d (%d features, %d bytes)", image_id, len(frame.descriptors), len(payload))
                if lines:
                    print(f"image {image_id}" + (f" ({frame.name})" if frame.name else "")
                          + f": {len(frame.descriptors)} features, {len(payload)} bytes", flush=True)
                if progress is not None:
                    progress(len(report.sent))
                if stopped():
                    break
            time.sleep(LINGER_S)  # the last puts leave before the session closes
        finally:
            if watch is not None:
                watch.close()
            session.close()
    finally:
        signals.restore(old)
    report.seconds = time.monotonic() - t_start
    if stop.signal is not None:
        report.why = "interrupted" if stop.signal == signal.SIGINT else "terminated"
    elif lost:
        report.why = "stream lost"
    print(report.summary(job, rate), flush=True)
    if lost:
        print(f"dqm camera: error: {lost}", file=sys.stderr, flush=True)
        return EXIT_STREAM_LOST
    if stop:
        return stop.exit_code()
    return EXIT_OK
