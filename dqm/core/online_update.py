"""Online QuickMatch's update engine: the state between calls and the steps of one update.

:class:`UpdateEngine` holds the stores (:mod:`dqm.core.online_store`) and runs
an update in the order the module docstring of :mod:`dqm.core.online` explains:

1. :meth:`~UpdateEngine._settle_lonely_sigma`: sigma of single-feature images
   (the batch rule, :func:`dqm.core.clustering.lonely_sigma`);
2. :meth:`~UpdateEngine._update_sums` and :meth:`~UpdateEngine._refresh_densities`:
   exact density sums, less what left, plus what arrived;
3. :meth:`~UpdateEngine._refresh_parents`: parents where a density order or a
   candidate may have changed;
4. :meth:`~UpdateEngine._merge_region` and :meth:`~UpdateEngine._replay`:
   break/merge replayed in the components that hold a change;
5. :func:`dqm.core.online_identity.reconcile`: stable ids and events.
"""
from __future__ import annotations

import time
from typing import Dict, List, Optional, Set, Tuple

import numpy as np

from . import pairs, tree
from .clustering import lonely_sigma
from .events import ChangeSet, ClusterEvent
from .online_density import add_terms, group_value, reach_pairs
from .online_identity import reconcile
from .online_store import MARGIN, DuplicateGroups, FeatureStore, NeighbourStore
from .params import QuickMatchParams

_NO_SLOTS = np.zeros(0, np.int64)


class UpdateEngine:
    """The state of an online QuickMatch and the update that keeps it equal to batch.

    ``store`` is None until the first features arrive (it takes their dimension).
    """

    def __init__(self, params: QuickMatchParams, n_threads: int):
        self.params = params
        self.n_threads = n_threads
        self.store: Optional[FeatureStore] = None
        self.edges = NeighbourStore()
        self.groups = DuplicateGroups()
        self.image_slots: Dict[int, np.ndarray] = {}
        self.next_key = 0
        self.next_cid = 0
        self.next_comp = 0
        self.lonely_sigma = 0.0
        self.center: Optional[np.ndarray] = None
        self.max_norm2 = 0.0
        self._order_cache: Optional[np.ndarray] = None

    # ------------------------------------------------------------------ state
    def order(self) -> np.ndarray:
        """Alive slots in key (arrival) order: the batch order."""
        if self._order_cache is None:
            s = self.store
            if s is None:
                self._order_cache = np.zeros(0, np.int64)
            else:
                alive = s.alive_slots()
                self._order_cache = alive[np.argsort(s.key[alive], kind="stable")]
        return self._order_cache

    def prepare(self, X: np.ndarray) -> None:
        """Make room for descriptors ``X`` (validated): the store on first use, kept as uint8 while every
        descriptor is an integer in 0..255, widened to float64 when one is not."""
        integral = X.dtype == np.uint8 or (np.all(X == np.round(X)) and X.min() >= 0 and X.max() <= 255)
        if self.store is None:
            self.store = FeatureStore(X.shape[1], np.uint8 if integral else np.float64)
            self.center = X.mean(axis=0)
        elif not integral and self.store.X.dtype == np.uint8:
            self.store.widen_exact()

    def new_keys(self, n: int) -> np.ndarray:
        keys = np.arange(self.next_key, self.next_key + n, dtype=np.int64)
        self.next_key += n
        return keys

    def insert(self, X: np.ndarray, ids: np.ndarray, keys: np.ndarray, sig: np.ndarray) -> np.ndarray:
        """New slots for features (sigma NaN: alone in its image, settled by the update)."""
        s = self.store
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
        s.left[slots], s.right[slots], n2 = pairs.augmented_rows(X - self.center)
        s.norm2[slots] = n2
        self.max_norm2 = max(self.max_norm2, float(n2.max()))
        for img in np.unique(ids).tolist():
            mine = slots[ids == img]
            old = self.image_slots.get(img)
            self.image_slots[img] = mine if old is None else np.concatenate([old, mine])
        self.groups.add(s, slots, X)
        return slots

    def take_image(self, img: int) -> np.ndarray:
        """The slots of image ``img``, which leaves the image index (the update removes them)."""
        return self.image_slots.pop(img)

    # ------------------------------------------------------------------ the update
    def update(self, new: np.ndarray, gone: np.ndarray, *, removed_keys: np.ndarray, added_keys: np.ndarray,
               t0: float) -> ChangeSet:
        """Bring densities, parents and clusters up to date after slots ``new`` arrived and ``gone`` left."""
        s = self.store
        stats: Dict[str, float] = {}
        n_before = int(s.alive[:s.n].sum()) - len(new)
        s.alive[gone] = False
        new, gone = self._settle_lonely_sigma(new, gone)
        self._order_cache = None
        t = time.perf_counter()
        is_new = s.mask(new)
        touched, changed_groups = self._update_sums(new, gone, is_new)
        stats["time_density"] = time.perf_counter() - t
        t = time.perf_counter()
        prev, dchanged = self._refresh_densities(new, touched, changed_groups, is_new)
        stats["density_changed"] = float(len(dchanged))
        A, old_parent, old_pdist = self._refresh_parents(new, gone, np.union1d(dchanged, new), prev, is_new)
        pchanged = A[(s.parent[A] != old_parent) | (s.pdist[A] != old_pdist)]
        stats["parents_recomputed"] = float(len(A))
        stats["parents_changed"] = float(len(np.setdiff1d(pchanged, new)))
        stats["time_parents"] = time.perf_counter() - t
        t = time.perf_counter()
        region = self._merge_region(A, old_parent, old_pdist, gone, new, is_new)
        events = self._relabel(region, gone, is_new, removed_keys, added_keys)
        stats["replayed"] = float(len(region))
        stats["time_merges"] = time.perf_counter() - t
        self._maybe_compact()
        stats["features_before"] = float(n_before)
        stats["time"] = time.perf_counter() - t0
        return ChangeSet(events, np.asarray(added_keys, np.int64), np.asarray(removed_keys, np.int64), stats)

    # -- 1. sigma of single-feature images
    def _settle_lonely_sigma(self, new: np.ndarray, gone: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Single-feature images take :func:`lonely_sigma` of all others; when that value moves, the
        present ones are re-inserted with it (their old slots join ``gone``, the fresh ones ``new``)."""
        s = self.store
        lonely_new = new[np.isnan(s.sigma[new])]
        lonely_old = np.array([sl[0] for sl in self.image_slots.values() if len(sl) == 1], np.int64)
        lonely_old = lonely_old[~np.isin(lonely_old, new)]
        if not (len(lonely_new) or len(lonely_old)):
            return new, gone
        alive = s.alive_slots()
        single = s.mask(np.concatenate([lonely_old, lonely_new]))
        value = lonely_sigma(s.sigma[alive[~single[alive]]])
        s.sigma[lonely_new] = value
        if len(lonely_old) and value != self.lonely_sigma:
            # re-insert: the old slots leave (their terms subtracted), new slots with the new sigma arrive
            img = s.image[lonely_old]
            X = s.X[lonely_old]
            keys = s.key[lonely_old].copy()
            for i in img.tolist():
                self.image_slots.pop(i)
            s.alive[lonely_old] = False
            fresh = self.insert(X, img, keys, np.full(len(keys), value))
            gone = np.concatenate([gone, lonely_old])
            new = np.concatenate([new, fresh])
        self.lonely_sigma = value
        return new, gone

    # -- 2. densities
    def _update_sums(self, new: np.ndarray, gone: np.ndarray, is_new: np.ndarray
                     ) -> Tuple[List[np.ndarray], Set[bytes]]:
        """Subtract what left, add what arrived; returns the slots whose sums were touched and the
        duplicate groups whose membership changed."""
        alive_cols = np.flatnonzero(self.store.alive[:self.store.n] & ~is_new)
        touched: List[np.ndarray] = []
        changed_groups: Set[bytes] = set()
        if len(gone):
            touched.append(self._subtract_gone(gone, alive_cols, changed_groups))
        if len(new):
            touched += self._add_new(new, alive_cols, changed_groups)
        return touched, changed_groups

    def _subtract_gone(self, gone: np.ndarray, alive_cols: np.ndarray, changed_groups: Set[bytes]) -> np.ndarray:
        """Terms of the features that left, off the sums they reached; their duplicate groups shrink."""
        s = self.store
        ga, gb, gd = self._reach(gone, alive_cols, triangle=False, rows_only=True)
        add_terms(s, ga, gb, gd, -1, self.params.ratio_density)
        for slot in gone.tolist():
            key = self.groups.discard(s, slot)
            if key is not None:
                changed_groups.add(key)
        return gb

    def _add_new(self, new: np.ndarray, alive_cols: np.ndarray, changed_groups: Set[bytes]) -> List[np.ndarray]:
        """Terms between the new features and everything present, both ways; the pairs parents need
        (within ``rho * sigma`` of either end) go into the neighbour store."""
        s = self.store
        rho = self.params.rho
        a, b, d2 = self._reach(new, alive_cols, triangle=True, rows_only=False)
        add_terms(s, a, b, d2, +1, self.params.ratio_density)
        add_terms(s, b, a, d2, +1, self.params.ratio_density)
        touched = [a, b]
        d = np.sqrt(d2)
        near = (d < rho * s.sigma[a] * MARGIN) | (d < rho * s.sigma[b] * MARGIN)
        a, b, d2 = a[near], b[near], d2[near]
        self.edges.add(np.concatenate([a, b]), np.concatenate([b, a]), np.concatenate([d2, d2]), s.alive)
        for slot in new.tolist():
            key = self.groups.shared_key(slot)
            if key is not None:
                changed_groups.add(key)
        return touched

    def _reach(self, rows: np.ndarray, cols: np.ndarray, *, triangle: bool, rows_only: bool):
        return reach_pairs(self.store, rows, cols, rho=self.params.rho, max_norm2=self.max_norm2,
                           n_threads=self.n_threads, triangle=triangle, rows_only=rows_only)

    def _refresh_densities(self, new: np.ndarray, touched: List[np.ndarray], changed_groups: Set[bytes],
                           is_new: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Density values of every touched slot; returns the values before and the (not new) slots
        whose value changed."""
        s = self.store
        cand = np.unique(np.concatenate(touched + [new])) if touched or len(new) else _NO_SLOTS
        extra = [m for key in changed_groups for m in self.groups.members(key)]
        if extra:
            cand = np.union1d(cand, np.array(extra, np.int64))
        cand = cand[s.alive[cand]]
        prev = s.dvalue[:s.n].copy()
        s.dvalue[cand] = group_value(s, self.groups, cand)
        dchanged = cand[(s.dvalue[cand] != prev[cand]) & ~is_new[cand]]
        return prev, dchanged

    # -- 3. parents
    def _refresh_parents(self, new: np.ndarray, gone: np.ndarray, movers: np.ndarray, prev: np.ndarray,
                         is_new: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Recompute the parents of new features, of orphans (their parent left) and of features a mover
        may have re-ranked; returns those slots and their parents and distances before."""
        s = self.store
        was_gone = s.mask(gone)
        alive_idx = s.alive_slots()
        orphans = alive_idx[(s.parent[alive_idx] >= 0) & was_gone[np.maximum(s.parent[alive_idx], 0)]]
        A = np.unique(np.concatenate([new, orphans, self._triggered(movers, prev, is_new)]))
        old_parent = s.parent[A].copy()
        old_pdist = s.pdist[A].copy()
        self._select_parents(A)
        return A, old_parent, old_pdist

    def _near_pairs(self, nodes: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stored pairs (child, candidate, distance) at ``nodes``, both directions, where the candidate is
        within the child's search radius ``rho * sigma`` (and, for ``other-image``, of another image)."""
        s = self.store
        ka, kb, kd = self.edges.query(nodes, s.alive)
        d = np.sqrt(kd)
        child = np.concatenate([kb, ka])
        cand = np.concatenate([ka, kb])
        d = np.concatenate([d, d])
        ok = d < self.params.rho * s.sigma[child]
        if self.params.parent == "other-image":
            ok &= s.image[child] != s.image[cand]
        return child[ok], cand[ok], d[ok]

    def _triggered(self, movers: np.ndarray, prev: np.ndarray, is_new: np.ndarray) -> np.ndarray:
        """Features whose parent may change because a mover (new, or density changed) near them did:
        the mover now ranks above them and is nearer than their parent, or it was their parent and no
        longer ranks above them. Both ends of every stored pair at a mover are checked as the child."""
        s = self.store
        child, cand, d = self._near_pairs(movers)
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
        s = self.store
        a, b, d2 = self.edges.query(A, s.alive)
        d = np.sqrt(d2)
        keep = d < self.params.rho * s.sigma[a]
        if self.params.parent == "other-image":
            keep &= s.image[a] != s.image[b]
        a, b, d = a[keep], b[keep], d[keep]
        above = tree.rank_order(s.dvalue[b], s.dvalue[a], s.key[b], s.key[a])
        a, b, d = a[above], b[above], d[above]
        parent, pdist, _ = tree.nearest_candidates(a, b, d, s.n, tie=s.key[b])
        s.parent[A] = parent[A]
        s.pdist[A] = pdist[A]

    # -- 4. merges
    def _eligible(self, child: np.ndarray, parent: np.ndarray, pdist: np.ndarray) -> np.ndarray:
        """Tree edges that can merge at all: ``d < rho * min(sigma_child, sigma_parent)``."""
        s = self.store
        ok = parent >= 0
        p = np.maximum(parent, 0)
        return ok & (pdist < self.params.rho * np.minimum(s.sigma[child], s.sigma[p]))

    def _merge_region(self, A: np.ndarray, old_parent: np.ndarray, old_pdist: np.ndarray, gone: np.ndarray,
                      new: np.ndarray, is_new: np.ndarray) -> np.ndarray:
        """Slots (key order) of the components that hold a changed mergeable edge, a new or a removed
        feature: where break/merge must be replayed."""
        s = self.store
        old_eligible_parent = np.where(self._eligible(A, old_parent, old_pdist), old_parent, -1)
        new_eligible_parent = np.where(self._eligible(A, s.parent[A], s.pdist[A]), s.parent[A], -1)
        edge_changed = (old_eligible_parent != new_eligible_parent) | (
            (new_eligible_parent >= 0) & (old_pdist != s.pdist[A]))
        touched = np.concatenate([A[edge_changed], old_eligible_parent[edge_changed],
                                  new_eligible_parent[edge_changed], gone])
        touched = touched[touched >= 0]
        comps = np.unique(s.comp[touched])
        comps = comps[comps >= 0]
        alive_idx = s.alive_slots()
        region = np.union1d(alive_idx[np.isin(s.comp[alive_idx], comps)], new)
        return region[np.argsort(s.key[region], kind="stable")]

    def _replay(self, region: np.ndarray) -> np.ndarray:
        """Break/merge in ``region`` (whole components, key order); sets components, returns local labels."""
        s = self.store
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
                                     s.image[region], self.params.rho)
        j = np.flatnonzero(lp >= 0)
        from scipy.sparse import coo_matrix  # here: scipy.sparse costs 0.3 s of every command's start-up
        from scipy.sparse.csgraph import connected_components

        g = coo_matrix((np.ones(len(j)), (j, lp[j])), shape=(m, m))
        _, comp = connected_components(g, directed=False)
        s.comp[region] = comp + self.next_comp
        self.next_comp += int(comp.max()) + 1
        return labels

    # -- 5. stable ids and events
    def _relabel(self, region: np.ndarray, gone: np.ndarray, is_new: np.ndarray, removed_keys: np.ndarray,
                 added_keys: np.ndarray) -> List[ClusterEvent]:
        """Replay merges in ``region``, give its clusters stable ids and list the events."""
        s = self.store
        old_members = np.union1d(region[~is_new[region]], gone)
        old_cid = {int(k): int(c) for k, c in zip(s.key[old_members], s.cid[old_members]) if c >= 0}
        local = self._replay(region)
        gone_images = dict(zip(s.key[gone].tolist(), s.image[gone].tolist()))
        out = reconcile(s.key[region], s.image[region], local, old_cid, set(int(k) for k in removed_keys),
                        gone_images, set(int(k) for k in added_keys), self.next_cid)
        s.cid[region] = out.ids
        self.next_cid = out.next_cid
        return out.events

    def _maybe_compact(self) -> None:
        """Drop dead slots once they are more than a quarter of the store (and over 4096)."""
        s = self.store
        dead = s.n - int(s.alive[:s.n].sum())
        if dead <= max(4096, s.n // 4):
            return
        mapping = s.compact()
        self.edges.remap(mapping)
        self.groups.remap(mapping)
        self.image_slots = {i: mapping[v] for i, v in self.image_slots.items()}
        self._order_cache = None

