"""Online QuickMatch: clusters kept up to date as images arrive and leave.

:class:`OnlineQuickMatch` holds a growing (and, with :meth:`~OnlineQuickMatch.remove`,
shrinking) set of features. After every ``add`` or ``remove`` its ``labels``
are **identical** to batch :func:`dqm.quickmatch` (``kernel="quadratic"``) on
the features present, in arrival order. Each call returns a
:class:`~dqm.core.events.ChangeSet`: which clusters were created, grew,
merged, split, shrank or went, under stable cluster ids.

How it stays exact and local (the finite kernel makes every effect local):

1. **sigma** of a new feature comes from its own image (exact, as in batch).
   Images with a single feature take the median sigma of all others; when that
   median moves, those features are re-inserted with the new value.
2. **Densities** are exact integer sums (:mod:`dqm.core.density`), so adding
   or subtracting one contributor's terms gives the same bits as summing from
   scratch. A new feature ``i`` changes only densities within its support
   ``sigma_i``; its own density needs every contributor whose support reaches
   it. One float32 GEMM of the new rows against the stored features finds
   every pair within ``max(1, rho) * max(sigma)`` of either end (with the
   engine's rigorous error bound), and the pairs' exact distances are kept
   in a neighbour store. A removal subtracts the removed features' terms from
   the stored pairs: no GEMM.
3. **Parents** are recomputed only for features whose density value changed,
   that are new, whose parent left, or that have a new or re-ranked feature
   within their search radius ``rho * sigma``; from the stored neighbours.
4. **Merges** are replayed only in the components of the forest of mergeable
   tree edges (``d < rho * min(sigma_child, sigma_parent)``) that contain a
   changed edge, a new or a removed feature. Break/merge runs independently
   in every such component, so the others keep their clusters.

Guarantees: ``labels`` equal batch after every call (the tests check it at
every step); clusters keep their id while they survive; a change set's events
replayed over the previous assignment give the new one.

Worst case: the GEMM of an ``add`` costs (new rows) x (all rows), a batch
recompute (all rows)^2 / 2, so adding 1 of m equal images costs about 2/m of
a batch. The neighbour store holds every pair within ``max(1, rho) * sigma``
of either end: tens per feature on SIFT at rho <= 1, but up to O(n^2) on data
where most features lie within each other's sigma (a quarter of all pairs on
dqm.synthetic at rho 1.1), where batch's streaming pass is the better tool.
A change can reach a whole component of the forest: merges are replayed in
Python, so one that spans most features costs about a batch tree pass.
Changing the lonely-image sigma (see 1) re-inserts every single-feature image.
"""
from __future__ import annotations

import time
from typing import Dict, List, Optional, Tuple

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from .. import validation as V
from . import density, native, pairs, tree
from .clustering import DEFAULT_RATIO_DENSITY, DEFAULT_RHO, PARENT_MODES, QuickMatchResult, kernel_weights
from .events import ChangeSet, ClusterEvent

#: margin on stored-pair radii, so rounding never leaves a needed pair out
_MARGIN = 1.0 + 1e-6


class _Store:
    """Growable per-slot arrays (a slot is one feature's row; re-inserted features get a new slot)."""

    FIELDS = {"key": np.int64, "image": np.int64, "sigma": np.float64, "alive": bool, "hi": np.float64,
              "lo": np.float64, "dvalue": np.float64, "parent": np.int64, "pdist": np.float64,
              "comp": np.int64, "cid": np.int64, "dup": bool, "norm2": np.float64}

    def __init__(self, dim: int, exact_dtype):
        self.n = 0
        self.dim = dim
        cap = 16
        for name, dt in self.FIELDS.items():
            setattr(self, name, np.zeros(cap, dt))
        self.left = np.zeros((cap, dim + 2), np.float32)
        self.right = np.zeros((cap, dim + 2), np.float32)
        self.X = np.zeros((cap, dim), exact_dtype)

    def grow(self, extra: int) -> np.ndarray:
        need = self.n + extra
        cap = len(self.key)
        if need > cap:
            cap = max(need, 2 * cap)
            for name in list(self.FIELDS) + ["left", "right", "X"]:
                old = getattr(self, name)
                new = np.zeros((cap,) + old.shape[1:], old.dtype)
                new[:self.n] = old[:self.n]
                setattr(self, name, new)
        slots = np.arange(self.n, need)
        self.n = need
        return slots

    def widen_exact(self) -> None:
        """Store exact copies as float64 (a float descriptor arrived after integer ones)."""
        self.X = self.X.astype(np.float64)

    def compact(self) -> np.ndarray:
        """Drop dead slots; returns the map old slot -> new slot (-1: dropped)."""
        keep = np.flatnonzero(self.alive[:self.n])
        mapping = np.full(self.n, -1, np.int64)
        mapping[keep] = np.arange(len(keep))
        for name in list(self.FIELDS) + ["left", "right", "X"]:
            old = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(old[keep]))
        self.n = len(keep)
        return mapping


class _EdgeStore:
    """Directed neighbour pairs ``a -> b`` with exact squared distances, looked up by ``a``.

    Sorted runs merged as they grow (a log-structured store): appending a run
    costs its sort, a lookup one binary search per run.
    """

    def __init__(self):
        self.runs: List[Tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def __len__(self) -> int:
        return sum(len(r[0]) for r in self.runs)

    def add(self, a: np.ndarray, b: np.ndarray, d2: np.ndarray, alive: np.ndarray) -> None:
        if len(a):
            order = np.argsort(a, kind="stable")
            self.runs.append((a[order], b[order], d2[order]))
        while len(self.runs) >= 2 and len(self.runs[-1][0]) * 2 >= len(self.runs[-2][0]):
            (a1, b1, d1), (a2, b2, d2_) = self.runs[-2], self.runs[-1]
            a_, b_, d_ = np.concatenate([a1, a2]), np.concatenate([b1, b2]), np.concatenate([d1, d2_])
            keep = alive[a_] & alive[b_]
            a_, b_, d_ = a_[keep], b_[keep], d_[keep]
            order = np.argsort(a_, kind="stable")
            self.runs[-2:] = [(a_[order], b_[order], d_[order])]

    def query(self, nodes: np.ndarray, alive: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Edges ``a -> b`` with ``a`` in ``nodes`` (sorted, unique) and ``b`` alive."""
        out_a, out_b, out_d = [], [], []
        for a, b, d2 in self.runs:
            lo = np.searchsorted(a, nodes, "left")
            hi = np.searchsorted(a, nodes, "right")
            cnt = hi - lo
            total = int(cnt.sum())
            if total == 0:
                continue
            starts = np.repeat(lo - np.cumsum(cnt) + cnt, cnt)
            idx = np.arange(total) + starts
            bb = b[idx]
            ok = alive[bb]
            out_a.append(a[idx][ok])
            out_b.append(bb[ok])
            out_d.append(d2[idx][ok])
        if not out_a:
            z = np.zeros(0, np.int64)
            return z, z, np.zeros(0)
        return np.concatenate(out_a), np.concatenate(out_b), np.concatenate(out_d)

    def remap(self, mapping: np.ndarray) -> None:
        if not self.runs:
            return
        a = mapping[np.concatenate([r[0] for r in self.runs])]
        b = mapping[np.concatenate([r[1] for r in self.runs])]
        d = np.concatenate([r[2] for r in self.runs])
        keep = (a >= 0) & (b >= 0)
        a, b, d = a[keep], b[keep], d[keep]
        order = np.argsort(a, kind="stable")
        self.runs = [(a[order], b[order], d[order])] if len(a) else []


class OnlineQuickMatch:
    """QuickMatch whose clusters follow a stream of images (quadratic kernel).

    >>> om = OnlineQuickMatch(rho=0.9)                 # doctest: +SKIP
    >>> changes = om.add(descriptors, image_ids)       # one or more new images
    >>> for event in changes.events: print(event)      # doctest: +SKIP
    >>> om.labels                                      # == dqm.quickmatch(..., kernel="quadratic").labels
    >>> om.remove(image_id)                            # a camera leaves, a frame expires

    Parameters are those of :func:`dqm.quickmatch`: ``rho`` (merge ratio),
    ``kernel`` (only ``"quadratic"``: a Gaussian kernel reaches every feature,
    so one image would change every density) and ``parent`` (``"any"`` or
    ``"other-image"``). ``n_threads``: worker threads of the GEMM.

    Features get **keys** 0, 1, 2, ... in arrival order (never reused);
    clusters get stable **ids**. See the module docstring for what is exact,
    what is local and the worst case.
    """

    def __init__(self, rho: float = DEFAULT_RHO, kernel: str = "quadratic", parent: str = "any",
                 n_threads: Optional[int] = None):
        self.rho = V.check_positive(rho, "rho")
        if kernel != "quadratic":
            raise V.InputError(f"online QuickMatch needs the finite kernel (kernel='quadratic'), got {kernel!r}: "
                               "a Gaussian term reaches every feature, so one image would change every density")
        self.kernel = kernel
        self.parent_mode = V.check_choice(parent, "parent", PARENT_MODES)
        self.n_threads = pairs.default_threads() if n_threads is None else max(1, int(n_threads))
        self._s: Optional[_Store] = None
        self._edges = _EdgeStore()
        self._groups: Dict[bytes, List[int]] = {}  # exact descriptor bytes -> present slots with them
        self._group_key: Dict[int, bytes] = {}
        self._image_slots: Dict[int, np.ndarray] = {}
        self._next_key = 0
        self._next_cid = 0
        self._next_comp = 0
        self._lonely_sigma = 0.0
        self._center: Optional[np.ndarray] = None
        self._max_norm2 = 0.0
        self._order_cache: Optional[np.ndarray] = None

    # ------------------------------------------------------------------ views
    def _order(self) -> np.ndarray:
        """Alive slots in key (arrival) order: the batch order."""
        if self._order_cache is None:
            s = self._s
            if s is None:
                self._order_cache = np.zeros(0, np.int64)
            else:
                alive = np.flatnonzero(s.alive[:s.n])
                self._order_cache = alive[np.argsort(s.key[alive], kind="stable")]
        return self._order_cache

    @property
    def n_features(self) -> int:
        return len(self._order())

    @property
    def images(self) -> np.ndarray:
        """Image ids present, sorted."""
        return np.array(sorted(self._image_slots), np.int64)

    @property
    def keys(self) -> np.ndarray:
        """Key of every present feature, in arrival order."""
        return self._s.key[self._order()].copy() if self._s is not None else np.zeros(0, np.int64)

    @property
    def image_ids(self) -> np.ndarray:
        return self._s.image[self._order()].copy() if self._s is not None else np.zeros(0, np.int64)

    @property
    def descriptors(self) -> np.ndarray:
        if self._s is None:
            return np.zeros((0, 0))
        return self._s.X[self._order()].copy()

    @property
    def cluster_ids(self) -> np.ndarray:
        """Stable cluster id of every present feature, in arrival order."""
        return self._s.cid[self._order()].copy() if self._s is not None else np.zeros(0, np.int64)

    @property
    def labels(self) -> np.ndarray:
        """Cluster labels numbered as batch :func:`dqm.quickmatch` numbers them (by lowest feature index)."""
        return tree.canonical_labels(self.cluster_ids)

    def assignment(self) -> Dict[int, int]:
        """Feature key -> stable cluster id, for every present feature."""
        return dict(zip(self.keys.tolist(), self.cluster_ids.tolist()))

    def result(self) -> QuickMatchResult:
        """The present state as a :class:`QuickMatchResult` (densities exact; parents as indices)."""
        order = self._order()
        if self._s is None or len(order) == 0:
            z = np.zeros(0)
            return QuickMatchResult(np.zeros(0, np.int64), z, z, np.zeros(0, np.int64), z, np.zeros(0, np.int64),
                                    self.rho, DEFAULT_RATIO_DENSITY, self.kernel, self.parent_mode)
        s = self._s
        pos = np.full(s.n, -1, np.int64)
        pos[order] = np.arange(len(order))
        par = s.parent[order]
        parent = np.where(par >= 0, pos[np.maximum(par, 0)], -1)
        return QuickMatchResult(self.labels, s.sigma[order].copy(), s.dvalue[order].copy(), parent,
                                s.pdist[order].copy(), s.image[order].copy(), self.rho, DEFAULT_RATIO_DENSITY,
                                self.kernel, self.parent_mode, {"n_stored_pairs": float(len(self._edges))})

    # ------------------------------------------------------------------ API
    def add(self, descriptors, image_ids) -> ChangeSet:
        """Add the features of one or more new images; returns what changed.

        Refused with :class:`dqm.InputError`, before any change, for bad
        descriptors (shape, NaN, dimension unlike earlier ones), bad image ids
        and an image id already present (remove it first).
        """
        t0 = time.perf_counter()
        X = V.check_descriptors(descriptors)
        ids = V.check_image_ids(image_ids, len(X))
        V.check_magnitude(X)  # every later add must share the scale: refused here, not rescaled
        if self._s is not None and len(X) and X.shape[1] != self._s.dim:
            raise V.InputError(f"descriptors have {X.shape[1]} dimensions, earlier ones {self._s.dim}")
        present = sorted(set(np.unique(ids).tolist()) & set(self._image_slots))
        if present:
            raise V.InputError(f"image {present[0]} is already present; remove it before adding it again")
        if len(X) == 0:
            return ChangeSet([], np.zeros(0, np.int64), np.zeros(0, np.int64), {"time": 0.0})
        raw = np.asarray(descriptors)
        integral = raw.dtype == np.uint8 or (np.all(X == np.round(X)) and X.min() >= 0 and X.max() <= 255)
        if self._s is None:
            self._s = _Store(X.shape[1], np.uint8 if integral else np.float64)
            self._center = X.mean(axis=0)
        elif not integral and self._s.X.dtype == np.uint8:
            self._s.widen_exact()
        # sigma of the new features from their own images (exact, as batch computes it)
        _, local = np.unique(ids, return_inverse=True)
        local = local.ravel().astype(np.int64)
        sig = pairs.nearest_same_image(pairs.Augmented(X), local, int(local.max()) + 1, n_threads=self.n_threads)
        keys = np.arange(self._next_key, self._next_key + len(X), dtype=np.int64)
        self._next_key += len(X)
        new = self._insert(X, ids, keys, sig)
        return self._update(new, np.zeros(0, np.int64), removed_keys=np.zeros(0, np.int64), added_keys=keys,
                            t0=t0)

    def remove(self, image_id) -> ChangeSet:
        """Remove every feature of image ``image_id``; returns what changed."""
        t0 = time.perf_counter()
        try:
            img = int(image_id)
        except (TypeError, ValueError):
            raise V.InputError(f"image id must be an integer, got {image_id!r}") from None
        if img not in self._image_slots:
            raise V.InputError(f"image {img} is not present (present: {len(self._image_slots)} images)")
        slots = self._image_slots.pop(img)
        keys = self._s.key[slots].copy()
        return self._update(np.zeros(0, np.int64), slots, removed_keys=keys, added_keys=np.zeros(0, np.int64),
                            t0=t0)

    # ------------------------------------------------------------------ internals
    def _insert(self, X: np.ndarray, ids: np.ndarray, keys: np.ndarray, sig: np.ndarray) -> np.ndarray:
        """New slots for features (sigma NaN: alone in its image, filled in by :meth:`_update`)."""
        s = self._s
        slots = s.grow(len(X))
        s.key[slots] = keys
        s.image[slots] = ids
        s.sigma[slots] = sig
        s.alive[slots] = True
        s.hi[slots] = 0
        s.lo[slots] = 0
        s.parent[slots] = -1
        s.pdist[slots] = np.inf
        s.cid[slots] = -1
        s.comp[slots] = -1
        s.X[slots] = X if s.X.dtype != np.uint8 else X.astype(np.uint8)
        s.left[slots], s.right[slots], n2 = pairs.augmented_rows(X - self._center)
        s.norm2[slots] = n2
        self._max_norm2 = max(self._max_norm2, float(n2.max()))
        for img in np.unique(ids).tolist():
            mine = slots[ids == img]
            old = self._image_slots.get(img)
            self._image_slots[img] = mine if old is None else np.concatenate([old, mine])
        byte_rows = X + 0.0  # float64 bytes whatever the store's type; -0.0 -> 0.0 as duplicate_groups does
        for slot, row in zip(slots.tolist(), byte_rows):
            key = row.tobytes()
            members = self._groups.setdefault(key, [])
            members.append(slot)
            self._group_key[slot] = key
            if len(members) > 1:
                s.dup[members] = True
        return slots

    def _weights(self, slots: np.ndarray) -> np.ndarray:
        w, _ = kernel_weights(self._s.sigma[slots], "quadratic", DEFAULT_RATIO_DENSITY)
        return w

    def _add_terms(self, contrib: np.ndarray, target: np.ndarray, d2: np.ndarray, sign: int) -> None:
        """Add (sign 1) or subtract (-1) contributor terms to targets' exact sums."""
        s = self._s
        act = s.sigma[contrib] > 0
        contrib, target, d2 = contrib[act], target[act], d2[act]
        if len(contrib) == 0:
            return
        terms = density.quadratic_terms(d2, self._weights(contrib))
        pos = terms > 0
        hi, lo = density.term_parts(terms[pos])
        t = target[pos]
        # integer part sums (density.ExactSums' representation), exact in float64 in any order
        s.hi[:s.n] += sign * np.bincount(t, weights=hi, minlength=s.n)
        s.lo[:s.n] += sign * np.bincount(t, weights=lo, minlength=s.n)

    def _pairs(self, rows: np.ndarray, cols: np.ndarray, *, triangle: bool, rows_only: bool
               ) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Pairs (row, col) within ``max(1, rho) * sigma`` (with a margin) of the row's end, or of
        either end unless ``rows_only``, with exact squared distances. ``triangle``: ``rows`` also
        take part as columns, each unordered pair among them once. One float32 GEMM per block with
        the engine's rigorous error bound, then exact distances of the survivors."""
        s = self._s
        n = s.n
        reach = max(1.0, self.rho) * s.sigma[:n] * _MARGIN
        slack = pairs.error_gamma(s.dim) * (s.norm2[:n] + self._max_norm2) + 1e-30  # as Augmented.d2_slack
        rad2 = (reach ** 2 + slack).astype(np.float32)
        rad2c = np.full(n, -np.inf, np.float32) if rows_only else rad2
        B = pairs.BLOCK
        row_blocks = [rows[i:i + B] for i in range(0, len(rows), B)]
        tasks = [(r, cols[j:j + B], False) for r in row_blocks for j in range(0, len(cols), B)]
        if triangle:
            tasks += [(row_blocks[i], row_blocks[j], i == j) for i in range(len(row_blocks))
                      for j in range(i, len(row_blocks))]
        zeros = np.zeros(max(B, 1), np.float32)

        def work(task):
            rb, cb, diagonal = task
            G = np.ascontiguousarray(s.left[rb] @ s.right[cb].T)
            dr, er, dc, ec = np.zeros(len(rb)), np.zeros(len(rb)), np.zeros(len(cb)), np.zeros(len(cb))
            r, c = native.tile_sym(G, zeros[:len(cb)], zeros[:len(cb)], zeros[:len(rb)], zeros[:len(rb)],
                                   "quadratic", rad2[rb], rad2c[cb], dr, er, dc, ec)
            if diagonal:
                keep = c > r
                r, c = r[keep], c[keep]
            return rb[r], cb[c]

        ra, ca = [], []
        with pairs.tile_pool(self.n_threads) as run:
            for r, c in run(work, tasks):
                ra.append(r)
                ca.append(c)
        a = np.concatenate(ra) if ra else np.zeros(0, np.int64)
        b = np.concatenate(ca) if ca else np.zeros(0, np.int64)
        d2 = pairs.exact_sq_distances(s.X, a, b)
        far = reach[a] if rows_only else np.maximum(reach[a], reach[b])
        keep = (d2 < far * far) | (d2 == 0)
        return a[keep], b[keep], d2[keep]

    def _group_value(self, slots: np.ndarray) -> np.ndarray:
        """Density value (1 + others) of slots, computed as batch computes it: duplicates take their
        group's first member's value, with zero-sigma duplicates added as integers after the exact sum."""
        s = self._s
        out = 1.0 + density.parts_value(s.hi[slots], s.lo[slots])
        for k in np.flatnonzero(s.dup[slots]).tolist():
            members = self._groups[self._group_key[int(slots[k])]]
            first = min(members, key=lambda m: s.key[m])
            b = density.parts_value(s.hi[first], s.lo[first])
            zc = sum(1 for m in members if s.sigma[m] == 0)
            out[k] = 1.0 + ((b + zc) - (1 if s.sigma[first] == 0 else 0))
        return out

    def _update(self, new: np.ndarray, gone: np.ndarray, *, removed_keys: np.ndarray, added_keys: np.ndarray,
                t0: float) -> ChangeSet:
        s = self._s
        stats: Dict[str, float] = {}
        n_before = int(s.alive[:s.n].sum()) - len(new)
        # -- sigma of single-feature images: the median of all finite sigmas (re-insert when it moves)
        s.alive[gone] = False
        lonely_new = new[np.isnan(s.sigma[new])]
        lonely_old = np.array([sl[0] for img, sl in self._image_slots.items() if len(sl) == 1], np.int64)
        lonely_old = lonely_old[~np.isin(lonely_old, new)]
        if len(lonely_new) or len(lonely_old):
            alive = np.flatnonzero(s.alive[:s.n])
            single = np.zeros(s.n, bool)
            single[lonely_old] = True
            single[lonely_new] = True
            finite = s.sigma[alive[~single[alive]]]
            value = float(np.median(finite)) if len(finite) else 0.0
            s.sigma[lonely_new] = value
            if len(lonely_old) and value != self._lonely_sigma:
                # re-insert: the old slots leave (their terms subtracted), new slots with the new sigma arrive
                img = s.image[lonely_old]
                X = s.X[lonely_old].astype(np.float64)
                keys = s.key[lonely_old].copy()
                for i in img.tolist():
                    self._image_slots.pop(i)
                s.alive[lonely_old] = False
                fresh = self._insert(X, img, keys, np.full(len(keys), value))
                gone = np.concatenate([gone, lonely_old])
                new = np.concatenate([new, fresh])
            self._lonely_sigma = value
        self._order_cache = None
        # -- densities: subtract what left, add what arrived
        t = time.perf_counter()
        changed_groups = set()
        is_new = np.zeros(s.n, bool)
        is_new[new] = True
        alive_cols = np.flatnonzero(s.alive[:s.n] & ~is_new)
        touched_d = []
        if len(gone):
            ga, gb, gd = self._pairs(gone, alive_cols, triangle=False, rows_only=True)
            self._add_terms(ga, gb, gd, -1)
            touched_d.append(gb)
            for slot in gone.tolist():
                key = self._group_key.pop(slot)
                members = self._groups[key]
                members.remove(slot)
                if members:
                    changed_groups.add(key)
                    if len(members) == 1:
                        s.dup[members] = False
                else:
                    del self._groups[key]
        if len(new):
            a, b, d2 = self._pairs(new, alive_cols, triangle=True, rows_only=False)
            self._add_terms(a, b, d2, +1)
            self._add_terms(b, a, d2, +1)
            touched_d += [a, b]
            # the neighbour store keeps what parents need: pairs within rho * sigma of either end
            d = np.sqrt(d2)
            near = (d < self.rho * s.sigma[a] * _MARGIN) | (d < self.rho * s.sigma[b] * _MARGIN)
            a, b, d2 = a[near], b[near], d2[near]
            self._edges.add(np.concatenate([a, b]), np.concatenate([b, a]), np.concatenate([d2, d2]), s.alive)
            for slot in new.tolist():
                key = self._group_key[slot]
                if len(self._groups[key]) > 1:
                    changed_groups.add(key)
        stats["time_density"] = time.perf_counter() - t
        t = time.perf_counter()
        cand = np.unique(np.concatenate(touched_d + [new])) if touched_d or len(new) else np.zeros(0, np.int64)
        extra = [m for key in changed_groups for m in self._groups.get(key, [])]
        if extra:
            cand = np.union1d(cand, np.array(extra, np.int64))
        cand = cand[s.alive[cand]]
        prev = s.dvalue[:s.n].copy()
        s.dvalue[cand] = self._group_value(cand)
        dchanged = cand[(s.dvalue[cand] != prev[cand]) & ~is_new[cand]]
        stats["density_changed"] = float(len(dchanged))
        # -- parents: recompute where a density order or a candidate may have changed
        was_gone = np.zeros(s.n, bool)
        was_gone[gone] = True
        alive_idx = np.flatnonzero(s.alive[:s.n])
        orphans = alive_idx[(s.parent[alive_idx] >= 0) & was_gone[np.maximum(s.parent[alive_idx], 0)]]
        movers = np.union1d(dchanged, new)
        A = np.unique(np.concatenate([new, orphans, self._triggered(movers, prev, is_new)]))
        old_parent = s.parent[A].copy()
        old_pdist = s.pdist[A].copy()
        self._select_parents(A)
        pchanged = A[(s.parent[A] != old_parent) | (s.pdist[A] != old_pdist)]
        stats["parents_recomputed"] = float(len(A))
        stats["parents_changed"] = float(len(np.setdiff1d(pchanged, new)))
        stats["time_parents"] = time.perf_counter() - t
        # -- merges: replay the components that hold a changed edge, a new or a removed feature
        t = time.perf_counter()
        old_eligible_parent = np.where(self._eligible(A, old_parent, old_pdist), old_parent, -1)
        new_eligible_parent = np.where(self._eligible(A, s.parent[A], s.pdist[A]), s.parent[A], -1)
        edge_changed = (old_eligible_parent != new_eligible_parent) | (
            (new_eligible_parent >= 0) & (old_pdist != s.pdist[A]))
        touched = np.concatenate([A[edge_changed], old_eligible_parent[edge_changed],
                                  new_eligible_parent[edge_changed], gone])
        touched = touched[touched >= 0]
        comps = np.unique(s.comp[touched])
        comps = comps[comps >= 0]
        region = np.union1d(alive_idx[np.isin(s.comp[alive_idx], comps)], new)
        region = region[np.argsort(s.key[region], kind="stable")]
        old_members = np.union1d(region[~is_new[region]], gone)
        old_cid = {int(k): int(c) for k, c in zip(s.key[old_members], s.cid[old_members]) if c >= 0}
        gone_keys = set(int(k) for k in removed_keys)
        local_labels = self._replay(region)
        stats["replayed"] = float(len(region))
        gone_images = dict(zip(s.key[gone].tolist(), s.image[gone].tolist()))
        events = self._events(region, local_labels, old_cid, gone_keys, gone_images,
                              set(int(k) for k in added_keys))
        stats["time_merges"] = time.perf_counter() - t
        self._maybe_compact()
        stats["features_before"] = float(n_before)
        stats["time"] = time.perf_counter() - t0
        return ChangeSet(events, np.asarray(added_keys, np.int64), np.asarray(removed_keys, np.int64), stats)

    def _triggered(self, movers: np.ndarray, prev: np.ndarray, is_new: np.ndarray) -> np.ndarray:
        """Features whose parent may change because a mover (new, or density changed) near them did:
        the mover now ranks above them and is nearer than their parent, or it was their parent and no
        longer ranks above them. Both ends of every stored pair at a mover are checked as the child."""
        s = self._s
        ka, kb, kd = self._edges.query(movers, s.alive)
        d = np.sqrt(kd)
        child = np.concatenate([kb, ka])
        cand = np.concatenate([ka, kb])
        d = np.concatenate([d, d])
        ok = d < self.rho * s.sigma[child]
        if self.parent_mode == "other-image":
            ok &= s.image[child] != s.image[cand]
        child, cand, d = child[ok], cand[ok], d[ok]
        now = tree.rank_order(s.dvalue[cand], s.dvalue[child], s.key[cand], s.key[child])
        before = tree.rank_order(prev[cand], prev[child], s.key[cand], s.key[child]) & ~is_new[cand] & ~is_new[child]
        par = s.parent[child]
        pd = s.pdist[child]
        pkey = np.where(par >= 0, s.key[np.maximum(par, 0)], np.iinfo(np.int64).max)
        nearer = (d < pd) | ((d == pd) & (s.key[cand] < pkey))
        lost = (cand == par) & ~now
        gained = now & ~before & nearer
        return np.unique(child[lost | gained])

    def _select_parents(self, A: np.ndarray) -> None:
        """Parents of slots ``A`` from the stored neighbours (the batch rule, keys as indices)."""
        s = self._s
        a, b, d2 = self._edges.query(A, s.alive)
        d = np.sqrt(d2)
        keep = d < self.rho * s.sigma[a]
        if self.parent_mode == "other-image":
            keep &= s.image[a] != s.image[b]
        a, b, d = a[keep], b[keep], d[keep]
        above = tree.rank_order(s.dvalue[b], s.dvalue[a], s.key[b], s.key[a])
        a, b, d = a[above], b[above], d[above]
        parent, pdist, _ = tree.nearest_candidates(a, b, d, s.n, tie=s.key[b])
        s.parent[A] = parent[A]
        s.pdist[A] = pdist[A]

    def _eligible(self, child: np.ndarray, parent: np.ndarray, pdist: np.ndarray) -> np.ndarray:
        """Tree edges that can merge at all: ``d < rho * min(sigma_child, sigma_parent)``."""
        s = self._s
        ok = parent >= 0
        p = np.maximum(parent, 0)
        return ok & (pdist < self.rho * np.minimum(s.sigma[child], s.sigma[p]))

    def _replay(self, region: np.ndarray) -> np.ndarray:
        """Break/merge in ``region`` (whole components, key order); sets components, returns local labels."""
        s = self._s
        m = len(region)
        if m == 0:
            return np.zeros(0, np.int64)
        pos = np.full(s.n, -1, np.int64)
        pos[region] = np.arange(m)
        par = s.parent[region]
        elig = self._eligible(region, par, s.pdist[region])
        lp = np.where(elig, pos[np.maximum(par, 0)], -1)
        if (elig & (lp < 0)).any():  # an eligible edge leaving the region: the region is not whole components
            raise AssertionError("online QuickMatch: merge region is not closed under tree edges")
        labels = tree.merge_clusters(lp, np.where(lp >= 0, s.pdist[region], np.inf), s.sigma[region],
                                     s.image[region], self.rho)
        j = np.flatnonzero(lp >= 0)
        g = coo_matrix((np.ones(len(j)), (j, lp[j])), shape=(m, m))
        _, comp = connected_components(g, directed=False)
        s.comp[region] = comp + self._next_comp
        self._next_comp += int(comp.max()) + 1
        return labels

    def _events(self, region: np.ndarray, local: np.ndarray, old_cid: Dict[int, int], gone_keys: set,
                gone_images: Dict[int, int], added_keys: set) -> List[ClusterEvent]:
        """Stable ids for the region's new clusters, and the events that lead from the old ids to them."""
        s = self._s
        events: List[ClusterEvent] = []
        key_image = {}
        rkeys = s.key[region]
        for k, img in zip(rkeys.tolist(), s.image[region].tolist()):
            key_image[k] = img
        # removed features, per old cluster
        by_cid: Dict[int, List[int]] = {}
        for k, c in old_cid.items():
            by_cid.setdefault(c, []).append(k)
        gone_by: Dict[int, List[int]] = {}
        for k in sorted(gone_keys):
            if k in old_cid:
                gone_by.setdefault(old_cid[k], []).append(k)
        for c in sorted(gone_by):
            ks = gone_by[c]
            kind = "removed" if len(ks) == len(by_cid[c]) else "shrunk"
            events.append(ClusterEvent(kind, c, np.array(ks, np.int64),
                                       np.array([gone_images.get(k, -1) for k in ks], np.int64)))
        # overlaps of surviving old clusters with new local clusters
        overlap: Dict[Tuple[int, int], int] = {}
        for k, lab in zip(rkeys.tolist(), local.tolist()):
            c = old_cid.get(k)
            if c is not None and k not in gone_keys:
                overlap[(c, lab)] = overlap.get((c, lab), 0) + 1
        inherit: Dict[int, int] = {}
        taken = set()
        for (c, lab), cnt in sorted(overlap.items(), key=lambda kv: (-kv[1], kv[0][0], kv[0][1])):
            if lab in inherit or c in taken:
                continue
            inherit[lab] = c
            taken.add(c)
        born = set()
        new_id = np.empty(len(local), np.int64)
        ids_of_label: Dict[int, int] = {}
        for lab in sorted(set(local.tolist())):
            if lab in inherit:
                ids_of_label[lab] = inherit[lab]
            else:
                ids_of_label[lab] = self._next_cid
                born.add(self._next_cid)
                self._next_cid += 1
        for i, lab in enumerate(local.tolist()):
            new_id[i] = ids_of_label[lab]
        s.cid[region] = new_id
        # moves of surviving features between clusters
        moves: Dict[Tuple[int, int], List[int]] = {}
        for k, t in zip(rkeys.tolist(), new_id.tolist()):
            c = old_cid.get(k)
            if c is not None and c != t:
                moves.setdefault((c, t), []).append(k)
        announced = set()
        last_part: Dict[int, Tuple[int, int]] = {}
        for (c, t) in sorted(moves):
            if c not in taken:
                last_part[c] = (c, t)
        for (c, t) in sorted(moves):
            ks = moves[(c, t)]
            kind = "merged" if last_part.get(c) == (c, t) else "split"
            is_new = t in born and t not in announced
            announced.add(t)
            events.append(ClusterEvent(kind, t, np.array(ks, np.int64), np.array([key_image[k] for k in ks]),
                                       source=c, new=is_new))
        # arrivals
        arrivals: Dict[int, List[int]] = {}
        for k, t in zip(rkeys.tolist(), new_id.tolist()):
            if k in added_keys:
                arrivals.setdefault(t, []).append(k)
        for t in sorted(arrivals):
            ks = arrivals[t]
            kind = "created" if t in born and t not in announced else "grown"
            events.append(ClusterEvent(kind, t, np.array(ks, np.int64), np.array([key_image[k] for k in ks]),
                                       new=t in born))
        return events

    def _maybe_compact(self) -> None:
        s = self._s
        dead = s.n - int(s.alive[:s.n].sum())
        if dead <= max(4096, s.n // 4):
            return
        mapping = s.compact()
        self._edges.remap(mapping)
        par = s.parent[:s.n]
        s.parent[:s.n] = np.where(par >= 0, mapping[np.maximum(par, 0)], -1)
        self._groups = {k: [int(mapping[m]) for m in v] for k, v in self._groups.items()}
        self._group_key = {int(mapping[k]): v for k, v in self._group_key.items() if mapping[k] >= 0}
        self._image_slots = {i: mapping[v] for i, v in self._image_slots.items()}
        self._order_cache = None
