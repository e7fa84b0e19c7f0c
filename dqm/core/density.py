"""Exact densities of the finite (quadratic) kernel, the same wherever they are summed.

A quadratic term ``t = max(0, 1 - d2 * w)`` computed in float64 from the exact
squared distance ``d2`` and the contributor's weight ``w = 1 / sigma^2`` is
always a multiple of 2^-53 in [0, 1]: for ``y = fl(d2 * w)`` in [0.5, 1) the
subtraction ``1 - y`` is exact (Sterbenz) and y is a multiple of 2^-53; for y
in [0, 0.5) the result lies in (0.5, 1], whose float64 grid is 2^-53. So every
term is an integer ``K = t * 2^53`` in [0, 2^53], and a density is an integer
sum that can be accumulated exactly, in any order, in pieces on different
machines, and rounded once at the end (``round(sum)``, the value math.fsum
would give).

That is what makes Distributed QuickMatch exact: the centralized engine
(dqm.core.clustering, for the densities whose order it must settle) and every
agent (dqm.distributed.balanced, for partial sums that travel between agents)
compute the same float64 density bit for bit, so near-ties break the same way.

Representation: two float64 integer accumulators per target, ``hi`` (units of
2^-27) and ``lo`` (units of 2^-53), each term split as ``K = hi * 2^26 + lo``
with ``lo < 2^26``. Both sums stay exact below 2^53, i.e. for fewer than 2^26
terms per target; the final value ``hi * 2^-27 + lo * 2^-53`` is one correctly
rounded addition of two exact numbers.
"""
from __future__ import annotations

from typing import Tuple

import numpy as np

_SPLIT = float(2 ** 26)
_UNIT = float(2 ** 53)


def quadratic_terms(d2: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Kernel terms ``max(0, 1 - d2 * w)`` (the canonical float64 formula)."""
    return np.maximum(0.0, 1.0 - np.asarray(d2, np.float64) * np.asarray(w, np.float64))


def term_parts(terms: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Terms (multiples of 2^-53 in [0, 1]) as exact float64 integer parts ``(hi, lo)``, ``K = hi 2^26 + lo``."""
    K = np.asarray(terms, np.float64) * _UNIT
    hi = np.floor(K / _SPLIT)
    return hi, K - hi * _SPLIT


def parts_value(hi: np.ndarray, lo: np.ndarray) -> np.ndarray:
    """The correctly rounded float64 value of exact integer part sums (any sign, below 2^53 each)."""
    return hi * (1.0 / (_UNIT / _SPLIT)) + lo * (1.0 / _UNIT)


class ExactSums:
    """Exact per-target sums of quadratic kernel terms."""

    def __init__(self, n: int):
        self.hi = np.zeros(n)
        self.lo = np.zeros(n)

    def __len__(self) -> int:
        return len(self.hi)

    def add_terms(self, targets: np.ndarray, terms: np.ndarray) -> None:
        """Add ``terms[k]`` (multiples of 2^-53 in [0, 1]) to target ``targets[k]``."""
        if len(targets) == 0:
            return
        hi, lo = term_parts(terms)
        n = len(self.hi)
        self.hi += np.bincount(targets, weights=hi, minlength=n)
        self.lo += np.bincount(targets, weights=lo, minlength=n)

    def add_parts(self, targets: np.ndarray, hi: np.ndarray, lo: np.ndarray) -> None:
        """Add partial sums in this class's representation (see :meth:`parts`)."""
        if len(targets) == 0:
            return
        n = len(self.hi)
        self.hi += np.bincount(targets, weights=np.asarray(hi, np.float64), minlength=n)
        self.lo += np.bincount(targets, weights=np.asarray(lo, np.float64), minlength=n)

    def parts(self, idx: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
        """Normalised exact partial sums of targets ``idx`` as int64 ``(hi, lo)``, ``lo < 2^26``."""
        hi = self.hi[idx]
        lo = self.lo[idx]
        carry = np.floor(lo / _SPLIT)
        return (hi + carry).astype(np.int64), (lo - carry * _SPLIT).astype(np.int64)

    def values(self) -> np.ndarray:
        """The correctly rounded float64 sum of every target."""
        return parts_value(self.hi, self.lo)


def pack_parts(hi: np.ndarray, lo: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Compact wire form of normalised partial sums: ``(units, high)``.

    ``units = hi * 2^26 + lo`` as int64 when every partial sum is below 1024
    (always, in practice: it is a partial density); otherwise ``units = lo``
    and ``high = hi`` (an empty ``high`` means the compact form).
    """
    hi = np.asarray(hi, np.int64)
    lo = np.asarray(lo, np.int64)
    if len(hi) == 0 or int(hi.max()) < 2 ** 36:
        return hi * (2 ** 26) + lo, np.zeros(0, np.int64)
    return lo, hi


def unpack_parts(units: np.ndarray, high: np.ndarray) -> Tuple[np.ndarray, np.ndarray]:
    """Inverse of :func:`pack_parts`: normalised ``(hi, lo)``."""
    units = np.asarray(units, np.int64)
    if len(high) == 0:
        return units >> 26, units & (2 ** 26 - 1)
    return np.asarray(high, np.int64), units
