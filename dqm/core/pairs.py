"""Blocked distance computations: the only place that looks at pairs of features.

No n x n matrix is ever formed. Squared distances come from a float32 GEMM on
augmented vectors ``[x, |x|^2, 1] . [-2x, 1, |x|^2]`` (one BLAS call per tile),
on data centred on its mean so the expansion loses little precision. Every
quantity that decides the result is then made exact in float64:

* distinctiveness ``sigma`` (nearest other feature of the same image): the
  float32 pass keeps every column within a rigorous slack of the row minimum
  and the minimum is recomputed from those in float64;
* candidate tree edges: the float32 pass keeps every pair within the search
  radius plus slack and their distances are recomputed in float64;
* densities: the float32 pass returns each density with an error bound; the
  caller asks :func:`exact_density` (float64) for those whose order matters and
  is not certain from the bounds.

Why a blocked GEMM and not a neighbour-search library: QuickMatch's density is a
sum over *all* features (a Gaussian term is negligible only several bandwidths
out, and on SIFT 1.5 sigma reaches ~10% of all features), so any exact method
visits every pair; measured on this 2-core machine (scripts/bench_quickmatch.py)
faiss' exact IndexFlatL2 k-NN pass is itself a GEMM over all pairs and is no
faster than ours, while a fused tile kernel (dqm/core/_tilekernel.c) does the
density and the radius search in the same pass over each tile.
"""
from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Callable, List, Optional, Tuple

import numpy as np

from . import density, native

#: features per block; a tile is BLOCK x BLOCK (4 MiB of float32)
BLOCK = 1024
#: relative error of a float32 squared distance from the augmented GEMM, as a
#: fraction of |x|^2 + |y|^2 (measured ~7e-7 on SIFT; 4 sqrt(K) eps32 with margin)
_EPS32 = float(np.finfo(np.float32).eps)

ProgressFn = Optional[Callable[[int, int], None]]


def default_threads() -> int:
    """Worker threads for the tile loop: ``DQM_THREADS`` or the CPU count (max 8)."""
    env = os.environ.get("DQM_THREADS")
    if env:
        return max(1, int(env))
    return max(1, min(8, os.cpu_count() or 1))


@contextmanager
def tile_pool(n_threads: Optional[int] = None):
    """Worker threads for tile work: ``with tile_pool() as run: run(fn, tasks)`` maps ``fn``
    over ``tasks`` in order. Each worker makes its own BLAS calls single-threaded once, so
    one GEMM per tile and thread does not oversubscribe the cores."""
    local = threading.local()

    def wrap(fn):
        def run(task):
            if not getattr(local, "blas_set", False):
                native.single_threaded_blas_in_this_thread()
                local.blas_set = True
            return fn(task)
        return run

    n = default_threads() if n_threads is None else max(1, int(n_threads))
    pool = ThreadPoolExecutor(max_workers=n)
    try:
        yield lambda fn, tasks: pool.map(wrap(fn), tasks)
    except BaseException:
        # Ctrl-C, SIGTERM or an error: drop the tiles not started (map queues them all at once), so
        # that the process ends after the running tiles instead of computing the whole pass first
        pool.shutdown(wait=False, cancel_futures=True)
        raise
    pool.shutdown(wait=True)


def augmented_rows(Xc: np.ndarray, norm2: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """GEMM operands of centred rows: ``left = [x, |x|^2, 1]``, ``right = [-2x, 1, |x|^2]`` (float32),
    so ``left_i . right_j`` is the squared distance; and the float64 ``|x|^2`` (computed unless given)."""
    if norm2 is None:
        norm2 = np.einsum("ij,ij->i", Xc, Xc)
    n, dim = Xc.shape
    return _operand_from_chunks(n, dim, [(0, Xc)], norm2, 0), _operand_from_chunks(n, dim, [(0, Xc)], norm2, 1), norm2


def _operand_from_chunks(n: int, dim: int, chunks, norm2: np.ndarray, side: int) -> np.ndarray:
    """Float32 operand ``side`` of :func:`augmented_rows` (0: left ``[x, |x|^2, 1]``, 1: right ``[-2x, 1, |x|^2]``)
    filled from ``(first row, centred rows)`` chunks (the rows are not modified; scaling by -2 is exact in
    float32)."""
    out = np.empty((n, dim + 2), dtype=np.float32)
    for a, xc in chunks:
        out[a:a + len(xc), :dim] = xc
        if side:
            out[a:a + len(xc), :dim] *= -2.0
    out[:, dim + side] = norm2
    out[:, dim + 1 - side] = 1.0
    return out


def error_gamma(dim: int) -> float:
    """``gamma``: a float32 GEMM squared distance is within ``gamma (|x|^2 + |y|^2)`` of the exact one."""
    return 4.0 * np.sqrt(dim + 2) * _EPS32


#: float32 integers are exact up to this magnitude
_F32_EXACT_INT = float(1 << 24)

#: rows per chunk where integer descriptors are centred in float32 (4 MiB of 128-dim rows)
_CENTRE_CHUNK = 1 << 13


def _centred_float32_chunks(X: np.ndarray, center: np.ndarray):
    """``(first row, X[rows] - center)`` in float32, chunk by chunk: integer rows centred on an integer
    centre stay exact integers, and no whole-array float copy is made."""
    c32 = center.astype(np.float32)
    for a in range(0, len(X), _CENTRE_CHUNK):
        xc = X[a:a + _CENTRE_CHUNK].astype(np.float32)
        xc -= c32
        yield a, xc


class Augmented:
    """Float32 augmented vectors of centred descriptors for GEMM squared distances.

    Integer descriptors (uint8 SIFT, RootSIFT) are centred on the rounded mean,
    so the operands stay integers. When every partial sum of the GEMM is an
    integer below 2^24 in magnitude (``4 max |x|^2 < 2^24``; normalised SIFT has
    ``|x|^2`` about 512^2), the float32 squared distances are exact whatever the
    order of the sums, and :attr:`gamma` is 0: sigma, candidate edges and
    parents need no float32 slack, and the densities' error bounds narrow to
    the rounding of the kernel terms themselves.
    """

    def __init__(self, X: np.ndarray):
        X = np.asarray(X)
        if X.dtype.kind not in "iu":
            X = np.asarray(X, dtype=np.float64)
        self.n, self.dim = X.shape
        integral = self.n > 0 and (X.dtype.kind in "iu" or bool(np.all(X == np.round(X))))
        mean = X.mean(axis=0) if self.n else np.zeros(self.dim)
        self.center = np.round(mean) if integral else mean
        # |x - center| < 2048 bounds every square below 2^22 (exact in float32) without a float64 copy
        small = integral and max(float(X.max()) - self.center.min(), self.center.max() - float(X.min())) < 2048.0
        if small:  # integers stay integers in float32: no float64 copy of the data (and no float32 one)
            norm2 = np.empty(self.n)
            for a, xc in _centred_float32_chunks(X, self.center):
                norm2[a:a + len(xc)] = np.einsum("ij,ij->i", xc, xc)
            max_norm2 = float(norm2.max())
        self._X = X
        self._operands_lock = threading.Lock()
        if small and 4.0 * max_norm2 < _F32_EXACT_INT:
            self.Xc = None  # exact mode: float32 GEMMs give exact distances (exact_density_others uses them)
            self.norm2 = norm2
            self._operands = [None, None]  # made on first use: the integer kernels, where they run, need none
        else:
            Xc = X - self.center
            self.Xc = Xc
            left, right, self.norm2 = augmented_rows(Xc)
            self._operands = [left, right]
        self.max_norm2 = float(self.norm2.max()) if self.n else 0.0
        #: the float32 GEMM distances are exact integers (see the class docstring)
        self.exact_d2 = self.Xc is None
        # bound on |float32 d2 - exact d2| for a pair (i, j): gamma * (|x_i|^2 + |x_j|^2)
        self.gamma = 0.0 if self.exact_d2 else error_gamma(self.dim)
        # compact copy for exact distances: integer descriptors (uint8 SIFT) as
        # small ints, so gathers move 8x fewer bytes and the arithmetic is exact
        self.exact = X
        if integral:
            lo, hi = X.min(), X.max()
            for dt in (np.uint8, np.int16, np.int32):
                info = np.iinfo(dt)
                if info.min <= lo and hi <= info.max:
                    self.exact = X.astype(dt, copy=False)
                    break
        #: the native integer (VNNI) distance kernel runs on these descriptors (decided here, once): exact
        #: squared distances (at most 258 x 255^2 < 2^24, so float32 holds them) at about 2.6x the float32
        #: GEMM's speed; :attr:`u8` holds them packed for it
        self.integer_kernel = self.exact.dtype == np.uint8 and self.dim <= 258 and native.u8_kernel_runs(self.exact)
        self._u8: Optional[native.U8Operands] = None

    @property
    def u8(self) -> Optional[native.U8Operands]:
        """The descriptors packed for the integer kernel where it runs (:attr:`integer_kernel`; else None), made
        on first use (the fast engine packs its own, in list order, and never needs these)."""
        if not self.integer_kernel:
            return None
        with self._operands_lock:
            if self._u8 is None:
                self._u8 = native.U8Operands(self.exact)
        return self._u8

    def _float32_operand(self, side: int) -> np.ndarray:
        """Operand ``side`` (0: left, 1: right) of the exact mode, made on first use chunk by chunk from the
        integer rows (the same values as :func:`augmented_rows` of the centred float32 rows, without a
        whole-array temporary), each side on its own: the fast engine on the integer kernel needs the left
        one only. Under a lock: the pass's worker threads ask at once, and each would otherwise make its own."""
        with self._operands_lock:
            if self._operands[side] is None:
                self._operands[side] = _operand_from_chunks(
                    self.n, self.dim, _centred_float32_chunks(self._X, self.center), self.norm2, side)
        return self._operands[side]

    @property
    def left(self) -> np.ndarray:
        """float32 GEMM operand ``[x, |x|^2, 1]`` of the centred rows (made on first use in exact mode)."""
        return self._float32_operand(0)

    def left_rows(self, rows) -> np.ndarray:
        """Rows ``rows`` (a slice or indices) of :attr:`left`, the same values, as a new C-contiguous array;
        where the whole operand is not made yet (exact mode), from those integer rows only, so that a caller
        that needs a few rows at a time (the fast engine's k-means and nearest lists on the integer kernel)
        never holds the whole operand (n x (dim + 2) float32: 47 MB at 90k SIFT)."""
        with self._operands_lock:
            made = self._operands[0]
        if made is not None:
            return np.ascontiguousarray(made[rows])
        X = self._X[rows]
        return _operand_from_chunks(len(X), self.dim, _centred_float32_chunks(X, self.center), self.norm2[rows], 0)

    @property
    def right(self) -> np.ndarray:
        """float32 GEMM operand ``[-2x, 1, |x|^2]`` of the centred rows (made on first use in exact mode)."""
        return self._float32_operand(1)

    def d2_rows(self, rows: np.ndarray) -> np.ndarray:
        """Exact float32 squared distances of the features ``rows`` to every feature, from the integer
        kernel (only where :attr:`u8` is set)."""
        return native.U8Operands(self.exact, rows).d2(0, len(rows), 0, self.n, cols=self.u8)

    def d2_block(self, a: int, a1: int, b: int, b1: int) -> np.ndarray:
        """float32 squared distances of features ``a..a1`` to ``b..b1`` (within :attr:`gamma`'s bound;
        exact from the integer kernel or when :attr:`exact_d2`)."""
        if self.u8 is not None:
            return self.u8.d2(a, a1, b, b1)
        return self.left[a:a1] @ self.right[b:b1].T

    def d2_slack(self, rows: np.ndarray) -> np.ndarray:
        """Upper bound on the float32 squared-distance error of each row against any column."""
        return self.gamma * (self.norm2[rows] + self.max_norm2) + 1e-30


def exact_sq_distances(X: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 1 << 14) -> np.ndarray:
    """Squared Euclidean distances ``||X[a_k] - X[b_k]||^2`` by direct differences.

    Exact for integer-valued descriptors (pass the compact integer copy,
    :attr:`Augmented.exact`: integer differences and sums). For float data the
    float64 value depends only on the two vectors (not on the batch, the order
    of ``a`` and ``b`` or the machine's other work), so every process that holds
    both features computes the same bits; the distributed mode relies on that.
    """
    fast = native.sq_distances_u8(X, a, b) if len(a) > 256 else None
    if fast is not None:
        return fast
    out = np.empty(len(a), dtype=np.float64)
    if X.dtype == np.uint8 and X.shape[1] <= 32768:
        wide = np.int32  # |diff| <= 255, sum of squares < 2^31
    elif np.issubdtype(X.dtype, np.integer):
        wide = np.int64
    else:
        wide = np.float64
    for s in range(0, len(a), chunk):
        diff = X[a[s:s + chunk]].astype(wide) - X[b[s:s + chunk]]
        diff *= diff
        out[s:s + chunk] = diff.sum(axis=1)
    return out


def exact_distances(X: np.ndarray, a: np.ndarray, b: np.ndarray, chunk: int = 1 << 14) -> np.ndarray:
    """Euclidean distances ``||X[a_k] - X[b_k]||``: the square root of :func:`exact_sq_distances`."""
    return np.sqrt(exact_sq_distances(X, a, b, chunk))


def duplicate_groups(X: np.ndarray) -> np.ndarray:
    """Group id of every row; rows with identical values share an id (ids are 0..g-1).

    Pass the compact copy (:attr:`Augmented.exact`) where there is one:
    uint8 rows sort 8x faster and in an eighth of the memory."""
    if len(X) == 0:
        return np.zeros(0, np.int64)
    Z = np.ascontiguousarray(X if X.dtype.kind in "iu" else X + 0.0)  # -0.0 -> 0.0: equal values, equal bytes
    rows = Z.view(np.dtype((np.void, Z.dtype.itemsize * Z.shape[1]))).ravel()
    _, inverse = np.unique(rows, return_inverse=True)
    return inverse.ravel().astype(np.int64)


def nearest_same_image(aug: Augmented, image_index: np.ndarray, n_images: int,
                       n_threads: Optional[int] = None, use_native: bool = True,
                       groups: Optional[np.ndarray] = None) -> np.ndarray:
    """Distance from every feature to the nearest *other* feature of its image (exact).

    A feature with an exact duplicate in its image has distance 0; of the
    others, one representative per distinct vector and image takes part (the
    same exact distances, but a set of many duplicates costs nothing extra).
    Each unordered block pair of an image is computed once; a tile keeps every
    entry within the float32 error bound of its row's (and column's) tile
    minimum, the global minimum of every row is then known, and the entries
    within the bound of it are recomputed exactly. Features alone in their
    image get ``nan`` (the caller decides what that means). ``groups``: the
    caller's :func:`duplicate_groups` of ``aug.exact``, if it has them.
    """
    n = aug.n
    image_index = np.asarray(image_index, np.int64)
    if groups is None:
        groups = duplicate_groups(aug.exact)
    _, first, inverse, count = np.unique(groups * np.int64(max(1, n_images)) + image_index, return_index=True,
                                         return_inverse=True, return_counts=True)
    duplicated = count[inverse.ravel()] > 1  # an identical vector in the same image
    order = first[np.argsort(image_index[first], kind="stable")]  # one per (vector, image), by image
    bounds = np.searchsorted(image_index[order], np.arange(n_images + 1))
    # exact float32 distances (integer descriptors): the minima are the exact squared distances themselves, so
    # no tile needs to hand over the entries near them
    minima_only = aug.exact_d2
    slack = None if minima_only else 2.0 * aug.d2_slack(np.arange(n))
    images = [img for img in range(n_images) if bounds[img + 1] - bounds[img] >= 2]
    tasks = [tile + (img,) for img in images for tile in _block_pairs(bounds[img], bounds[img + 1])]

    nothing = np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    scratch = threading.local()  # each thread's strip for the integer kernel's minima

    def work(task):
        a, a1, b, b1, img = task
        ra, rb = order[a:a1], order[b:b1]
        if img in packed:
            lo, ops = packed[img]
            if minima_only:  # the minima straight from the kernel's strips: no tile made, read again
                if not hasattr(scratch, "strip"):
                    scratch.strip = native.minima_scratch()
                rmin, cmin = ops.minima(a - lo, a1 - lo, b - lo, b1 - lo, a == b, scratch.strip)
                return nothing + (ra, rmin, rb, cmin)
            G = ops.d2(a - lo, a1 - lo, b - lo, b1 - lo)
        else:
            G = aug.left[ra] @ aug.right[rb].T
        if a == b:
            np.fill_diagonal(G, np.finfo(np.float32).max)
        sr, sc = (None, None) if minima_only else (slack[ra], slack[rb])
        rmin, cmin, r, c, g = native.nearest_sym(G, sr, sc, use_native=use_native)
        return ra[r], rb[c], g.astype(np.float64), ra, rmin, rb, cmin

    def pack(img):
        lo, hi = bounds[img], bounds[img + 1]
        return img, (lo, native.U8Operands(aug.exact, order[lo:hi]))

    best = np.full(n, np.inf)
    rows_l, cols_l, g_l = [], [], []
    packed = {}  # image -> its representatives packed for the integer kernel (tiles start at 0 in each)
    with tile_pool(n_threads) as run:
        if aug.integer_kernel and use_native:
            packed.update(run(pack, images))  # on the threads: packing is copies that run without the GIL
        for r, c, g, ra, rmin, rb, cmin in run(work, tasks):
            best[ra] = np.minimum(best[ra], rmin)  # a tile's rows (columns) are distinct features
            best[rb] = np.minimum(best[rb], cmin)
            rows_l.append(r)
            cols_l.append(c)
            g_l.append(g)
    sigma = np.full(n, np.nan)
    sigma[duplicated] = 0.0
    if minima_only:  # the square root of the exact integer, as exact_distances takes it
        has = (best < np.finfo(np.float32).max) & ~duplicated  # the huge diagonal: no other representative
        sigma[has] = np.sqrt(best[has])
        return sigma
    if not rows_l:
        return sigma
    r = np.concatenate(rows_l)
    c = np.concatenate(cols_l)
    g = np.concatenate(g_l)
    # both directions of each pair; keep those within the bound of the row's minimum
    a = np.concatenate([r, c])
    b = np.concatenate([c, r])
    g = np.concatenate([g, g])
    keep = g <= best[a] + slack[a]
    a, b = a[keep], b[keep]
    d = exact_distances(aug.exact, a, b)
    exact_min = np.full(n, np.inf)
    np.minimum.at(exact_min, a, d)
    # a representative's distance is its vector's: every unduplicated copy of it is the representative itself
    has = np.isfinite(exact_min) & ~duplicated
    sigma[has] = exact_min[has]
    return sigma


def search_rad2(aug: Augmented, radius: np.ndarray) -> np.ndarray:
    """float32 squared search radii that cannot miss a pair within ``radius`` (error bound added).

    A zero radius finds nothing (-inf): an edge needs a distance strictly below the radius, so
    such a child has no candidate, and exact duplicates (sigma 0) never flood the passes with
    pairs that lie within the error bound of zero."""
    r = np.asarray(radius, dtype=np.float64)
    want = r ** 2 * (1.0 + 1e-12) + aug.d2_slack(np.arange(aug.n))
    rad2 = want.astype(np.float32)
    low = rad2 < want  # round up: with exact distances the slack no longer covers float32 rounding
    rad2[low] = np.nextafter(rad2[low], np.float32(np.inf))
    rad2[r <= 0] = -np.inf
    return rad2


def _block_pairs(lo: int, hi: int, limit: Optional[int] = None) -> List[Tuple[int, int, int, int]]:
    """The pairs of :data:`BLOCK`-row blocks of rows ``lo:hi``, each unordered pair once (a block with itself
    included), as ``(a, a1, b, b1)``; with ``limit``, only those whose row block starts below it."""
    starts = list(range(lo, hi, BLOCK))
    return [(a, min(hi, a + BLOCK), b, min(hi, b + BLOCK)) for i, a in enumerate(starts)
            if limit is None or a < limit for b in starts[i:]]


def pass_tile(aug: Augmented, a: int, a1: int, b: int, b1: int, diag: bool, w: np.ndarray, s: np.ndarray,
              kernel: str, rad2: np.ndarray, fused: bool, use_native: bool = True):
    """One tile of :func:`kernel_pass`, rows ``a:a1`` by columns ``b:b1`` (``diag``: the same block, one
    direction): ``(dens_r, err_r, dens_c, err_c, child, cand)``, the columns' sums None on the diagonal;
    ``fused``: distances and kernel terms in one call of the integer kernel (uint8 on VNNI)."""
    dr = np.zeros(a1 - a)
    er = np.zeros(a1 - a)
    if fused:  # distances and kernel fused in one native call
        if diag:
            r, c = native.pass_tile_u8(aug.u8, a, a1, b, b1, w, s, kernel, rad2, dr, er)
            return dr, er, None, None, r, c
        dc, ec = np.zeros(b1 - b), np.zeros(b1 - b)
        r, c = native.pass_tile_u8(aug.u8, a, a1, b, b1, w, s, kernel, rad2, dr, er, dc, ec, diag=False)
        return dr, er, dc, ec, r, c
    G = aug.left[a:a1] @ aug.right[b:b1].T
    if diag:
        r, c = native.tile(G, w[b:b1], s[b:b1], kernel, rad2[a:a1], 0, dr, er, use_native=use_native)
        return dr, er, None, None, r, c
    dc = np.zeros(b1 - b)
    ec = np.zeros(b1 - b)
    r, c = native.tile_sym(G, w[b:b1], s[b:b1], w[a:a1], s[a:a1], kernel, rad2[a:a1], rad2[b:b1],
                           dr, er, dc, ec, use_native=use_native)
    return dr, er, dc, ec, r, c


def kernel_pass(
    aug: Augmented,
    weights: np.ndarray,
    active: np.ndarray,
    kernel: str,
    radius: np.ndarray,
    *,
    n_threads: Optional[int] = None,
    progress: ProgressFn = None,
    use_native: bool = True,
    rows_limit: Optional[int] = None,
    cols_from: Optional[int] = None,
    max_edges: Optional[int] = None,
    on_edges: Optional[Callable[[np.ndarray, np.ndarray], None]] = None,
    undirected: bool = False,
) -> Tuple[np.ndarray, np.ndarray, Optional[np.ndarray], Optional[np.ndarray]]:
    """One pass over all pairs: approximate densities and candidate edges.

    ``weights[c]`` scales a squared distance into the kernel argument of
    contributor ``c`` (Gaussian ``exp(-d2 w)``, quadratic ``max(0, 1 - d2 w)``),
    ``active[c]`` (0/1) says whether ``c`` contributes at all. ``radius[j]`` is
    the edge search radius of feature ``j`` as a child.

    Each unordered block pair is computed once (one GEMM) and used both ways.
    With ``rows_limit = L`` only pairs with at least one feature among the
    first L are visited (a distributed agent: its own features first, then
    copies of other cells' features, whose pairs among themselves are another
    agent's work). The candidate edges are then exactly those pairs; the
    approximate densities are not restricted and should not be used. With
    ``cols_from = C`` as well, only pairs between the first L and the features
    from C on are visited (an agent meeting one batch of copies at a time: its
    own features first, the batch after them, with L = C); the tiles then cover that rectangle only, so a
    batch costs its pairs with the own features and no more. With
    ``max_edges``, collection stops once more edges than that are found; the
    densities are still complete and ``child`` and ``cand`` come back as None
    (the streaming :func:`parent_pass` then finds the parents). With
    ``on_edges``, every tile's edges go to ``on_edges(child, cand)`` instead
    (in the same order on every run; a pair lies in one tile only), nothing is
    collected, and ``child`` and ``cand`` come back empty: memory O(n + one
    tile's edges) whatever the radius. With ``undirected`` as well, ``on_edges``
    gets every candidate pair once, as (lower index, higher index), instead of
    both directions (a caller that needs each pair once, the balanced agents,
    then does not sort every tile's edges to drop the mirror images).

    Returns ``(density_others, density_error, child, cand)``: the density
    without the self term (float32 accuracy), a bound on its absolute error,
    and directed candidate edges ``child -> cand``, a superset of the pairs
    whose exact distance is below ``radius[child]``.
    """
    n = aug.n
    w = np.ascontiguousarray(weights, dtype=np.float32)
    s = np.ascontiguousarray(active, dtype=np.float32)
    no_edges = np.full(n, -np.inf, dtype=np.float32)
    rad2_all = search_rad2(aug, radius)
    collecting = [True]
    dens = np.zeros(n, dtype=np.float64)
    err = np.zeros(n, dtype=np.float64)
    limit = n if rows_limit is None else int(rows_limit)
    cross = 0 if cols_from is None else int(cols_from)
    fused = aug.integer_kernel and use_native
    if cols_from is None:  # unordered block pairs, each once; diagonal blocks (a == b) use one direction
        tasks = _block_pairs(0, n, limit)
    else:  # rows end at the limit and columns start at cross (the integer kernel's tiles at a multiple of 32):
        # only the own-by-batch rectangle, whatever the sizes (own rows in the columns' first 31: edges filtered)
        c0 = cross - cross % 32 if fused else cross
        tasks = [(a, min(limit, a + BLOCK), b, min(n, b + BLOCK)) for a in range(0, limit, BLOCK)
                 for b in range(c0, n, BLOCK)]

    def work(task: Tuple[int, int, int, int]):
        a, a1, b, b1 = task
        return (a, b) + pass_tile(aug, a, a1, b, b1, a == b and cols_from is None, w, s, kernel,
                                  rad2_all if collecting[0] else no_edges, fused, use_native)

    def within_limit(ch: np.ndarray, ca: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        if cross:
            keep = ((ch < limit) & (ca >= cross)) | ((ca < limit) & (ch >= cross))
            return ch[keep], ca[keep]
        if limit >= n:
            return ch, ca
        keep = (ch < limit) | (ca < limit)  # blocks straddling the limit also met pairs beyond it
        return ch[keep], ca[keep]

    child: List[np.ndarray] = []
    cand: List[np.ndarray] = []
    narrow = n < np.iinfo(np.int32).max  # edges' indices fit int32
    held = 0
    with tile_pool(n_threads) as run:
        for done, (a, b, dr, er, dc, ec, r, c) in enumerate(run(work, tasks), start=1):
            dens[a:a + len(dr)] += dr
            err[a:a + len(er)] += er
            if dc is not None:
                dens[b:b + len(dc)] += dc
                err[b:b + len(ec)] += ec
            if progress is not None:
                progress(done, len(tasks))
            if not collecting[0]:
                continue
            if on_edges is not None:
                r, c = r.astype(np.int64) + a, c.astype(np.int64) + b
                if undirected:  # a tile off the diagonal has each pair once; on it, in one or both directions
                    r, c = (np.minimum(r, c), np.maximum(r, c)) if dc is not None else _pairs_once(r, c, n)
                elif dc is not None:
                    r, c = np.concatenate([r, c]), np.concatenate([c, r])
                on_edges(*within_limit(r, c))
                continue
            # held as int32 until the end (half the memory of the edges while the pass runs)
            r, c = (r + a, c + b) if narrow else (r.astype(np.int64) + a, c.astype(np.int64) + b)
            held += len(r) * (1 if dc is None else 2)
            if max_edges is not None and held > max_edges:
                collecting[0] = False  # tiles in flight may still bring edges: ignored
                child.clear()
                cand.clear()
                continue
            child.append(r)
            cand.append(c)
            if dc is not None:
                child.append(c)
                cand.append(r)
    err *= term_error_factor(aug)
    err += sum_error(dens, n)
    if not collecting[0]:
        return dens, err, None, None
    if not child:
        return dens, err, np.zeros(0, np.int64), np.zeros(0, np.int64)
    child_a = np.concatenate(child, dtype=np.int64)
    child.clear()
    cand_a = np.concatenate(cand, dtype=np.int64)
    cand.clear()
    child_a, cand_a = within_limit(child_a, cand_a)
    return dens, err, child_a, cand_a


#: rows of :func:`pair_cpu_s_here`'s generated block: three 1024-row tiles, 3-4 ms of CPU a pass on AVX-512 VNNI
#: (uint8, 128 dimensions), 15-20 ms in portable C
PROBE_ROWS = 2048
#: :func:`pair_cpu_s_here` stops timing passes once they have taken this much CPU: four passes on AVX-512 VNNI,
#: one on a machine whose kernel is 10x slower (a 2-core AMD EPYC with AVX2 only: 27 ms a pass, and four of them
#: with the warm-up cost ``--mode auto`` 0.6 s at a quarter core, 10-15% of graf's balanced job at M = 8)
PROBE_CPU_S = 0.012


def pair_cpu_s_here(dim: int, dtype, rows: int = PROBE_ROWS, repeats: int = 4, kernel: str = "quadratic") -> float:
    """CPU-seconds per pair-dimension of :func:`kernel_pass` on one thread, measured here: the least of
    ``repeats`` passes (after one tile to warm up; fewer once they took :data:`PROBE_CPU_S`) over ``rows``
    generated rows of ``dim`` elements of ``dtype``
    (uint8 or float32), on a thread of its own timed by that thread's CPU clock (a CPU quota's throttling and the
    process's other threads do not count; the process's clock where BLAS cannot be made single-threaded in
    one thread, whose workers would otherwise go uncounted).

    What the machine does with the same code: ``--mode auto``'s cost model scales its fitted compute by this
    over the value measured where it was fitted (:class:`dqm.distributed.costmodel.CostConstants`). Over
    all-pairs passes of 5,000 to 40,000 generated features, a full :func:`dqm.quickmatch` on one thread took
    0.75-1.05x this per pair-dimension at every SIMD level of one machine (AVX-512 VNNI, AVX2, portable C).
    Four timed passes of 2048 rows (about 15 ms of CPU on AVX-512 VNNI): two gave values 20% apart on one
    machine and day."""
    import time

    dt = np.dtype(dtype)
    if dt not in (np.dtype(np.uint8), np.dtype(np.float32)) or int(dim) < 1 or int(rows) < 2:
        raise ValueError(f"pair_cpu_s_here times uint8 or float32 rows of dim >= 1, got {dt} x {dim}, {rows} rows")
    # bytes of a multiplicative hash, near-uniform (each value 1023-1026 times in 2048 x 128): no import of
    # numpy.random (about 20 ms of CPU, in a coordinator that waits on a quarter core before it decides)
    k = np.arange(int(rows) * int(dim), dtype=np.uint64)
    X = ((k * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(56)).astype(np.uint8).reshape(int(rows), int(dim))
    scale = 1.0 if dt == np.uint8 else 1.0 / 256
    X = X if dt == np.uint8 else (X * np.float32(scale)).astype(np.float32)
    n = len(X)
    aug = Augmented(X)
    w = np.full(n, 1e-6 / scale ** 2, np.float32)  # kernel arguments of order one for both types
    active = np.ones(n, np.float32)
    rad2 = np.full(n, -np.inf, np.float32)  # no edges: the pass's distances and kernel terms only
    fused = aug.integer_kernel
    tiles = _block_pairs(0, n)
    times: List[float] = []
    failed: List[BaseException] = []

    def run() -> None:  # in a thread of its own: its CPU clock counts this work only, its BLAS single-threaded
        try:
            clock = time.thread_time if native.single_threaded_blas_in_this_thread() else time.process_time
            a, a1, b, b1 = tiles[0]  # warm-up (the operands, made whole on first use; pages): one tile, not counted
            pass_tile(aug, a, a1, b, b1, a == b, w, active, kernel, rad2, fused)
            for _ in range(max(1, int(repeats))):  # passes until PROBE_CPU_S is spent (a slow machine: one)
                t = clock()
                for a, a1, b, b1 in tiles:
                    pass_tile(aug, a, a1, b, b1, a == b, w, active, kernel, rad2, fused)
                times.append(clock() - t)
                if sum(times) >= PROBE_CPU_S:
                    break
        except BaseException as exc:  # noqa: BLE001 - re-raised in the caller's thread, whatever it is
            failed.append(exc)

    worker = threading.Thread(target=run, name="dqm-pair-probe")
    worker.start()
    worker.join()
    if failed:
        raise failed[0]
    best = min(times)
    return max(best, 1e-9) / (n * (n - 1) / 2.0 * X.shape[1])


def _pairs_once(r: np.ndarray, c: np.ndarray, n: int) -> Tuple[np.ndarray, np.ndarray]:
    """Directed edges among n rows as unordered pairs, each once: (lower, higher), sorted."""
    key = np.unique(np.minimum(r, c) * n + np.maximum(r, c))
    return key // n, key % n


def term_error_factor(aug: Augmented) -> np.ndarray:
    """Per row, the factor that turns the tile kernel's error weights ``sum |dK/d(d2)|`` into a
    bound on the kernel terms' error from their arguments.

    A term's argument ``t = d2 w`` is computed in float32 from the float32 distance (error
    ``gamma (|x|^2 + |y|^2)``, 0 when exact) and the float32 weight, with two roundings (at most
    ``eps32 t``); as ``d2 <= 2 (|x|^2 + |y|^2)`` both are ``(gamma + 2 eps32) (|x|^2 + |y|^2)``
    in d2 terms, and ``|y|^2 <= max |y|^2``. A third eps32 is margin.
    """
    return (aug.gamma + 3.0 * _EPS32) * (aug.norm2 + aug.max_norm2)


def sum_error(dens: np.ndarray, n: int) -> np.ndarray:
    """Bound on the error of the float32 evaluation and summation of the kernel terms.

    Each term comes from a float32 exp within 2 ulp (the quadratic kernel: within 1 ulp) and is
    rounded at most :data:`native.SUM_ROUNDINGS` times on its way into a float64 sum, each time
    by at most eps32 / 2 of the partial sum it joins (terms are non-negative, so partial sums
    are at most the total). A term clamped at ``exp(-87)`` is over by less than 1.7e-38, for
    each of at most ``n`` contributors.
    """
    return (2.0 * _EPS32 + 0.5 * _EPS32 * native.SUM_ROUNDINGS) * dens + n * 1.7e-38 + 1e-300


def exact_density_others(
    aug: Augmented,
    targets: np.ndarray,
    weights: np.ndarray,
    active: np.ndarray,
    kernel: str,
    n_threads: Optional[int] = None,
) -> np.ndarray:
    """Float64 densities (without the self term) of the given targets over all contributors, in chunks
    of targets, ``n_threads`` at a time (each target's value does not depend on the chunk or the thread).

    Gaussian: a float64 GEMM on the centred data (error ~1e-16 |x|^2 on a
    squared distance, far below any difference that decides the result).

    Quadratic: the float64 GEMM only selects the contributors within reach
    (with a rigorous margin); their terms come from exact squared distances and
    are summed exactly (:mod:`dqm.core.density`), so the value is the correctly
    rounded density, the same bits a distributed agent computes from its part
    of the data.
    """
    targets = np.asarray(targets, dtype=np.int64)
    contrib = np.flatnonzero(active > 0)
    if len(targets) == 0 or len(contrib) == 0:  # every sigma 0: no kernel contributes (the caller counts duplicates)
        return np.zeros(len(targets))
    nrm = aug.norm2
    if aug.u8 is not None and kernel == "gaussian":
        return _gaussian_density_u8(aug, targets, np.asarray(weights, np.float64), active, n_threads)
    every = len(contrib) == aug.n  # no gathered copy of the data when every feature contributes
    cols = slice(None) if every else contrib
    wc = np.asarray(weights, dtype=np.float64)[cols]
    ncon = nrm[cols]
    gamma64 = 0.0  # the distance error the quadratic selection allows for: none where they are exact
    if aug.u8 is not None:  # exact distances from the integer kernel, no copy of the data
        def squared(t):
            d2 = aug.d2_rows(t)
            return (d2 if every else d2[:, contrib]).astype(np.float64)
    elif aug.exact_d2:  # float32 GEMM distances are exact integers
        right = aug.right[cols]

        def squared(t):
            return (right @ aug.left[t].T).T.astype(np.float64)  # this orientation: 2-3x faster in OpenBLAS
    else:
        Xcon = aug.Xc[cols]
        # bound on the float64 GEMM error of a squared distance, relative to |x|^2 + |y|^2
        gamma64 = 4.0 * (aug.dim + 2) * float(np.finfo(np.float64).eps)

        def squared(t):
            d2 = aug.Xc[t] @ Xcon.T
            d2 *= -2.0
            d2 += nrm[t][:, None]
            d2 += ncon[None, :]
            return d2
    step = max(1, min(256, (8 << 20) // max(1, len(contrib))))  # ~64 MiB of float64 scratch a thread

    def chunk(s: int) -> Tuple[int, np.ndarray]:
        t = targets[s:s + step]
        d2 = squared(t)
        np.maximum(d2, 0.0, out=d2)
        pos = np.searchsorted(contrib, t)
        hit = (pos < len(contrib)) & (contrib[np.minimum(pos, len(contrib) - 1)] == t)
        rows = np.flatnonzero(hit)
        if kernel == "quadratic":
            slack = gamma64 * (nrm[t][:, None] + ncon[None, :])
            near = (d2 - slack) * wc[None, :] < 1.0
            near[rows, pos[rows]] = False  # the self term
            r, c = np.nonzero(near)
            exact_d2 = exact_sq_distances(aug.exact, t[r], contrib[c])
            sums = density.ExactSums(len(t))
            sums.add_terms(r, density.quadratic_terms(exact_d2, wc[c]))
            return s, sums.values()
        d2 *= wc[None, :]
        np.negative(d2, out=d2)
        vals = np.exp(d2, out=d2)
        vals[rows, pos[rows]] = 0.0  # the self term
        return s, vals.sum(axis=1)

    return _by_chunks(len(targets), step, chunk, n_threads)


def _by_chunks(n: int, step: int, chunk: Callable[[int], Tuple[int, np.ndarray]],
               n_threads: Optional[int]) -> np.ndarray:
    """``n`` float64 values computed ``step`` at a time by ``chunk(start) -> (start, values)``, on
    ``n_threads`` threads, each written at its start."""
    out = np.empty(n)
    with tile_pool(n_threads) as run:
        for s, values in run(chunk, range(0, n, step)):
            out[s:s + len(values)] = values
    return out


def _gaussian_density_u8(aug: Augmented, targets: np.ndarray, weights: np.ndarray, active: np.ndarray,
                         n_threads: Optional[int] = None) -> np.ndarray:
    """:func:`exact_density_others` (Gaussian) from the integer kernel's exact distances: every
    column's float64 term, summed with the 0/1 ``active`` weights (no gathered copies), in chunks
    of ~1M terms, ``n_threads`` chunks at a time."""
    on = (np.asarray(active) > 0).astype(np.float64)
    negw = -np.where(on > 0, weights, 0.0)
    step = max(1, (1 << 20) // aug.n)
    scratch = threading.local()  # each thread's float64 terms, reused from chunk to chunk

    def chunk(s: int) -> Tuple[int, np.ndarray]:
        t = targets[s:s + step]
        if not hasattr(scratch, "terms"):
            scratch.terms = np.empty(step * aug.n)
        vals = scratch.terms[:len(t) * aug.n].reshape(len(t), aug.n)
        np.multiply(aug.d2_rows(t), negw[None, :], out=vals)  # float32 distances times float64: exact as before
        np.exp(vals, out=vals)
        vals[np.arange(len(t)), t] = 0.0  # the self term
        return s, vals @ on

    return _by_chunks(len(targets), step, chunk, n_threads)


def parent_pass(
    aug: Augmented,
    lo: np.ndarray,
    hi: np.ndarray,
    radius: np.ndarray,
    image_index: Optional[np.ndarray] = None,
    *,
    n_threads: Optional[int] = None,
    progress: ProgressFn = None,
    use_native: bool = True,
) -> Tuple[np.ndarray, np.ndarray]:
    """Streaming parent pass: candidate parents in memory O(n), whatever the radius.

    Needs every feature's density interval ``[lo, hi]`` (rigorous bounds;
    ``lo == hi`` for an exact value). One more GEMM over all pairs; for every
    child j it keeps, of the features within ``radius[j]`` (and outside j's
    image when ``image_index`` is given):

    * those that certainly rank above j and lie within the float32 error bound
      of the nearest such one (the exact nearest is among them), and
    * all whose rank relative to j is uncertain (the caller settles them with
      exact densities).

    Returns directed pairs ``(child, cand)``: a superset of each child's nearest
    higher-ranked feature within its radius, usually a few per feature.
    """
    n = aug.n
    lo = np.ascontiguousarray(lo, dtype=np.float64)
    hi = np.ascontiguousarray(hi, dtype=np.float64)
    slack = aug.d2_slack(np.arange(n))
    rad2 = search_rad2(aug, radius)
    slack2 = (2.0 * slack).astype(np.float32)
    img = None if image_index is None else np.ascontiguousarray(image_index, dtype=np.int32)
    big = np.finfo(np.float32).max
    best = np.full(n, big, dtype=np.float32)
    starts = list(range(0, n, BLOCK))
    tasks = [(a, b) for ia, a in enumerate(starts) for b in starts[ia:]]

    def work(task):
        a, b = task
        a1, b1 = min(n, a + BLOCK), min(n, b + BLOCK)
        G = aug.d2_block(a, a1, b, b1) if use_native else aug.left[a:a1] @ aug.right[b:b1].T
        # a snapshot of the limits: stale values are larger, so they keep a superset
        limr = np.minimum(best[a:a1] + slack2[a:a1], big)
        limc = np.minimum(best[b:b1] + slack2[b:b1], big)
        return a, b, native.parent_tile(G, a, b, a == b, lo, hi, img, rad2[a:a1], rad2[b:b1], limr, limc,
                                        slack2[a:a1], slack2[b:b1], use_native=use_native)

    kept_child: List[np.ndarray] = []
    kept_cand: List[np.ndarray] = []
    kept_g: List[np.ndarray] = []
    held = 0
    threshold = 4 * n + (1 << 20)

    def prune():
        child, cand, g = np.concatenate(kept_child), np.concatenate(kept_cand), np.concatenate(kept_g)
        keep = (g <= best[child] + slack2[child]) | (native.rank_relation(lo, hi, cand, child) == 0)
        kept_child[:], kept_cand[:], kept_g[:] = [child[keep]], [cand[keep]], [g[keep]]
        return int(keep.sum())

    with tile_pool(n_threads) as run:
        for done, (a, b, (rmin, cmin, child, cand, g)) in enumerate(run(work, tasks), start=1):
            np.minimum(best[a:a + len(rmin)], rmin, out=best[a:a + len(rmin)])
            if a != b:
                np.minimum(best[b:b + len(cmin)], cmin, out=best[b:b + len(cmin)])
            kept_child.append(child)
            kept_cand.append(cand)
            kept_g.append(g)
            held += len(child)
            if held > threshold:
                held = prune()
                threshold = max(threshold, 2 * held)  # many uncertain pairs: do not prune every tile
            if progress is not None:
                progress(done, len(tasks))
    if not kept_child:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    prune()
    return kept_child[0], kept_cand[0]
