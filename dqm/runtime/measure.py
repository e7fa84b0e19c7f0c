"""What the coordinator of a ``--mode auto`` job measures before it picks a mode (docs/runtime.md):
the link rate to each agent process (timed ``probe`` messages) and the cores of its own host.

**Link rate.** The coordinator sends a process two probes of ``size`` filler bytes back to back; the
process answers each at once with a small probe of the same token. The first probe drains whatever
burst the links let through at once (a ``tc tbf`` bucket: at least 96 KiB in
:class:`dqm.runtime.multihost.EmulatedHosts`, 4 ms of traffic at higher rates), so the second crosses
at the sustained rate, and the gap between the two answers is ``size / rate``: latency and the
process's reaction time cancel. The coordinator asks for :data:`STAMP_BYTES` bytes in each answer,
and the process writes there the time its receiver decoded the probe (:func:`probe_answer`, its own
monotonic clock): the gap is taken between those two stamps, so that an answer queued behind the
next probe on a shared link (a process on the coordinator's own host) does not shorten it. A gap
under :data:`MIN_SPREAD_S` is too short to trust (a burst, a
fast link): the size grows to about :data:`TARGET_SPREAD_S` of traffic at the rate seen (at most
:data:`MAX_GROWTH` times, at most :data:`MAX_PROBE_BYTES`) and the pair is sent again. It starts at
:data:`START_PROBE_BYTES` (past a 96 KiB burst), and each process after the first at the size that
sufficed for the one before. About 0.1-0.2 s per process at 10 and 100 Mbit/s (a second or two for
8 processes) and at 1 Gbit/s, where 8 MiB pairs are sent; on loopback the rate is what zenoh and
the codec reach with 8 MiB. Sizes are powers of two and the coordinator gives every pair the tokens
1 and 2, so that it encodes each size once (:class:`ProbeEncoder`).

**Cores.** :func:`host_cores` reads the CPU affinity and the cgroup quota of this process. A process
started with ``ip netns exec`` (the emulated hosts) sees no cgroup file system, so there the caller
says the cores (``dqm coordinator --host-cores / --gather-cores``).

The rate is that of the path coordinator -> router -> process (the slower of the coordinator's link
and the process's), one direction; links are taken as symmetric. A process on the coordinator's own
host, whose path crosses the coordinator's link twice, can read high with small probes (on the
emulated hosts at 10 Mbit/s, 15 Mbit/s with a 128 KiB pair, 10.2 with 512 KiB; right at 100 Mbit/s):
the TCP acknowledgements of its side queue behind the next probe on the shared link and hold back
the end of the first. The cost model therefore takes the median rate, not the best, for the
coordinator's link.
"""
from __future__ import annotations

import logging
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Optional, Tuple

import numpy as np

LOG = logging.getLogger("dqm.runtime")

#: the first probe pair's size: past the smallest tc tbf burst of the emulated hosts (96 KiB)
START_PROBE_BYTES = 128 << 10
#: the largest probe (a pair moves twice this)
MAX_PROBE_BYTES = 8 << 20
#: the least gap between a pair's answers that is taken as a measurement (unless at the largest size)
MIN_SPREAD_S = 0.04
#: the gap a grown probe aims at
TARGET_SPREAD_S = 0.06
#: the most a probe grows from one pair to the next (a pair inside a burst shows a rate far too high)
MAX_GROWTH = 8
#: most pairs per process
MAX_ROUNDS = 5
#: how long one probe's answer may take
PROBE_TIMEOUT_S = 15.0
#: the bytes the coordinator asks for in a probe's answer: the process's receive time (float64, little-endian)
STAMP_BYTES = 8


@dataclass(frozen=True)
class LinkRate:
    """One process's measured link: ``bytes_s`` (bytes per second), the probe size of the pair that
    measured it, the pairs sent, the seconds the measurement took, the filler bytes sent, and every
    pair's (size, gap between its answers, time from its first put to its second answer) in seconds."""

    process: int
    bytes_s: float
    probe_bytes: int
    rounds: int
    seconds: float
    bytes_sent: int
    pairs: Tuple[Tuple[int, float, float], ...] = ()
    #: ``bytes_s`` is only a lower bound: a pair read at least the ``enough_bytes_s`` asked for
    at_least: bool = False


def probe_answer(nbytes: int, received: float) -> np.ndarray:
    """The ``data`` of a process's answer to a probe that asks for ``nbytes``: filler whose first
    :data:`STAMP_BYTES` bytes (when it has that many) are ``received``, the time (the process's monotonic
    clock) the probe was decoded."""
    data = filler(nbytes)
    if nbytes >= STAMP_BYTES:
        data[:STAMP_BYTES] = np.frombuffer(np.array([received], "<f8").tobytes(), np.uint8)
    return data


def answer_stamp(data: np.ndarray) -> Optional[float]:
    """The receive time an answer's ``data`` carries (:func:`probe_answer`), or None (too short, not finite)."""
    if len(data) < STAMP_BYTES:
        return None
    t = float(np.frombuffer(np.ascontiguousarray(data[:STAMP_BYTES]).tobytes(), "<f8")[0])
    return t if math.isfinite(t) else None


class ProbeEncoder:
    """The coordinator's probe payloads, encoded once per (token, size): the filler does not compress,
    and trying to compress megabytes at every pair would cost a slow host more than the pair's traffic.
    ``encode(token, nbytes)`` calls ``make(token, filler_bytes)`` once for each pair of arguments."""

    def __init__(self, make: Callable[[int, np.ndarray], bytes]):
        self.make = make
        self.data = filler(MAX_PROBE_BYTES)
        self.cache: dict = {}

    def encode(self, token: int, nbytes: int) -> bytes:
        key = (token, int(nbytes))
        if key not in self.cache:
            self.cache[key] = self.make(token, self.data[:nbytes])
        return self.cache[key]


def filler(nbytes: int) -> np.ndarray:
    """``nbytes`` bytes of probe filler (pseudo-random: no link compression shortens them)."""
    return np.random.default_rng(nbytes).integers(0, 256, size=int(nbytes), dtype=np.uint8)


def measure_link(process: int, send_pair: Callable[[int, int, int, int], None],
                 await_reply: Callable[[int, float], float], tokens, clock: Callable[[], float],
                 start_bytes: int = START_PROBE_BYTES, enough_bytes_s: Optional[float] = None) -> LinkRate:
    """Measure the rate to ``process`` with probe pairs (module doc).

    ``enough_bytes_s``: a rate at which the caller needs no finer reading (where the mode is settled above some
    rate). Each pair also gives a lower bound of the sustained rate: its two probes (``2 size`` bytes) have
    crossed the link between the first put and the second answer's arrival (``clock``), so the rate is at least
    ``(2 size - burst) / elapsed``, and at least ``size / elapsed`` for any burst up to one probe's size
    (latency and the process's reaction only lower it). A pair whose bound reaches ``enough_bytes_s`` ends
    the measurement with that bound (``at_least``), however short the gap between its answers.

    ``send_pair(process, token_a, token_b, nbytes)`` puts two probes of ``nbytes`` filler bytes back to
    back (both encoded before the first put: the link must not wait for the second);
    ``await_reply(token, timeout_s)`` returns the time (``clock``) its answer arrived, or raises;
    ``tokens`` yields the pairs' tokens (they may repeat from pair to pair: every answer is awaited before
    the next pair goes). ``start_bytes``: the first pair's size."""
    t0 = clock()
    size = int(min(MAX_PROBE_BYTES, max(START_PROBE_BYTES, start_bytes)))
    sent = 0
    pairs = []
    for rounds in range(1, MAX_ROUNDS + 1):
        a, b = next(tokens), next(tokens)
        t_sent = clock()
        send_pair(process, a, b, size)
        sent += 2 * size
        ta = await_reply(a, PROBE_TIMEOUT_S)
        tb = await_reply(b, PROBE_TIMEOUT_S)
        elapsed = max(clock() - t_sent, 1e-6)
        bound = size / elapsed
        spread = max(tb - ta, 1e-6)
        pairs.append((size, round(spread, 6), round(elapsed, 6)))
        if enough_bytes_s is not None and bound >= enough_bytes_s:
            LOG.debug("link to process %d: at least %.3g MB/s from %d probe pairs (last %d bytes)", process,
                      bound / 1e6, rounds, size)
            return LinkRate(process, bound, size, rounds, clock() - t0, sent, tuple(pairs), at_least=True)
        if spread >= MIN_SPREAD_S or size >= MAX_PROBE_BYTES or rounds == MAX_ROUNDS:
            LOG.debug("link to process %d: %.3g MB/s from %d probe pairs (last %d bytes)", process,
                      size / spread / 1e6, rounds, size)
            return LinkRate(process, size / spread, size, rounds, clock() - t0, sent, tuple(pairs))
        seen = size / spread
        size = int(min(MAX_PROBE_BYTES, MAX_GROWTH * size, max(2 * size, power_of_two(seen * TARGET_SPREAD_S))))
    raise AssertionError("unreachable")  # pragma: no cover


def power_of_two(nbytes: float) -> int:
    """The power of two nearest ``nbytes`` (on a log scale): probe sizes repeat, so that their encodings can be
    kept and sent again."""
    return 1 << max(0, int(round(math.log2(max(1.0, nbytes)))))


def next_start_bytes(rate: LinkRate) -> int:
    """The first probe size for the next process: what the last one needed (a power of two; a lower bound
    needed the size it was read with)."""
    if rate.at_least:
        return rate.probe_bytes
    return int(min(MAX_PROBE_BYTES, max(START_PROBE_BYTES, power_of_two(rate.bytes_s * TARGET_SPREAD_S))))


def _cgroup_quota(root: Path = Path("/sys/fs/cgroup"), cgroup_file: Path = Path("/proc/self/cgroup")
                  ) -> Optional[float]:
    """Cores this process's CPU cgroup allows (the least along its path; v1 ``cpu.cfs_quota_us`` /
    ``cpu.cfs_period_us`` or v2 ``cpu.max``), or None without a limit or a readable cgroup."""
    try:
        lines = cgroup_file.read_text().splitlines()
    except OSError:
        return None
    best: Optional[float] = None
    for line in lines:
        parts = line.split(":", 2)
        if len(parts) != 3:
            continue
        _, controllers, path = parts
        names = controllers.split(",")
        if controllers == "":  # v2: one unified hierarchy
            bases, files = [root], ("cpu.max",)
        elif "cpu" in names:
            bases, files = [root / controllers, root / "cpu"], ("cpu.cfs_quota_us",)
        else:
            continue
        for base in bases:
            if not base.is_dir():
                continue
            d = base / path.lstrip("/")
            while True:
                quota = _read_quota(d, files[0])
                if quota is not None:
                    best = quota if best is None else min(best, quota)
                if d == base or base not in d.parents:
                    break
                d = d.parent
            break
    return best


def _read_quota(d: Path, name: str) -> Optional[float]:
    try:
        if name == "cpu.max":
            quota, _, period = (d / name).read_text().strip().partition(" ")
            return None if quota == "max" else int(quota) / int(period or 100000)
        quota = int((d / "cpu.cfs_quota_us").read_text())
        period = int((d / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 or period <= 0 else quota / period
    except (OSError, ValueError):
        return None


def host_cores() -> float:
    """The cores this process may use: its CPU affinity, capped by its cgroup's CPU quota (a container,
    an emulated host of :class:`dqm.runtime.multihost.EmulatedHosts`)."""
    try:
        cores = float(len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        cores = float(os.cpu_count() or 1)
    quota = _cgroup_quota()
    if quota is not None and math.isfinite(quota) and quota > 0:
        cores = min(cores, quota)
    return cores
