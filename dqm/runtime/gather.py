"""Gather: every source sends its features to one host, which runs centralized QuickMatch.

The baseline that the distributed modes must beat on real links (``scripts/bench_hosts.py``):
sources put their features as ``gather`` messages (parts of at most 1 MiB, BLOCK congestion
control) on ``dqm/<job>/gather/from/<src>`` once the gathering host's liveliness token
(``dqm/<job>/alive/gather``) is present; the gathering host, itself source 0, takes its own
features from disk, waits until every part of every source is in (each part is checked like
every message, and the key must name the part's sender) and runs :func:`dqm.quickmatch` on the
whole set: the quadratic kernel by default, so that its clusters are the balanced mode's.

    python -m dqm.runtime.gather receive --sources 4 --connect tcp/R:7447 --job J --out r.json own.npz
    python -m dqm.runtime.gather send --id 2 --connect tcp/R:7447 --job J agent2.npz

Both exit 0 when done, 2 with one line on bad input or no router, 3 when the transfer does not
complete within --timeout.
"""
from __future__ import annotations

import argparse
import json
import queue
import sys
import time
from typing import Dict, List, Optional

import numpy as np

from ..distributed import keys, messages
from ..core.params import FINITE_KERNEL
from ..validation import InputError

#: rows of one ``gather`` part: at most about this many bytes of descriptors
PART_BYTES = 1 << 20


def _parts(n: int, row_bytes: int) -> List[slice]:
    rows = max(1, PART_BYTES // max(1, row_bytes))
    return [slice(i, min(n, i + rows)) for i in range(0, max(n, 1), rows)]


def send(session, job: str, me: int, features, wait_s: float = 60.0) -> int:
    """Put source ``me``'s features for the gathering host and wait until it has everything (its token
    goes away): a put returns once queued, and closing the session earlier would lose what is still
    in the queue of a slow link. Returns the bytes put (payload + key)."""
    import zenoh

    from .stream import TokenWatch

    watch = TokenWatch(session, keys.alive_gather(job))
    try:
        if not watch.wait(wait_s):
            raise TimeoutError(f"no gathering host of job {job!r} appeared within {wait_s:g} s "
                               f"({keys.alive_gather(job)})")
        sent = _put_parts(session, job, me, features, zenoh.CongestionControl.BLOCK)
        t0 = time.monotonic()
        while watch.present:
            if time.monotonic() - t0 > wait_s:
                raise TimeoutError(f"the gathering host of job {job!r} did not finish within {wait_s:g} s")
            time.sleep(0.05)
        return sent
    finally:
        watch.close()


def _put_parts(session, job: str, me: int, features, congestion) -> int:
    d = features.descriptors
    key = keys.gather_from(job, me)
    parts = _parts(len(d), d.shape[1] * d.itemsize + 16)
    sent = 0
    for k, sl in enumerate(parts):
        payload = messages.encode("gather", job, me, seq=k, part=k, parts=len(parts), ids=features.ids[sl],
                                  image_ids=features.image_ids[sl], descriptors=np.ascontiguousarray(d[sl]))
        session.put(key, payload, congestion_control=congestion)
        sent += len(payload) + len(key)
    return sent


class Gathering:
    """The gathering host's inbox: every part of every source, checked; :meth:`wait` until complete."""

    def __init__(self, session, job: str, sources: int, dim: Optional[int] = None):
        self.job, self.sources, self.dim = job, sources, dim
        self.inbox: "queue.Queue" = queue.Queue()
        self.parts: Dict[int, Dict[int, dict]] = {}
        self.expected: Dict[int, int] = {}
        self.bytes = 0
        self.rejected: List[str] = []
        self.sub = session.declare_subscriber(
            keys.gather_inbox(job), lambda s: self.inbox.put((str(s.key_expr), bytes(s.payload.to_bytes()))))
        self.token = session.liveliness().declare_token(keys.alive_gather(job))

    def _take(self, key: str, raw: bytes) -> None:
        sender = keys.gather_source_of_key(self.job, key)
        if sender is None:
            self.rejected.append(f"a message on {key}, which names no source")
            return
        try:
            msg = messages.decode(raw, job=self.job, agents=self.sources, dim=self.dim, sender=sender)
        except messages.MessageError as exc:
            self.rejected.append(str(exc))
            return
        if msg["kind"] != "gather" or sender == 0:
            self.rejected.append(f"a {msg['kind']} message of source {sender} on the gather key")
            return
        self.bytes += len(raw) + len(key)
        self.expected[sender] = msg["parts"]
        self.parts.setdefault(sender, {})[msg["part"]] = msg

    def complete(self) -> bool:
        return len(self.expected) == self.sources - 1 and all(
            len(self.parts[s]) == n for s, n in self.expected.items())

    def wait(self, timeout_s: float) -> None:
        t0 = time.monotonic()
        while not self.complete():
            left = timeout_s - (time.monotonic() - t0)
            if left <= 0:
                have = {s: f"{len(self.parts.get(s, {}))}/{self.expected.get(s, '?')}" for s in range(1, self.sources)}
                raise TimeoutError(f"gathering incomplete after {timeout_s:g} s: parts per source {have}")
            try:
                self._take(*self.inbox.get(timeout=min(0.2, left)))
            except queue.Empty:
                continue

    def features(self, own) -> tuple:
        """(ids, image_ids, descriptors) of every source, own first, then by source and part."""
        blocks = [(own.ids, own.image_ids, own.descriptors)]
        for s in sorted(self.parts):
            for k in sorted(self.parts[s]):
                m = self.parts[s][k]
                blocks.append((m["ids"], m["image_ids"], m["descriptors"]))
        return tuple(np.concatenate([b[i] for b in blocks]) for i in range(3))

    def close(self) -> None:
        for obj in (self.token, self.sub):
            obj.undeclare()


def _main(argv=None) -> int:
    from .agent import load_agent_features
    from .bus import RouterUnreachable, open_client

    p = argparse.ArgumentParser(prog="python -m dqm.runtime.gather", description=__doc__.split("\n\n")[0])
    p.add_argument("role", choices=["send", "receive"])
    p.add_argument("features", help="this source's FEATURES file")
    p.add_argument("--connect", required=True)
    p.add_argument("--job", default="gather")
    p.add_argument("--id", type=int, default=0, help="this source's index (the gathering host is 0)")
    p.add_argument("--sources", type=int, default=1, help="receive: the number of sources, itself included")
    p.add_argument("--out", help="receive: the result JSON (ids, labels, timings, bytes)")
    p.add_argument("--approximate", action="store_true", help="receive: approximate QuickMatch (faiss)")
    p.add_argument("--kernel", default=FINITE_KERNEL)
    p.add_argument("--timeout", type=float, default=600.0)
    args = p.parse_args(argv)
    t_start = time.monotonic()
    try:
        keys.check_job(args.job)
        me = 0 if args.role == "receive" else args.id
        if me < 0 or (args.role == "send" and me == 0):
            raise InputError("--id of a sending source must be 1 or more (0 is the gathering host)")
        own = load_agent_features([args.features], me)
        session = open_client(args.connect)
    except (InputError, RouterUnreachable, OSError, ValueError) as exc:
        print(f"gather: error: {exc}", file=sys.stderr)
        return 2
    try:
        if args.role == "send":
            sent = send(session, args.job, me, own, wait_s=args.timeout)
            print(json.dumps({"source": me, "bytes": sent, "features": len(own.ids)}))
            return 0
        import dqm

        g = Gathering(session, args.job, args.sources, dim=own.descriptors.shape[1])
        try:
            g.wait(args.timeout)
        finally:
            g.close()
        t_gathered = time.monotonic()
        ids, image_ids, X = g.features(own)
        r = dqm.quickmatch(X, image_ids, kernel=args.kernel, approximate=args.approximate)
        out = {"ids": ids.tolist(), "labels": r.labels.tolist(), "features": int(len(ids)),
               "bytes": g.bytes, "rejected": g.rejected, "gather_s": t_gathered - t_start,
               "match_s": time.monotonic() - t_gathered}
        if args.out:
            with open(args.out, "w") as fh:
                json.dump(out, fh)
        return 0
    except TimeoutError as exc:
        print(f"gather: error: {exc}", file=sys.stderr)
        return 3
    finally:
        session.close()


if __name__ == "__main__":
    sys.exit(_main())
