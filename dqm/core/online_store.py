"""What online QuickMatch keeps between updates: per-feature slots, neighbour pairs, duplicate groups.

* :class:`FeatureStore`: growable per-slot arrays (a slot is one feature's row:
  exact descriptor copy, GEMM operands, sigma, exact density sums, parent,
  component and stable cluster id).
* :class:`NeighbourStore`: directed neighbour pairs with exact squared distances.
* :class:`DuplicateGroups`: the present slots of every exact descriptor value.

Plain containers: :mod:`dqm.core.online_update` decides what goes in and out.
"""
from __future__ import annotations

from typing import Dict, List, Optional, Tuple

import numpy as np

#: margin on stored-pair radii, so rounding never leaves a needed pair out
MARGIN = 1.0 + 1e-6


class FeatureStore:
    """Growable per-slot arrays (a slot is one feature's row; re-inserted features get a new slot)."""

    FIELDS = {"key": np.int64, "image": np.int64, "sigma": np.float64, "alive": bool, "hi": np.float64,
              "lo": np.float64, "dvalue": np.float64, "parent": np.int64, "pdist": np.float64,
              "comp": np.int64, "cid": np.int64, "dup": bool, "norm2": np.float64}
    #: per-slot rows that are not in FIELDS: the float32 GEMM operands and the exact descriptor copy
    ROWS = ("left", "right", "X")

    def __init__(self, dim: int, exact_dtype):
        self.n = 0
        self.dim = dim
        cap = 16
        for name, dt in self.FIELDS.items():
            setattr(self, name, np.zeros(cap, dt))
        self.left = np.zeros((cap, dim + 2), np.float32)
        self.right = np.zeros((cap, dim + 2), np.float32)
        self.X = np.zeros((cap, dim), exact_dtype)

    def _names(self) -> List[str]:
        return list(self.FIELDS) + list(self.ROWS)

    def grow(self, extra: int) -> np.ndarray:
        """``extra`` new slots at the end (capacity doubled when needed); returns their indices."""
        need = self.n + extra
        cap = len(self.key)
        if need > cap:
            cap = max(need, 2 * cap)
            for name in self._names():
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

    def alive_slots(self) -> np.ndarray:
        return np.flatnonzero(self.alive[:self.n])

    def mask(self, slots: np.ndarray) -> np.ndarray:
        """Boolean per slot, true at ``slots``."""
        out = np.zeros(self.n, bool)
        out[slots] = True
        return out

    def compact(self) -> np.ndarray:
        """Drop dead slots; returns the map old slot -> new slot (-1: dropped)."""
        keep = self.alive_slots()
        mapping = np.full(self.n, -1, np.int64)
        mapping[keep] = np.arange(len(keep))
        for name in self._names():
            old = getattr(self, name)
            setattr(self, name, np.ascontiguousarray(old[keep]))
        self.n = len(keep)
        par = self.parent[:self.n]
        self.parent[:self.n] = np.where(par >= 0, mapping[np.maximum(par, 0)], -1)
        return mapping


class NeighbourStore:
    """Directed neighbour pairs ``a -> b`` with exact squared distances, looked up by ``a``.

    Sorted runs merged as they grow (a log-structured store): appending a run
    costs its sort, a lookup one binary search per run.
    """

    def __init__(self):
        self.runs: List[Tuple[np.ndarray, np.ndarray, np.ndarray]] = []

    def __len__(self) -> int:
        return sum(len(r[0]) for r in self.runs)

    def add(self, a: np.ndarray, b: np.ndarray, d2: np.ndarray, alive: np.ndarray) -> None:
        """Append pairs; runs of similar size merge (dropping pairs with a dead end)."""
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
        """Renumber slots after :meth:`FeatureStore.compact` (pairs with a dropped end go)."""
        if not self.runs:
            return
        a = mapping[np.concatenate([r[0] for r in self.runs])]
        b = mapping[np.concatenate([r[1] for r in self.runs])]
        d = np.concatenate([r[2] for r in self.runs])
        keep = (a >= 0) & (b >= 0)
        a, b, d = a[keep], b[keep], d[keep]
        order = np.argsort(a, kind="stable")
        self.runs = [(a[order], b[order], d[order])] if len(a) else []


class DuplicateGroups:
    """The present slots of every exact descriptor value (as :func:`dqm.core.pairs.duplicate_groups`
    groups them: float64 bytes, -0.0 as 0.0), and each slot's ``dup`` flag in the store."""

    def __init__(self):
        self._members: Dict[bytes, List[int]] = {}
        self._key: Dict[int, bytes] = {}

    def add(self, store: FeatureStore, slots: np.ndarray, X: np.ndarray) -> None:
        """Enter new ``slots`` holding rows ``X``; flags every member of a group of two or more."""
        byte_rows = X + 0.0  # float64 bytes whatever the dtype; -0.0 -> 0.0 as duplicate_groups does
        for slot, row in zip(slots.tolist(), byte_rows):
            key = row.tobytes()
            members = self._members.setdefault(key, [])
            members.append(slot)
            self._key[slot] = key
            if len(members) > 1:
                store.dup[members] = True

    def discard(self, store: FeatureStore, slot: int) -> Optional[bytes]:
        """Take ``slot`` out of its group; returns the group's key if members remain (their values may
        change), None if the group is gone."""
        key = self._key.pop(slot)
        members = self._members[key]
        members.remove(slot)
        if not members:
            del self._members[key]
            return None
        if len(members) == 1:
            store.dup[members] = False
        return key

    def shared_key(self, slot: int) -> Optional[bytes]:
        """The key of ``slot``'s group if it has other members, else None."""
        key = self._key[slot]
        return key if len(self._members[key]) > 1 else None

    def members(self, key: bytes) -> List[int]:
        return self._members.get(key, [])

    def members_of(self, slot: int) -> List[int]:
        return self._members[self._key[slot]]

    def remap(self, mapping: np.ndarray) -> None:
        """Renumber slots after :meth:`FeatureStore.compact` (every member is alive, so none is dropped)."""
        self._members = {k: [int(mapping[m]) for m in v] for k, v in self._members.items()}
        self._key = {int(mapping[k]): v for k, v in self._key.items() if mapping[k] >= 0}
