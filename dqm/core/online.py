"""Online QuickMatch: clusters kept up to date as images arrive and leave.

:class:`OnlineQuickMatch` holds a growing (and, with :meth:`~OnlineQuickMatch.remove`,
shrinking) set of features. After every ``add`` or ``remove`` its ``labels``
are **identical** to batch :func:`dqm.quickmatch` (``kernel="quadratic"``) on
the features present, in arrival order. Each call returns a
:class:`~dqm.core.events.ChangeSet`: which clusters were created, grew,
merged, split, shrank or went, under stable cluster ids.

How it stays exact and local (the finite kernel makes every effect local):

1. **sigma** of a new feature comes from its own image (exact, as in batch).
   Images with a single feature take the median sigma of all others (batch's
   rule, :func:`dqm.core.clustering.lonely_sigma`); when that median moves,
   those features are re-inserted with the new value.
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

Where the parts live: this module is the public API; :mod:`dqm.core.online_store`
holds the stores, :mod:`dqm.core.online_density` the pair search and exact
sums, :mod:`dqm.core.online_update` the update engine (steps 1-4) and
:mod:`dqm.core.online_identity` the stable ids and events.
"""
from __future__ import annotations

import time
from typing import Dict, Optional

import numpy as np

from .. import validation as V
from . import pairs, tree
from .clustering import QuickMatchResult
from .events import ChangeSet, ClusterEvent
from .online_update import UpdateEngine
from .params import DEFAULT_PARENT, DEFAULT_RATIO_DENSITY, DEFAULT_RHO, FINITE_KERNEL, QuickMatchParams

__all__ = ["ChangeSet", "ClusterEvent", "OnlineQuickMatch"]


class OnlineQuickMatch:
    """QuickMatch whose clusters follow a stream of images (quadratic kernel).

    >>> om = OnlineQuickMatch(rho=0.9)                 # doctest: +SKIP
    >>> changes = om.add(descriptors, image_ids)       # one or more new images
    >>> for event in changes.events: print(event)      # doctest: +SKIP
    >>> om.labels                                      # == dqm.quickmatch(..., kernel="quadratic").labels
    >>> om.remove(image_id)                            # a camera leaves, a frame expires

    Parameters are those of :func:`dqm.quickmatch`, held and validated as one
    :class:`~dqm.core.params.QuickMatchParams` (:attr:`params`): ``rho`` (merge
    ratio), ``kernel`` (only ``"quadratic"``, the default: a Gaussian kernel
    reaches every feature, so one image would change every density), ``parent``
    (``"any"`` or ``"other-image"``) and ``ratio_density`` (accepted so that
    ``OnlineQuickMatch(**params.as_kwargs())`` works; the quadratic kernel
    ignores it). ``n_threads``: worker threads of the GEMM.

    Features get **keys** 0, 1, 2, ... in arrival order (never reused);
    clusters get stable **ids**. See the module docstring for what is exact,
    what is local and the worst case.
    """

    def __init__(self, rho: float = DEFAULT_RHO, kernel: str = FINITE_KERNEL, parent: str = DEFAULT_PARENT,
                 n_threads: Optional[int] = None, ratio_density: float = DEFAULT_RATIO_DENSITY):
        self.params = QuickMatchParams(rho=rho, kernel=kernel, parent=parent, ratio_density=ratio_density
                                       ).validated(finite=True, engine="online QuickMatch")
        self.n_threads = pairs.default_threads() if n_threads is None else max(1, int(n_threads))
        self._engine = UpdateEngine(self.params, self.n_threads)

    # ------------------------------------------------------------------ parameters
    @property
    def rho(self) -> float:
        return self.params.rho

    @property
    def kernel(self) -> str:
        return self.params.kernel

    @property
    def parent_mode(self) -> str:
        return self.params.parent

    def get_params(self, deep: bool = True) -> Dict[str, object]:
        """The constructor's arguments (scikit-learn style)."""
        return {**self.params.as_kwargs(), "n_threads": self.n_threads}

    # ------------------------------------------------------------------ views
    def _order(self) -> np.ndarray:
        return self._engine.order()

    @property
    def n_features(self) -> int:
        return len(self._order())

    @property
    def n_stored_pairs(self) -> int:
        """Directed pairs in the neighbour store (the memory the update keeps beyond the features)."""
        return len(self._engine.edges)

    @property
    def images(self) -> np.ndarray:
        """Image ids present, sorted."""
        return np.array(sorted(self._engine.image_slots), np.int64)

    def _column(self, name: str, empty: np.ndarray) -> np.ndarray:
        """A copy of the store's column ``name`` for the present features, in arrival order."""
        s = self._engine.store
        return getattr(s, name)[self._order()].copy() if s is not None else empty

    @property
    def keys(self) -> np.ndarray:
        """Key of every present feature, in arrival order."""
        return self._column("key", np.zeros(0, np.int64))

    @property
    def image_ids(self) -> np.ndarray:
        return self._column("image", np.zeros(0, np.int64))

    @property
    def descriptors(self) -> np.ndarray:
        """Present descriptors in arrival order (uint8 while every one is an integer in 0..255)."""
        return self._column("X", np.zeros((0, 0)))

    @property
    def cluster_ids(self) -> np.ndarray:
        """Stable cluster id of every present feature, in arrival order."""
        return self._column("cid", np.zeros(0, np.int64))

    @property
    def labels(self) -> np.ndarray:
        """Cluster labels numbered as batch :func:`dqm.quickmatch` numbers them (by lowest feature index)."""
        return tree.canonical_labels(self.cluster_ids)

    def assignment(self) -> Dict[int, int]:
        """Feature key -> stable cluster id, for every present feature."""
        return dict(zip(self.keys.tolist(), self.cluster_ids.tolist()))

    def result(self) -> QuickMatchResult:
        """The present state as a :class:`QuickMatchResult` (densities exact; parents as indices)."""
        p = self.params
        order = self._order()
        s = self._engine.store
        if s is None or len(order) == 0:
            z = np.zeros(0)
            return QuickMatchResult(np.zeros(0, np.int64), z, z, np.zeros(0, np.int64), z, np.zeros(0, np.int64),
                                    p.rho, p.ratio_density, p.kernel, p.parent)
        pos = np.full(s.n, -1, np.int64)
        pos[order] = np.arange(len(order))
        par = s.parent[order]
        parent = np.where(par >= 0, pos[np.maximum(par, 0)], -1)
        return QuickMatchResult(self.labels, s.sigma[order].copy(), s.dvalue[order].copy(), parent,
                                s.pdist[order].copy(), s.image[order].copy(), p.rho, p.ratio_density,
                                p.kernel, p.parent, {"n_stored_pairs": float(self.n_stored_pairs)})

    # ------------------------------------------------------------------ API
    def add(self, descriptors, image_ids) -> ChangeSet:
        """Add the features of one or more new images; returns what changed.

        Refused with :class:`dqm.InputError`, before any change, for bad
        descriptors (shape, NaN, dimension unlike earlier ones), bad image ids
        and an image id already present (remove it first).
        """
        t0 = time.perf_counter()
        X = V.check_descriptors(descriptors, keep_integer=True)  # uint8 SIFT stays uint8
        ids = V.check_image_ids(image_ids, len(X))
        V.check_magnitude(X)  # every later add must share the scale: refused here, not rescaled
        eng = self._engine
        if eng.store is not None and len(X) and X.shape[1] != eng.store.dim:
            raise V.InputError(f"descriptors have {X.shape[1]} dimensions, earlier ones {eng.store.dim}")
        present = sorted(set(np.unique(ids).tolist()) & set(eng.image_slots))
        if present:
            raise V.InputError(f"image {present[0]} is already present; remove it before adding it again")
        if len(X) == 0:
            return ChangeSet([], np.zeros(0, np.int64), np.zeros(0, np.int64), {"time": 0.0})
        eng.prepare(X)
        # sigma of the new features from their own images (exact, as batch computes it)
        _, local = np.unique(ids, return_inverse=True)
        local = local.ravel().astype(np.int64)
        sig = pairs.nearest_same_image(pairs.Augmented(X), local, int(local.max()) + 1, n_threads=self.n_threads)
        keys = eng.new_keys(len(X))
        new = eng.insert(X, ids, keys, sig)
        return eng.update(new, np.zeros(0, np.int64), removed_keys=np.zeros(0, np.int64), added_keys=keys, t0=t0)

    def remove(self, image_id) -> ChangeSet:
        """Remove every feature of image ``image_id``; returns what changed."""
        t0 = time.perf_counter()
        try:
            img = int(image_id)
        except (TypeError, ValueError):
            raise V.InputError(f"image id must be an integer, got {image_id!r}") from None
        eng = self._engine
        if img not in eng.image_slots:
            raise V.InputError(f"image {img} is not present (present: {len(eng.image_slots)} images)")
        slots = eng.take_image(img)
        keys = eng.store.key[slots].copy()
        return eng.update(np.zeros(0, np.int64), slots, removed_keys=keys, added_keys=np.zeros(0, np.int64), t0=t0)
