"""Gather: every source sends its features to one host, which runs centralized QuickMatch.

Two users share the gather of :mod:`dqm.distributed.gathering` (the payload, the parts, the match):
the stand-alone baseline that the distributed modes must beat on
real links (``scripts/bench_hosts.py``, the command lines below) and agent 0 of a ``dqm run`` job in
``--mode gather`` (or ``auto`` when it picks gather), to which the other agents send the same ``gather``
messages (:class:`dqm.distributed.gathering.GatherDriver`).

* :func:`gather_payload`: one source's ``gather`` payload (sent in parts of at most 1 MiB by
  :func:`dqm.distributed.protocol.data_messages`, merged by :func:`dqm.distributed.protocol.merge_parts`);
* :class:`GatheredParts`: the parts received per source, their completeness, the features by id;
* :func:`match_gathered`: :func:`dqm.quickmatch` on the gathered features in feature-id order, labels
  numbered canonically (as :func:`dqm.distributed.sources.assemble_labels` numbers a distributed job's):
  with the quadratic kernel the balanced mode's labels exactly.

Stand-alone, sources put their parts (BLOCK congestion control) on ``dqm/<job>/gather/from/<src>``
once the gathering host's liveliness token (``dqm/<job>/alive/gather``) is present; the gathering host,
itself source 0, takes its own features from disk, waits until every part of every source is in (each
part is checked like every message, and the key must name the part's sender) and matches the whole set:
the quadratic kernel by default, so that its clusters are the balanced mode's.

    python -m dqm.runtime.gather receive --sources 4 --connect tcp/R:7447 --job J --out r.json own.npz
    python -m dqm.runtime.gather send --id 2 --connect tcp/R:7447 --job J agent2.npz

Both exit 0 when done, 2 with one line on bad input or no router, 3 when the transfer does not
complete within --timeout.
"""
from __future__ import annotations

import argparse
import json
import logging
import queue
import sys
import time
from typing import List, Optional

from ..core.params import FINITE_KERNEL, QuickMatchParams
from ..distributed import keys, messages, protocol
from ..distributed.config import DISTRIBUTED_ENGINES
from ..distributed.gathering import GatheredParts, gather_payload, match_gathered
from ..validation import InputError

LOG = logging.getLogger("dqm.runtime")


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
        key = keys.gather_from(job, me)
        sent = 0
        whole = gather_payload(features.ids, features.image_ids, features.descriptors)
        for part in protocol.data_messages("gather", job, me, whole):
            session.put(key, part, congestion_control=zenoh.CongestionControl.BLOCK)
            sent += len(part) + len(key)
        LOG.info("source %d: %d features put for the gathering host of job %s (%d bytes)", me, len(features.ids),
                 job, sent)
        t0 = time.monotonic()
        while watch.present:
            if time.monotonic() - t0 > wait_s:
                raise TimeoutError(f"the gathering host of job {job!r} did not finish within {wait_s:g} s")
            time.sleep(0.05)
        return sent
    finally:
        watch.close()


class Gathering:
    """The stand-alone gathering host's inbox (it is source 0): every part of sources 1 .. ``sources - 1``
    on the gather keys, checked; :meth:`wait` until complete."""

    def __init__(self, session, job: str, sources: int, dim: Optional[int] = None):
        self.job, self.sources, self.dim = job, sources, dim
        self.inbox: "queue.Queue" = queue.Queue()
        self.gathered = GatheredParts(range(1, sources))
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
            LOG.warning("gathering: rejected a message on %s: %s", key, exc)
            self.rejected.append(str(exc))
            return
        if msg["kind"] != "gather" or sender == 0:
            LOG.warning("gathering: rejected a %s message of source %d on the gather key", msg["kind"], sender)
            self.rejected.append(f"a {msg['kind']} message of source {sender} on the gather key")
            return
        self.bytes += len(raw) + len(key)
        self.gathered.take(msg)

    def complete(self) -> bool:
        return self.gathered.complete()

    def wait(self, timeout_s: float) -> None:
        t0 = time.monotonic()
        while not self.complete():
            left = timeout_s - (time.monotonic() - t0)
            if left <= 0:
                raise TimeoutError(f"gathering incomplete after {timeout_s:g} s: parts per source "
                                   f"{self.gathered.progress()}")
            try:
                self._take(*self.inbox.get(timeout=min(0.2, left)))
            except queue.Empty:
                continue

    def features(self, own) -> tuple:
        """(ids, image_ids, descriptors) of every source, its own included, ordered by feature id."""
        return self.gathered.features(own)

    def close(self) -> None:
        for obj in (self.token, self.sub):
            obj.undeclare()


def _main(argv=None) -> int:
    from ..distributed.sources import load_agent_features
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
    p.add_argument("--engine", default="exact", choices=DISTRIBUTED_ENGINES,
                   help="receive: dqm.quickmatch's engine (a distributed job's --engine)")
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
        g = Gathering(session, args.job, args.sources, dim=own.descriptors.shape[1])
        try:
            g.wait(args.timeout)
        finally:
            g.close()
        t_gathered = time.monotonic()
        ids, labels = match_gathered(*g.features(own), QuickMatchParams(kernel=args.kernel),
                                     approximate=args.approximate, engine=args.engine)
        out = {"ids": ids.tolist(), "labels": labels.tolist(), "features": int(len(ids)),
               "bytes": g.bytes, "rejected": g.rejected, "gather_s": t_gathered - t_start,
               "match_s": time.monotonic() - t_gathered}
        if args.out:
            with open(args.out, "w") as fh:
                json.dump(out, fh)
        return 0
    except TimeoutError as exc:
        print(f"gather: error: {exc}", file=sys.stderr)
        return 3
    except ValueError as exc:  # the sources' features do not fit together
        print(f"gather: error: {exc}", file=sys.stderr)
        return 2
    finally:
        session.close()


if __name__ == "__main__":
    sys.exit(_main())
