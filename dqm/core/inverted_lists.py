"""The fast engine: QuickMatch's pass over the pairs that matter, found by inverted lists.

The exact pass computes every pair of features (n^2 / 2 distances and two
kernel terms each). On photo SIFT nearly all of a feature's density and every
candidate parent come from its near neighbourhood, so the fast engine computes
only pairs of nearby features (a float32 GEMM, or on uint8 descriptors the
integer VNNI kernel where the CPU has it, and a native tile kernel per block,
as the exact pass):

1. **Lists.** k-means on a seeded sample gives ``n_lists`` centroids (about
   ``1.25 sqrt(n)``, a power of two); every feature belongs to the list of its
   nearest centroid, and scans its nearest lists until it has met as many
   features as ``n_probe`` lists of the mean size hold: by default a sixteenth
   of the lists, at least 32 (:func:`default_probes`). What decides how close
   the clusters come to the exact engine's on real SIFT is the share of the
   lists scanned, not n: densities are sums of Gaussian terms whose far part
   is spread over every list (on dtu/scan24's 668k features 1.4% of a median
   feature's density lies beyond its 32 nearest of 2,048 lists, about as much
   in each doubling of the ranks), so a fixed number of probes leaves out more
   of it as n grows, and the ranks of nearby features drift apart. Co-membership
   F1 against exact on scan24: 0.9900 with 32 of 2,048 lists, 0.9942 with 64,
   0.9964 with 128, 0.9960 with 64 of 1,024 (this rule; 0.17x the exact
   engine's time), 0.9953 with 32 of 512; sacre_coeur's 90k COLMAP features
   with 32 of 512, 0.9966.
2. **Scan.** For every list, the features that scan it are one block of rows
   against the list's members: one GEMM gives the squared distances, and the
   scan tile kernel (``dqm_scan_tile``) uses each pair both ways: the row gets
   the member's kernel term and the member the row's, and the pairs within
   either end's edge radius ``rho * sigma`` are kept as candidate parents. A
   pair whose two features each scan the other's list meets twice; the tile of
   the larger list index keeps it, so every pair counts once. Both ways: at the
   same GEMMs the densities miss half as much mass (median 0.0012 instead of
   0.0029 kernel terms on sacre_coeur at 32 probes) and F1 against exact rose
   from 0.9921 to 0.9966. Two lists most of whose members scan each other's are
   met whole instead (every member of the lower scans the higher, none of the
   higher the lower: :func:`_lists_met_whole`), which costs fewer pairs (16%
   fewer in all on 150k generated features) and leaves out fewer terms.
3. **Exact edges.** The kept pairs' distances are recomputed exactly and those
   within the radius are the candidate parents. (Adding the candidates of each
   feature's candidates, two hops, was measured with one-way scans: at 48
   probes it found 76 more edges among sacre_coeur's 90k features and did not
   change F1, so it is not done.)

sigma is exact (the per-image pass of the exact engine), distances on every
kept edge are exact, and break/merge is the exact one, so C1 and C2 hold
exactly. What is approximate: a density misses the terms of features outside
the scanned lists (far ones, whose terms are small), and a parent outside
them is missed. Both can change clusters; scripts/bench_quickmatch.py --fast measures co-membership F1 against
the exact engine (docs/quickmatch.md).

Deterministic for a given input and seed: the sample and k-means are seeded,
and every sum is added in list order whatever the thread count.
"""
from __future__ import annotations

import contextlib
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, Iterator, List, NamedTuple, Optional, Tuple, Union

import numpy as np

from . import native, pairs

#: lists per feature count: n_lists = LISTS_FACTOR * sqrt(n), rounded to a power of two
LISTS_FACTOR = 1.25
#: lists each feature scans by default (its nearest centroids): one in PROBE_SHARE of the lists, at least MIN_PROBES
PROBE_SHARE = 16
MIN_PROBES = 32
#: k-means: training sample per list, Lloyd iterations
TRAIN_PER_LIST = 32
KMEANS_ITERATIONS = 8
#: probing rows of a scan task (2,048: 150k generated features scan 7% faster than with 1,024 on the integer kernel,
#: whose tasks make their distances 64 rows at a time, and 3% on the float32 GEMM; the same sums)
ROWS = 2048
#: candidate parents kept per feature, the nearest: a physical point seen in hundreds of images (1M generated
#: features: points in ~350 of 500 images) would otherwise give hundreds of edges per feature (14.5 GiB)
MAX_CANDIDATES = 32
#: scans (feature, list) or list members handled at a time where a setup step's temporaries grow with the probes
ENTRIES = 1 << 22
#: features handled at a time where a set-up step goes column by column over their nearest lists
SETUP_ROWS = 16384

ProgressFn = Optional[Callable[[int, int], None]]


def n_lists(n: int) -> int:
    """Lists for ``n`` features: about ``LISTS_FACTOR * sqrt(n)``, a power of two, at least 1 and at
    most n / 8."""
    target = max(1.0, min(LISTS_FACTOR * np.sqrt(max(n, 1)), n / 8.0))
    return int(2 ** int(np.round(np.log2(target))))


def default_probes(lists: int) -> int:
    """Lists each feature scans by default among ``lists``: one in :data:`PROBE_SHARE`, at least
    :data:`MIN_PROBES` (all of them when there are fewer)."""
    return int(min(lists, max(MIN_PROBES, lists // PROBE_SHARE)))


#: the rows of the left operand: the array itself, or an :class:`~dqm.core.pairs.Augmented` that makes them
#: block by block (:meth:`~dqm.core.pairs.Augmented.left_rows`)
LeftRows = Union[np.ndarray, pairs.Augmented]


def _size_of(left: LeftRows) -> Tuple[int, int]:
    """``(rows, descriptor dimension)`` of the left operand (its columns less the two augmented ones)."""
    if isinstance(left, pairs.Augmented):
        return left.n, left.dim
    return len(left), left.shape[1] - 2


def _rows_of(left: LeftRows, rows) -> np.ndarray:
    """Rows ``rows`` (a slice or indices) of the left operand, C-contiguous."""
    if isinstance(left, pairs.Augmented):
        return left.left_rows(rows)
    return np.ascontiguousarray(left[rows])


def _nearest_centroids(left: LeftRows, centroids: np.ndarray, t: int, n_threads: Optional[int] = 1) -> np.ndarray:
    """Indices of the ``t`` nearest centroids of every row of ``left`` (augmented operand rows
    ``[x, |x|^2, 1]``, or an Augmented that makes them), nearest first (ties: the lower index); computed in
    blocks of rows, ``n_threads`` blocks at a time."""
    dim = centroids.shape[1]
    right = np.empty((len(centroids), dim + 2), dtype=np.float32)
    right[:, :dim] = -2.0 * centroids
    right[:, dim] = 1.0
    right[:, dim + 1] = (centroids.astype(np.float64) ** 2).sum(axis=1)
    n = _size_of(left)[0]
    out = np.empty((n, t), dtype=np.int32)

    def block(s: int) -> None:
        d = _rows_of(left, slice(s, s + 4096)) @ right.T
        if t == 1:
            out[s:s + len(d), 0] = d.argmin(axis=1)
            return
        out[s:s + len(d)] = native.smallest(d, t)

    with pairs.tile_pool(n_threads) as run:
        for _ in run(block, range(0, n, 4096)):
            pass
    return out


class NearestCandidates:
    """Each child's ``k`` nearest candidate parents (float32 squared distance ``g``, ties: the lower
    candidate index), kept as the scan's edges come (:func:`dqm.core.native.keep_nearest`): memory
    ``8 k n`` bytes whatever the number of edges (a physical point seen in hundreds of images gives its
    features hundreds of candidates: 1M generated features, 14.5 GiB of edges uncut). ``limit[child]``
    tightens to just above the k-th g once k are held; the scan tile takes it as a radius, so that most
    far candidates are never written. The kept set does not depend on the order edges come in, so the
    thread count does not change it."""

    def __init__(self, n: int, k: int, image: Optional[np.ndarray] = None):
        self.k = int(k)
        self.g = np.full((n, self.k), np.inf, dtype=np.float32)
        self.cand = np.zeros((n, self.k), dtype=np.int32)
        self.count = np.zeros(n, dtype=np.int32)
        self.limit = np.full(n, np.inf, dtype=np.float32)
        self.image = None if image is None else np.ascontiguousarray(image, dtype=np.int32)

    def add(self, r: np.ndarray, c: np.ndarray, g: np.ndarray, rows: np.ndarray) -> None:
        """Offer one scan tile's edges (rows of the tile: ``rows``)."""
        native.keep_nearest(r, c, g, rows, self.image, self.g, self.cand, self.count, self.limit)

    def nearest(self, names: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Every child's candidates, child by child, nearest first: ``(child, cand)`` as int64, or with ``names``
        (int64, one per feature) ``(names[child], names[cand])``, made without int64 copies of the indices
        first (the edges are up to ``k n``: 64M at 2M features)."""
        names = np.arange(len(self.count), dtype=np.int64) if names is None else names
        held = np.arange(self.k)[None, :] < self.count[:, None]
        return np.repeat(names, self.count), names[self.cand[held]]


def _by_list(lists: np.ndarray, k: int) -> np.ndarray:
    """Stable order of entries by their list (``k`` lists): numpy sorts 16-bit keys by radix, in linear time."""
    return np.argsort(lists.astype(np.uint16) if k <= 1 << 16 else lists, kind="stable")


def _list_bounds(lists: np.ndarray, k: int) -> np.ndarray:
    """Where each of the ``k`` lists starts among entries ordered by :func:`_by_list` (and, last, their count)."""
    return np.concatenate([[0], np.cumsum(np.bincount(lists, minlength=k))])


def _scanned_lists(counts: np.ndarray, near: np.ndarray, quota: float) -> np.ndarray:
    """How many of each feature's other nearest lists (``near[:, 1:]``, nearest first) it scans: those it
    reaches having met fewer than ``quota`` features (its own list's ``counts`` included); a prefix, as the
    features met only grow. :data:`SETUP_ROWS` features at a time, column by column (the columns of a block
    stay in cache: half the time of whole columns at 1M features)."""
    count = np.zeros(len(near), dtype=np.int64)
    for s in range(0, len(near), SETUP_ROWS):
        block = near[s:s + SETUP_ROWS]
        met = counts[block[:, 0]].astype(np.int64)
        part = count[s:s + SETUP_ROWS]
        for j in range(1, near.shape[1]):
            part += met < quota
            met += counts[block[:, j]]
    return count


def _scan_bits(near: np.ndarray, scans: np.ndarray, k: int) -> np.ndarray:
    """Every feature's scanned lists as a bitset: (n, ceil(k / 64)) uint64, bit l of word l // 64 set when the
    feature scans list l (its own list included). :data:`SETUP_ROWS` features at a time (their words stay in
    cache: half the time of whole columns at 1M features), one column of ``near`` at a time: within a column
    the rows differ, so no word is written twice by one assignment."""
    words = (k + 63) // 64
    out = np.zeros((len(near), words), dtype=np.uint64)
    for s in range(0, len(near), SETUP_ROWS):
        block, scanned = near[s:s + SETUP_ROWS], scans[s:s + SETUP_ROWS]
        flat = out[s:s + SETUP_ROWS].reshape(-1)  # a view: the block's rows are contiguous
        base = np.arange(len(block), dtype=np.int64) * words
        for j in range(near.shape[1]):
            rows = slice(None) if j == 0 else np.flatnonzero(scanned[:, j - 1])
            lists = block[rows, j].astype(np.int64)
            at = base[rows] + (lists >> 6)
            flat[at] |= np.left_shift(np.uint64(1), (lists & 63).astype(np.uint64))
    return out


def _scan_blocks(near: np.ndarray, scans: np.ndarray, entries: int,
                 of: Optional[np.ndarray] = None) -> Iterator[Tuple[slice, np.ndarray, np.ndarray]]:
    """The scans of a block of features at a time (about ``entries`` of them, at least one feature a block):
    ``(the block's features, lists, of[feature])`` for each scan ``near[:, 1:][scans]`` of the block, in feature
    order (``of`` None: the features' indices, int64)."""
    step = max(1, entries // max(1, near.shape[1]))
    for s in range(0, len(near), step):
        block = slice(s, min(len(near), s + step))
        sc = scans[block]
        who = np.arange(block.start, block.stop, dtype=np.int64) if of is None else of[block]
        yield block, near[block, 1:][sc], np.repeat(who, sc.sum(axis=1))


def _lists_met_whole(own: np.ndarray, near: np.ndarray, scans: np.ndarray, counts: np.ndarray, by_list: np.ndarray,
                     bounds: np.ndarray, k: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Lists whose pairs are met whole. A pair of features of lists a < b is met when either scans the other's
    list (used both ways; where both do, the scan computes it twice and keeps it once), so lists a and b cost
    ``P_ab |b| + P_ba |a|`` pairs, P_ab the members of a that scan b. Where that is more than ``|a| |b|``
    (neighbouring lists, most of whose members scan each other's), every member of a scans b and no member of b
    scans a: every pair of the two lists is met once, for fewer pairs (150k generated features: 3,006 of
    130,816 pairs of lists, 16% fewer pairs in all), and the densities miss fewer terms. Returns ``scans``
    without b's scans of a, the scanned lists' bitsets (:func:`_scan_bits`) and the scans added, ``(feature,
    list)`` (int32): a's members that did not scan b. (:func:`nearest_above`, the parent search of capped
    children, still searches the lists of the quota rule, :meth:`ListIndex.scanned`.) Made :data:`ENTRIES`
    scans or members at a time, so that the temporaries stay small whatever the probes (made whole, about 24
    bytes a scan, they were the fast engine's peak at 1M features once the scan's own end was made leaner)."""
    k2 = k * k
    # blocks of ENTRIES scans, or as many as P has entries (each block's count adds all k^2 of them)
    entries = max(ENTRIES, k2)
    P = np.zeros(k2, dtype=np.int64)
    for _, lists, rows in _scan_blocks(near, scans, entries, own):
        P += np.bincount(rows.astype(np.int64) * k + lists, minlength=k2)
    P = P.reshape(k, k)
    size = counts.astype(np.int64)
    whole = np.triu(P * size[None, :] + P.T * size[:, None] > size[:, None] * size[None, :], 1)
    del P
    low, high = np.nonzero(whole)  # a < b
    none = np.zeros(0, np.int32)
    if not len(low):
        return scans, _scan_bits(near, scans, k), none, none
    kept = scans.copy()
    for block, lists, rows in _scan_blocks(near, scans, entries, own):  # b's members no longer scan a
        kept[block][scans[block]] = ~whole[lists, rows]  # (whole[a, b] holds a < b only)
    bits = _scan_bits(near, kept, k)  # a's members keep their scans of b: b > a is none of those dropped
    # every member of each lower list a, with its partner b, where it did not scan b; pairs of lists in chunks of
    # about ENTRIES members (a member's bit of b is its own: setting a chunk's changes no other chunk's test)
    sizes = size[low]
    ends = np.cumsum(sizes)
    added_row, added_list = [], []
    p0 = 0
    while p0 < len(low):
        p1 = max(p0 + 1, int(np.searchsorted(ends, ends[p0] - sizes[p0] + ENTRIES, side="right")))
        sz = sizes[p0:p1]
        start = np.repeat(bounds[low[p0:p1]] - np.cumsum(sz) + sz, sz)
        member = by_list[start + np.arange(int(sz.sum()))]
        partner = np.repeat(high[p0:p1], sz)
        new = ~_has_bit(bits, member, partner)
        member, partner = member[new].astype(np.int32), partner[new].astype(np.int32)
        _set_bits(bits, member, partner)
        added_row.append(member)
        added_list.append(partner)
        p0 = p1
    return kept, bits, np.concatenate(added_row), np.concatenate(added_list)


def _set_bits(bits: np.ndarray, rows: np.ndarray, lists: np.ndarray) -> None:
    """Set bit ``lists[j]`` of feature ``rows[j]`` in the bitsets of :func:`_scan_bits` (any number of bits a
    word)."""
    if not len(rows):
        return
    words = bits.shape[1]
    at = rows.astype(np.int64) * words + (lists.astype(np.int64) >> 6)
    value = np.left_shift(np.uint64(1), (lists & 63).astype(np.uint64))
    order = np.argsort(at, kind="stable")
    at, value = at[order], value[order]
    first = np.flatnonzero(np.r_[True, at[1:] != at[:-1]])
    bits.reshape(-1)[at[first]] |= np.bitwise_or.reduceat(value, first)


def _probers(near: np.ndarray, scans: np.ndarray, extra_row: np.ndarray, extra_list: np.ndarray, k: int,
             where: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """The features that scan each list, list by list: ``(probers, pbounds)``, list b's at
    ``probers[pbounds[b]:pbounds[b + 1]]`` as positions ``where[feature]`` (int32); within a list, those of
    ``near[:, 1:][scans]`` in feature order, then the ``extra`` scans in their order (a stable sort of the scans
    by list). Placed :data:`ENTRIES` scans at a time (a counting sort), so that no array of every scan is made
    but the result: 4 bytes a scan where a whole sort held about 20."""
    def chunks():
        for _, lists, rows in _scan_blocks(near, scans, ENTRIES):
            yield lists, rows
        for s in range(0, len(extra_row), ENTRIES):
            yield extra_list[s:s + ENTRIES], extra_row[s:s + ENTRIES]

    sizes = np.zeros(k, dtype=np.int64)
    for lists, _ in chunks():
        sizes += np.bincount(lists, minlength=k)
    pbounds = np.concatenate([[0], np.cumsum(sizes)])
    cursor = pbounds[:-1].copy()
    probers = np.empty(int(pbounds[-1]), dtype=np.int32)
    for lists, rows in chunks():
        order = _by_list(lists, k)
        lists = lists[order]
        c = np.bincount(lists, minlength=k)
        rank = np.arange(len(lists)) - (np.cumsum(c) - c)[lists]
        probers[cursor[lists] + rank] = where[rows[order]]
        cursor += c
    return probers, pbounds


def kmeans(left: LeftRows, k: int, seed: int = 0, n_threads: Optional[int] = 1,
           stop: Optional[threading.Event] = None) -> np.ndarray:
    """``k`` centroids of the rows of the augmented operand ``left`` (or of an Augmented's; Lloyd's iterations
    on a seeded sample, k-means++-free: seeds are sample rows). Returns float32 (k, dim) centroids in the
    operand's centred coordinates. Sums are float64 whatever the thread count: deterministic.
    ``stop`` (set by another thread): give up before the next iteration (:class:`Stopped`)."""
    n, dim = _size_of(left)
    rng = np.random.default_rng(seed)
    sample = np.sort(rng.choice(n, size=min(n, TRAIN_PER_LIST * k), replace=False))
    S = _rows_of(left, sample)
    centroids = S[np.sort(rng.choice(len(S), size=k, replace=False)), :dim].copy()
    for _ in range(KMEANS_ITERATIONS):
        if stop is not None and stop.is_set():
            raise Stopped("k-means stopped")
        own = _nearest_centroids(S, centroids, 1, n_threads)[:, 0]
        counts = np.bincount(own, minlength=k)
        filled = np.flatnonzero(counts)
        # each list's members in sample order, summed in float64 row by row (the order bincount adds in)
        starts = (np.cumsum(counts) - counts)[filled]
        sums = np.add.reduceat(S[_by_list(own, k), :dim].astype(np.float64), starts, axis=0)
        centroids[filled] = (sums / counts[filled, None]).astype(np.float32)
    return centroids


class Stopped(Exception):
    """:func:`kmeans` gave up: its caller no longer wants the centroids."""


@contextlib.contextmanager
def centroids_meanwhile(left: LeftRows, k: int, seed: int = 0,
                        n_threads: Optional[int] = None) -> Iterator[Callable[[], np.ndarray]]:
    """:func:`kmeans` on a thread of its own while the caller computes something else (the fast engine's
    sigma, which does not need the lists): the k-means is mostly one core's work, so the two together fill
    both cores. Yields a function that waits for the centroids (the same as :func:`kmeans`'s, whatever
    runs beside them). Leaving the block early (an error, Ctrl-C) stops the k-means before its next
    iteration and waits for that."""
    stop = threading.Event()
    pool = ThreadPoolExecutor(max_workers=1)
    future = pool.submit(kmeans, left, k, seed, n_threads, stop)
    try:
        yield future.result
    finally:
        stop.set()
        pool.shutdown(wait=True)


class ListIndex:
    """The scan's inverted lists, kept for a second search once the densities are known
    (:func:`nearest_above`): the centroids, every list's members (``members[bounds[b]:bounds[b + 1]]``, in
    feature order), how many nearest lists a feature considers (``t``) and the quota of features it meets."""

    def __init__(self, centroids: np.ndarray, members: np.ndarray, bounds: np.ndarray, t: int, quota: float):
        self.centroids = centroids
        self.members = members
        self.bounds = bounds
        self.t = int(t)
        self.quota = float(quota)

    def scanned(self, left: LeftRows, n_threads: Optional[int] = 1) -> Tuple[np.ndarray, np.ndarray]:
        """The lists the rows of ``left`` scan, by the scan's rule: ``(near, count)``, each row's ``t``
        nearest lists (its own first) and how many of the others it scans."""
        near = _nearest_centroids(left, self.centroids, self.t, n_threads)
        return near, _scanned_lists(np.diff(self.bounds).astype(np.int32), near, self.quota)


def _block_d2(aug: pairs.Augmented, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """float32 squared distances of features ``rows`` to features ``cols`` (within :attr:`Augmented.gamma`'s
    bound; exact integers on uint8 descriptors): the integer kernel where it runs, else a float32 GEMM."""
    return _Blocks(aug, rows, cols).d2(0, len(rows), 0, len(cols))


#: columns (list members) of one task of :func:`nearest_above`: its consecutive lists' members gathered at once
NEAREST_ABOVE_COLUMNS = 16384


class _Blocks:
    """Distances of some rows to some columns (features), block by block: the rows and columns gathered once
    (packed for the integer kernel where it runs), then any block's float32 squared distances (within
    :attr:`Augmented.gamma`'s bound; exact integers on uint8 descriptors) as :func:`_block_d2` gives them."""

    def __init__(self, aug: pairs.Augmented, rows: np.ndarray, cols: np.ndarray):
        self.integer = aug.integer_kernel
        if self.integer:
            self.R, self.C = native.U8Operands(aug.exact, rows), native.U8Operands(aug.exact, cols)
        else:
            self.R, self.C = aug.left_rows(rows), aug.right[cols]

    def d2(self, a: int, a1: int, b: int, b1: int) -> np.ndarray:
        """Rows ``a..a1`` against columns ``b..b1`` (positions among the gathered ones)."""
        if not self.integer:
            return self.R[a:a1] @ self.C[b:b1].T
        G = np.empty((a1 - a, b1 - b), np.float32)
        for c0 in range(b - b % 32, b1, native.MAX_ROW):  # the packed columns' tiles start at multiples of 32
            c1, lo = min(b1, c0 + native.MAX_ROW), max(b, c0)
            G[:, lo - b:c1 - b] = self.R.d2(a, a1, c0, c1, cols=self.C)[:, lo - c0:]
        return G


def nearest_above(
    aug: pairs.Augmented,
    index: ListIndex,
    rows: np.ndarray,
    density: np.ndarray,
    radius: np.ndarray,
    image_index: Optional[np.ndarray] = None,
    n_threads: Optional[int] = None,
) -> Tuple[np.ndarray, np.ndarray]:
    """Candidate parents of the features ``rows`` among the members of the lists each scans, now that the
    densities are known: the features that rank above it (:func:`dqm.core.tree.rank_order`: higher
    ``density``, then the lower index), lie within ``radius`` (float32 error bound added) and, with
    ``image_index``, come from another image; of those, the nearest and any within the float32 error bound of
    it (exact distances settle them). Returns directed edges ``(child, cand)`` (int64).

    The scan keeps each child's :data:`MAX_CANDIDATES` nearest candidates before the densities exist. A child
    whose kept candidates are all of lower rank (the densest members of a point seen in hundreds of images:
    their nearest neighbours are the point's other members) would otherwise become a root, and its cluster
    split: this search gives it the parent an uncapped scan of its lists would."""
    rows = np.asarray(rows, dtype=np.int64)
    if len(rows) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    near, count = index.scanned(aug.left_rows(rows), n_threads)
    scans = np.concatenate([np.ones((len(rows), 1), bool), np.arange(index.t - 1)[None, :] < count[:, None]], 1)
    lists = near[scans].astype(np.int64)
    who = np.repeat(np.arange(len(rows)), scans.sum(axis=1))
    order = np.argsort(lists, kind="stable")
    lists, who = lists[order], who[order]
    starts = np.flatnonzero(np.r_[True, lists[1:] != lists[:-1]])
    ends = np.r_[starts[1:], len(lists)]
    rad2 = pairs.search_rad2(aug, radius)[rows]
    slack2 = (2.0 * aug.d2_slack(rows)).astype(np.float32)
    dens_r = density[rows]
    img_r = None if image_index is None else image_index[rows]
    b_all = lists[starts]
    # a task: consecutive lists of about NEAREST_ABOVE_COLUMNS members in all, their rows and members gathered
    # (packed for the integer kernel) once, then each list's block of distances in strips of ROWS rows
    groups, size = [], 0
    for g, b in enumerate(b_all.tolist()):
        if not groups or size >= NEAREST_ABOVE_COLUMNS:
            groups.append([])
            size = 0
        # the members gathered: this list's and those of the lists between the group's last one and it
        first = b_all[groups[-1][-1]] + 1 if groups[-1] else b
        size += int(index.bounds[b + 1] - index.bounds[first])
        groups[-1].append(g)

    def work(group):
        g0, g1 = group[0], group[-1]
        q_lo, q_hi = int(starts[g0]), int(ends[g1])
        c_lo, c_hi = int(index.bounds[b_all[g0]]), int(index.bounds[b_all[g1] + 1])
        block = _Blocks(aug, rows[who[q_lo:q_hi]], index.members[c_lo:c_hi])
        out = []
        for g in group:
            b = int(b_all[g])
            lo, hi = int(index.bounds[b]) - c_lo, int(index.bounds[b + 1]) - c_lo
            cols = index.members[c_lo + lo:c_lo + hi]
            for q0 in range(int(starts[g]), int(ends[g]), ROWS):
                q1 = min(int(ends[g]), q0 + ROWS)
                q = who[q0:q1]
                G = block.d2(q0 - q_lo, q1 - q_lo, lo, hi)
                r, c = np.nonzero(G <= rad2[q, None])  # few: then the rank and the image of those only
                qr, cc, g2 = q[r], cols[c], G[r, c]
                dc = density[cc]
                ok = (dc > dens_r[qr]) | ((dc == dens_r[qr]) & (cc < rows[qr]))
                if img_r is not None:
                    ok &= image_index[cc] != img_r[qr]
                out.append((qr[ok], cc[ok], g2[ok]))
        return out

    found = []
    with pairs.tile_pool(n_threads) as run:
        for part in run(work, groups):
            found.extend(part)
    q = np.concatenate([f[0] for f in found])
    cand = np.concatenate([f[1] for f in found])
    g = np.concatenate([f[2] for f in found])
    best = np.full(len(rows), np.inf, dtype=np.float32)
    np.minimum.at(best, q, g)
    keep = g <= best[q] + slack2[q]
    return rows[q[keep]], cand[keep]


class Scan(NamedTuple):
    """What :func:`scan` found: each feature's density without the self term (``density_others``), directed
    candidate edges ``child -> cand``, the features whose candidates were cut at the cap (``capped``), the
    lists (``index``, for :func:`nearest_above`) and counts (``stats``)."""

    density_others: np.ndarray
    child: np.ndarray
    cand: np.ndarray
    capped: np.ndarray
    index: ListIndex
    stats: dict


def scan(
    aug: pairs.Augmented,
    weights: np.ndarray,
    active: np.ndarray,
    kernel: str,
    radius: np.ndarray,
    *,
    n_probe: Optional[int] = None,
    lists: Optional[int] = None,
    seed: int = 0,
    n_threads: Optional[int] = None,
    progress: ProgressFn = None,
    max_candidates: Optional[int] = None,
    image_index: Optional[np.ndarray] = None,
    centroids: Optional[np.ndarray] = None,
) -> Scan:
    """Densities (without the self term) and candidate edges from the probed lists.

    Arguments as :func:`dqm.core.pairs.kernel_pass`; ``centroids``: the lists' :func:`kmeans` centroids
    (``lists`` of them, with this ``seed``) when the caller has them already (:func:`centroids_meanwhile`).
    Returns a :class:`Scan`: each feature's sum of the kernel terms of the members of the lists it probes
    (itself left out), directed candidate edges ``child -> cand`` whose float32 distance is within
    ``radius[child]`` plus its error bound (each child's ``max_candidates`` nearest, by default
    :data:`MAX_CANDIDATES`; the children cut there are ``capped``), the lists and counts (lists, probes,
    pairs computed). With ``image_index`` (the parent must come from another image), pairs within one image
    are left out before the nearest are chosen, so that they do not take a child's places.
    """
    n = aug.n
    k = n_lists(n) if lists is None else int(lists)
    t = int(min(max(1, default_probes(k) if n_probe is None else n_probe), k))
    t0 = time.perf_counter()
    if centroids is None:
        centroids = kmeans(aug, k, seed, n_threads)
    elif len(centroids) != k:
        raise ValueError(f"scan: {len(centroids)} centroids for {k} lists")
    near = _nearest_centroids(aug, centroids, t, n_threads)
    time_lists = time.perf_counter() - t0
    own = near[:, 0].astype(np.int64)
    # members of each list, in feature order; probing rows of each list: its members first (their own
    # list is their nearest), then the others, so that row i < len(members) is column i (the self pair)
    by_list = _by_list(own, k)
    bounds = _list_bounds(own, k)
    # a feature scans its nearest lists until it has met as many features as n_probe lists of the mean size
    # hold: where lists are uneven (generated data, repeated texture), dense regions do not cost more per
    # feature than sparse ones
    counts = np.diff(bounds).astype(np.int32)
    count = _scanned_lists(counts, near, (t * n) / k)
    scans = np.arange(t - 1)[None, :] < count[:, None]  # the first count[i] of feature i's other nearest lists
    # two lists whose members scan each other's so much that meeting them whole costs fewer pairs: every
    # member of the lower one scans the higher, and none of the higher's the lower (_lists_met_whole)
    scans, bits, extra_row, extra_list = _lists_met_whole(own, near, scans, counts, by_list, bounds, k)
    # everything in list order: a list's members are one slice of the operands (no gather per tile)
    perm = by_list
    where = np.empty(n, dtype=np.int32)
    where[perm] = np.arange(n, dtype=np.int32)
    probers, pbounds = _probers(near, scans, extra_row, extra_list, k, where)
    del near, scans, extra_row, extra_list, where  # 5 bytes a probe: 1.3 GB at 2M features
    bits = bits[perm]
    # the rows' distances to a list: the integer (VNNI) kernel on uint8 descriptors where the CPU has it
    # (exact, as the float32 GEMM's on such data), else one float32 GEMM
    u8 = native.U8Operands(aug.exact, perm) if aug.integer_kernel else None
    Lp, Rp = (None, None) if u8 is not None else (aug.left[perm], aug.right[perm])
    wp = np.ascontiguousarray(weights[perm], dtype=np.float32)
    sp = np.ascontiguousarray(active[perm], dtype=np.float32)
    rad2p = pairs.search_rad2(aug, radius)[perm]
    listp = own[perm].astype(np.int32)
    tasks = []  # (list, its columns lo..hi, first of its probing rows): each task makes its rows (task_rows)
    for b in range(k):
        lo, hi = int(bounds[b]), int(bounds[b + 1])
        if hi == lo:
            continue
        for r0 in range(0, hi - lo + int(pbounds[b + 1] - pbounds[b]), ROWS):
            tasks.append((b, lo, hi, r0))

    def task_rows(b: int, lo: int, hi: int, r0: int) -> np.ndarray:
        """Rows r0 .. r0 + ROWS of list b's probing rows (int64): its members lo..hi, then the features that
        probe it."""
        own = np.arange(lo + r0, min(hi, lo + r0 + ROWS), dtype=np.int64)
        p0 = int(pbounds[b]) + max(0, r0 - (hi - lo))
        p1 = min(int(pbounds[b + 1]), int(pbounds[b]) + r0 + ROWS - (hi - lo))
        return np.concatenate([own, probers[p0:max(p0, p1)].astype(np.int64)])

    cap = MAX_CANDIDATES if max_candidates is None else max_candidates
    held = NearestCandidates(n, cap, None if image_index is None else image_index[perm])
    limit = held.limit  # read by the workers as they tighten it: any value read is a valid radius
    keeping = threading.Lock()  # the kept set does not depend on the order edges come in
    workspace = threading.local()  # each thread's buffers
    # gather, distances and scan tile in one native call per task
    scanner = native.U8Scan(u8, wp, sp, kernel, rad2p, limit, listp, bits) if u8 is not None else None

    def work(task):
        b, lo, hi, r0 = task
        rows = task_rows(b, lo, hi, r0)
        n_own = max(0, min(hi - lo - r0, len(rows)))
        if u8 is not None:
            if not hasattr(workspace, "scan"):
                workspace.scan = scanner.buffers(ROWS)
            dr, dc, (r, c, g) = scanner.run(rows, lo, hi, n_own, r0, b, workspace.scan)
            with keeping:
                held.add(r, c, g, rows)
            return rows, dr, lo, dc, len(rows) * (hi - lo)
        dr = np.zeros(len(rows))
        dc = np.zeros(hi - lo)
        L = Lp[rows]
        args = (wp[rows], sp[rows])
        for c0 in range(lo, hi, native.MAX_ROW):
            c1 = min(hi, c0 + native.MAX_ROW)
            r, c, g = native.scan_tile(L @ Rp[c0:c1].T, wp[c0:c1], sp[c0:c1], *args, kernel,
                                       np.minimum(rad2p[rows], limit[rows]), np.minimum(rad2p[c0:c1], limit[c0:c1]),
                                       n_own, lo + r0 - c0, listp[rows], bits[c0:c1], b, dr, dc[c0 - lo:c1 - lo])
            with keeping:
                held.add(r, c + c0, g, rows)
        return rows, dr, lo, dc, len(rows) * (hi - lo)

    dens = np.zeros(n)
    computed = 0
    with pairs.tile_pool(n_threads) as run:
        for done, (rows, dr, lo, dc, size) in enumerate(run(work, tasks), start=1):
            dens[rows] += dr  # a feature scans a list once: rows are distinct; in task order: the same sums
            dens[lo:lo + len(dc)] += dc
            computed += size
            if progress is not None:
                progress(done, len(tasks))
    out = np.empty(n)
    out[perm] = dens
    # the kept distances and the scan's operands are done with: freed before the edges are made
    held.g = None
    u8 = Lp = Rp = probers = bits = tasks = scanner = None  # (the workers' closure holds them: rebound, not deleted)
    cr, cc = held.nearest(perm)
    capped = np.empty(n, dtype=bool)
    capped[perm] = held.count >= held.k
    stats = {"n_lists": float(k), "n_probe": float(t), "pairs_computed": float(computed), "time_lists": time_lists}
    return Scan(out, cr, cc, capped, ListIndex(centroids, perm, bounds, t, (t * n) / k), stats)


def _has_bit(bits: np.ndarray, rows: np.ndarray, lists: np.ndarray) -> np.ndarray:
    """Whether feature ``rows[k]`` scans list ``lists[k]`` (bitsets of :func:`_scan_bits`)."""
    lists = np.asarray(lists, dtype=np.int64)
    words = bits[rows, lists >> 6]
    return ((words >> (lists & 63).astype(np.uint64)) & np.uint64(1)).astype(bool)


#: a feature of a cell scans at most this share of the cell's lists (1 / CELL_SHARE): at a quarter, with pairs
#: used both ways, a cell computes about half its pairs in smaller blocks and is no faster than the exact pass
#: (12,500 generated features); at an eighth, about a quarter of them
CELL_SHARE = 8
#: :class:`CellLists` pays where a cell's lists hold this many own features on average: with smaller lists
#: the blocks' GEMMs and the numpy per block cost more than the pairs they skip (sacre_coeur's features on
#: 8 agents, 6,947 a cell in 128 lists, 54 a list: 1.28x the exact pass's CPU; on 4 agents, 13,893 in 128:
#: 0.78x; generated 100k on 8 agents, 12,523 in 128: 0.73x)
MIN_LIST_FEATURES = 80


def cell_probes(lists: int) -> int:
    """Lists a feature of a cell scans among ``lists`` (:class:`CellLists`): :func:`default_probes`, at most
    1 / :data:`CELL_SHARE` of them (an eighth of 128 lists where the engine's default is a quarter)."""
    return int(min(default_probes(lists), max(1, lists // CELL_SHARE)))


def lists_pay(n: int) -> bool:
    """Whether :class:`CellLists` meets a cell of ``n`` own features faster than the exact pass: its lists
    hold :data:`MIN_LIST_FEATURES` features on average (from about 10,000 features, 128 lists)."""
    k = n_lists(n)
    return n >= MIN_LIST_FEATURES * k and cell_probes(k) * CELL_SHARE <= k


def cell_pairs_share(n: int) -> float:
    """About the share of a cell's pairs (``n`` own features) that :class:`CellLists` computes: 1 where the lists
    do not pay (:func:`lists_pay`), else ``(2 t + 1) / k`` (a feature scans t of the k lists, is scanned from as
    many, and meets its own list: 0.254 at 256 lists, where a job of 160,196 generated features on 4 agents
    computed 0.263 of its busiest cell's pairs)."""
    if not lists_pay(n):
        return 1.0
    k = n_lists(n)
    return min(1.0, (2 * cell_probes(k) + 1) / k)


#: pairs handed over: ``(i, j)``, ``i < j``
PairFound = Tuple[np.ndarray, np.ndarray]
#: a pair's test of which block meets it: ``keep(rows, cols, r, c)`` for the pairs ``(rows[r], cols[c])``
KeepFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], np.ndarray]
#: a block of pairs to meet: rows, columns, whether only its upper triangle (a list with itself), and the test
#: of the pairs it shares with another block (None: every pair of the block is met there only)
PairTask = Tuple[np.ndarray, np.ndarray, bool, Optional[KeepFn]]


class CellLists:
    """The fast engine's lists over one cell's own features, for the distributed balanced mode
    (:mod:`dqm.distributed.balanced` with ``engine="fast"``): the pairs among the own features, and between
    them and a window of copies, that :func:`scan` would compute, instead of every pair of the cell.

    The lists and the quota are :func:`scan`'s for the own features (:func:`n_lists`, a seeded :func:`kmeans`),
    with at most an eighth of the lists probed (:func:`cell_probes`); a copy scans the own lists by the same
    quota, as a feature of the cell would. A pair is met where either of its features scans the other's list, and is
    handed over once (:meth:`own_pairs`, :meth:`copy_pairs`) as ``(i, j)``, ``i < j``, with its float32
    squared distance within ``rad2`` of either end (``rad2``: :func:`dqm.core.pairs.search_rad2` of the held
    features, so no pair within reach of a met pair is missed); the caller computes the exact distance.
    Deterministic for the features and the seed, whatever the thread count."""

    def __init__(self, aug: pairs.Augmented, seed: int = 0, n_threads: Optional[int] = None):
        n = aug.n
        self.k = k = n_lists(n)
        self.t = t = cell_probes(k)
        centroids = kmeans(aug, k, seed, n_threads)
        #: the centroids in the descriptors' own coordinates (a copy's operand is centred elsewhere)
        self.centroids = centroids.astype(np.float64) + aug.center
        near = _nearest_centroids(aug, centroids, t, n_threads)
        self.own_list = near[:, 0].astype(np.int64)
        self.members = _by_list(self.own_list, k)
        self.bounds = _list_bounds(self.own_list, k)
        self.counts = np.diff(self.bounds).astype(np.int32)
        self.quota = (t * n) / k
        count, scans, self.bits = self._scans(near)
        probe_list = near[:, 1:][scans]
        order = _by_list(probe_list, k)
        self.probers = np.repeat(np.arange(n, dtype=np.int64), count)[order]
        self.probe_bounds = _list_bounds(probe_list, k)
        self.n_threads = n_threads
        #: distances computed so far by :meth:`own_pairs` and :meth:`copy_pairs`
        self.computed = 0

    def _members(self, b: int) -> np.ndarray:
        return self.members[self.bounds[b]:self.bounds[b + 1]]

    def _scans(self, near: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """By the own features' quota, for features whose nearest lists are ``near`` (nearest first): how many
        of the others each scans, which (a prefix of ``near[:, 1:]``) and all it scans as bitsets."""
        count = _scanned_lists(self.counts, near, self.quota)
        scans = np.arange(self.t - 1)[None, :] < count[:, None]
        return count, scans, _scan_bits(near, scans, self.k)

    def _run(self, aug: pairs.Augmented, rad2: np.ndarray, tasks: List[PairTask]) -> Iterator[PairFound]:
        """Each task ``(rows, cols, upper, keep)``: the pairs within reach of the block (``upper``: the upper
        triangle of a block of a list with itself) that its ``keep`` leaves to it."""
        self.computed += sum(len(r) * (len(r) - 1) // 2 if upper else len(r) * len(c) for r, c, upper, _ in tasks)

        def work(task):
            rows, cols, upper, keep = task
            G = _block_d2(aug, rows, cols)
            near = (G <= rad2[rows, None]) | (G <= rad2[None, cols])
            if upper:
                near = np.triu(near, 1)
            r, c = np.nonzero(near)
            if keep is not None and len(r):
                ok = keep(rows, cols, r, c)
                r, c = r[ok], c[ok]
            i, j = rows[r], cols[c]
            return np.minimum(i, j), np.maximum(i, j)

        with pairs.tile_pool(self.n_threads) as run:
            yield from run(work, tasks)

    def own_pairs(self, aug: pairs.Augmented, rad2: np.ndarray) -> Iterator[PairFound]:
        """The met pairs among the own features (``aug``: the own features, in the order the lists were made
        from), list by list. A pair whose two features each scan the other's list is handed over by the
        list of the larger index (as :func:`scan` keeps it)."""
        def keep(rows, cols, r, c):  # a prober's pair: not where the member scans the prober's list of larger index
            mine, theirs = self.own_list[cols[c]], self.own_list[rows[r]]
            return ~_has_bit(self.bits, cols[c], theirs) | (theirs < mine)

        tasks: List[PairTask] = []
        for b in range(self.k):
            cols = self._members(b)
            if len(cols) == 0:
                continue
            tasks.append((cols, cols, True, None))
            probers = self.probers[self.probe_bounds[b]:self.probe_bounds[b + 1]]
            tasks.extend((probers[p:p + ROWS], cols, False, keep) for p in range(0, len(probers), ROWS))
        return self._run(aug, rad2, tasks)

    def copy_pairs(self, aug: pairs.Augmented, rad2: np.ndarray, first: int) -> Iterator[PairFound]:
        """The met pairs between the own features (rows ``0 .. first - 1`` of ``aug``, the order the lists were
        made from) and the copies after them: a copy scans the own lists by the quota of the own features
        (its nearest list counts as its own), and an own feature meets the copies whose own list it scans."""
        copies = np.arange(first, aug.n, dtype=np.int64)
        if len(copies) == 0 or first == 0:
            return iter(())
        centroids = (self.centroids - aug.center).astype(np.float32)
        near = _nearest_centroids(aug.left_rows(copies), centroids, self.t, self.n_threads)
        count, scans, bits = self._scans(near)
        mine = near[:, 0].astype(np.int64)
        probe_list = np.concatenate([mine, near[:, 1:][scans]])
        probing = np.concatenate([copies, np.repeat(copies, count)])
        order = _by_list(probe_list, self.k)
        probing, bounds = probing[order], _list_bounds(probe_list, self.k)
        by_own = _by_list(mine, self.k)
        own_bounds = _list_bounds(mine, self.k)

        def keep(rows, cols, r, c):  # an own prober's pair with a copy: not where the copy scans its list too
            return ~_has_bit(bits, cols[c] - first, self.own_list[rows[r]])

        tasks: List[PairTask] = []
        for b in range(self.k):
            cols = self._members(b)
            rows = probing[bounds[b]:bounds[b + 1]]  # copies that scan list b (their own list included): met here only
            if len(cols):
                tasks.extend((rows[p:p + ROWS], cols, False, None) for p in range(0, len(rows), ROWS))
            # (a list k-means left without own members can still be a copy's nearest, and scanned by own features)
            theirs = copies[by_own[own_bounds[b]:own_bounds[b + 1]]]  # copies whose own list is b
            probers = self.probers[self.probe_bounds[b]:self.probe_bounds[b + 1]]
            if len(theirs):
                tasks.extend((probers[p:p + ROWS], theirs, False, keep) for p in range(0, len(probers), ROWS))
        return self._run(aug, rad2, tasks)
