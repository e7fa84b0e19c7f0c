"""Lower-bound sketches: a cheap, rigorous pre-filter for ghost copies.

Before a cell ships copies of its boundary features to another cell, the
receiving cell sends short *sketches* of its own features near that boundary.
A sketch of y is its projection ``u_y = Q (y - mu)`` on k orthonormal
directions (the top principal directions of the set-up sample, so that
distances in them are as large as k directions allow), quantized to int8 per
dimension, the norm ``r_y`` of the part of ``y - mu`` outside those directions
(uint8), and y's reach rounded up (float32). For any x,

    |x - y|^2 = |Q(x - y)|^2 + |Q⊥(x - y)|^2 >= |u_x - u_y|^2 + (r_x - r_y)^2,

so ``|x - y| >= |w_x - w_y|`` with ``w = (u, r)``. The sender, which knows x
exactly, bounds the quantization errors of the sketch from above, so the bound
it computes never exceeds the true distance:
**the pre-filter never drops a pair** (tests check it against brute force).
A copy travels only if some sketched y could be within reach of it.

The basis: agent 0 computes the principal directions of the pooled set-up
sample around ``mu`` = the mean of the seeds (every agent has the seeds) and
broadcasts them as int8 (k x dim bytes). Every agent orthonormalizes the same
int8 matrix itself (QR); the tiny float differences this could leave between
machines are covered by the margins below.
"""
from __future__ import annotations

from typing import Dict, Optional, Tuple

import numpy as np

from ..core import native, pairs

#: relative margin for float64 rounding in projections, norms and the bound
_REL = 1e-7
#: tile of the pre-filter's pass (rows x sketch columns, float32)
_TILE_ROWS = 1024
_TILE_COLS = 2048


def basis_from_sample(sample: np.ndarray, center: np.ndarray, k: int) -> np.ndarray:
    """(k', dim) int8 rows spanning the top principal directions of the sample (k' <= k)."""
    S = np.asarray(sample, dtype=np.float64) - np.asarray(center, dtype=np.float64)[None, :]
    k = int(min(k, S.shape[1], max(0, len(S) - 1)))
    if k <= 0:
        return np.zeros((0, S.shape[1]), np.int8)
    _, _, Vt = np.linalg.svd(S, full_matrices=False)
    B = Vt[:k]
    B = B / np.maximum(np.abs(B).max(axis=1, keepdims=True), 1e-300) * 127.0
    return np.clip(np.round(B), -127, 127).astype(np.int8)


class SketchSpace:
    """The orthonormal sketch directions an agent derives from the broadcast int8 basis."""

    def __init__(self, basis: np.ndarray, center: np.ndarray):
        B = np.asarray(basis, dtype=np.float64)
        self.center = np.asarray(center, dtype=np.float64)
        if len(B):
            q, r = np.linalg.qr(B.T)
            keep = np.abs(np.diag(r)) > 1e-9 * max(1.0, np.abs(np.diag(r)).max())
            self.Q = q[:, keep].T
        else:
            self.Q = np.zeros((0, len(self.center)))
        self.k = len(self.Q)

    def project(self, X: np.ndarray) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(u, r, norm)``: coordinates in the k directions, norm of the rest, norm of ``x - mu``."""
        V = np.asarray(X, dtype=np.float64) - self.center[None, :]
        u = V @ self.Q.T
        norm2 = np.einsum("ij,ij->i", V, V)
        r = np.sqrt(np.maximum(norm2 - np.einsum("ij,ij->i", u, u), 0.0))
        return u, r, np.sqrt(norm2)


def encode(space: SketchSpace, X: np.ndarray, reach: np.ndarray) -> Dict[str, np.ndarray]:
    """The sketch payload of features ``X`` with their reach (arrays for dqm.distributed.messages)."""
    u, r, norm = space.project(X)
    n, k = u.shape
    scale = np.abs(u).max(axis=0) / 127.0 if n else np.zeros(k)
    scale = np.where(scale > 0, scale, 1.0)
    codes = np.clip(np.round(u / scale[None, :]), -127, 127).astype(np.int8)
    r_lo = float(r.min()) if n else 0.0
    r_step = (float(r.max()) - r_lo) / 255.0 if n else 1.0
    r_step = r_step if r_step > 0 else 1.0
    res = np.clip(np.round((r - r_lo) / r_step), 0, 255).astype(np.uint8)
    reach32 = np.asarray(reach, dtype=np.float32)
    low = reach32.astype(np.float64) < np.asarray(reach, np.float64)
    reach32[low] = np.nextafter(reach32[low], np.float32(np.inf))
    # error bounds of the receiver's quantization, widened for float rounding
    max_norm = float(norm.max()) if n else 0.0
    e_u = float(np.sqrt(np.sum((scale / 2.0) ** 2))) * (1.0 + _REL) + _REL * max_norm
    e_r = r_step / 2.0 * (1.0 + _REL) + 4.0 * np.sqrt(_REL) * max_norm
    return {"codes": codes, "residual": res, "reach": reach32, "scale": scale,
            "bounds": np.array([r_lo, r_step, e_u, e_r], dtype=np.float64)}


def plausible(space: SketchSpace, X: np.ndarray, reach_x: np.ndarray, sketch: Dict[str, np.ndarray],
              use_their_reach: bool = True, relax: float = 0.0, n_threads: Optional[int] = None) -> np.ndarray:
    """(n,) bool: could x be within reach of some sketched feature?

    With ``w = (u, r)`` (k + 1 numbers), ``|x - y| >= |w_x - w_y| >= |w_x - ŵ_y| - e``
    where ŵ_y is y's decoded sketch and e bounds its quantization error. The
    bound is compared with ``max(reach(x), reach(y))`` (``use_their_reach``, the
    one-way rule) or ``reach(x)`` alone (the two-way rule): True whenever the
    true distance is within the threshold, possibly True otherwise.

    Computed as a float32 GEMM per tile (augmented vectors around the sketch's
    mean) and a scan that stops at a row's first hit (dqm.core.native); later
    column tiles skip rows already hit. Every margin (the sketch's
    quantization, the rounding of x's own projection, the float32 GEMM's worst
    case) depends on x itself or on the sketch alone, so a row's answer does not
    depend on which other rows are tested with it: the receiver can recompute
    the sender's decision. ``relax`` widens the thresholds by that fraction (the
    receiver's check allows for float32 differences between batches).
    """
    n = len(X)
    codes = np.asarray(sketch["codes"])
    if n == 0 or len(codes) == 0:
        return np.zeros(n, dtype=bool)
    r_lo, r_step, e_u, e_r = (float(v) for v in sketch["bounds"])
    Wy = np.empty((len(codes), codes.shape[1] + 1))
    Wy[:, :-1] = codes.astype(np.float64) * np.asarray(sketch["scale"], np.float64)[None, :]
    Wy[:, -1] = r_lo + sketch["residual"].astype(np.float64) * r_step
    Ry = np.asarray(sketch["reach"], np.float64)
    ux, rx, normx = space.project(X)
    Wx = np.concatenate([ux, rx[:, None]], axis=1)
    e = float(np.hypot(e_u, e_r))
    crel = _REL + 4.0 * np.sqrt(_REL)  # rounding of a projection, relative to |x - mu|
    c0 = Wy.mean(axis=0)
    Yc = Wy - c0[None, :]
    Xc = Wx - c0[None, :]
    ny = np.einsum("ij,ij->i", Yc, Yc)
    nx = np.einsum("ij,ij->i", Xc, Xc)
    K = Wx.shape[1] + 2
    gamma = (2 * K + 4) * float(np.finfo(np.float32).eps)  # worst case of the float32 GEMM, any order
    grow = 1.0 + relax
    # x's own threshold: |w_x - ŵ_y| < R_x + e + m_x
    rad2r = ((np.asarray(reach_x, np.float64) + e + crel * normx) ** 2 * grow + gamma * (nx + float(ny.max())))
    if use_their_reach:
        # y's threshold; where it matters |x - mu| <= |ŵ_y| + e + R_y, which bounds x's rounding and norm
        far = Ry + e
        wy_norm = np.sqrt(np.einsum("ij,ij->i", Wy, Wy))
        rad2c = (far + crel * (wy_norm + far)) ** 2 * grow + gamma * (ny + (np.sqrt(ny) + far + e) ** 2)
    else:
        rad2c = np.full(len(Wy), -np.inf)
    order = np.argsort(-rad2c, kind="stable")  # likely hits first: earlier exits
    L = np.empty((n, K), np.float32)
    L[:, :-2], L[:, -2], L[:, -1] = Xc, nx, 1.0
    Rm = np.empty((len(Wy), K), np.float32)
    Rm[:, :-2], Rm[:, -2], Rm[:, -1] = -2.0 * Yc[order], 1.0, ny[order]
    rad2r32 = rad2r.astype(np.float32)
    rad2c32 = np.where(np.isfinite(rad2c[order]), rad2c[order], -np.inf).astype(np.float32)
    hit = np.zeros(n, np.uint8)
    pending = np.arange(n)

    def work(task):
        rows, c_lo, c_hi = task
        G = L[rows] @ Rm[c_lo:c_hi].T
        h = np.zeros(len(rows), np.uint8)
        native.any_within(G, rad2r32[rows], rad2c32[c_lo:c_hi], h)
        return rows, h

    with pairs.tile_pool(n_threads) as run:
        for c_lo in range(0, len(Wy), _TILE_COLS):
            if len(pending) == 0:
                break
            c_hi = min(len(Wy), c_lo + _TILE_COLS)
            tasks = [(pending[s:s + _TILE_ROWS], c_lo, c_hi) for s in range(0, len(pending), _TILE_ROWS)]
            for rows, h in run(work, tasks):
                hit[rows] |= h
            pending = pending[hit[pending] == 0]
    return hit.astype(bool)


def hashed_subset(ids: np.ndarray, bits: int) -> np.ndarray:
    """Mask of a deterministic 1 / 2^bits of the features, chosen by a hash of their ids."""
    h = np.asarray(ids, np.uint64) * np.uint64(0x9E3779B97F4A7C15)
    return (h >> np.uint64(64 - bits)) == 0


def pilot_mask(ids: np.ndarray) -> np.ndarray:
    """The deterministic eighth of features whose sketches travel first (a hash of the id)."""
    return hashed_subset(ids, 3)


def worth_the_rest(n_unhit: int, n_rest: int, copy_bytes: float, sketch_bytes: float) -> bool:
    """Should the sender ask for the rest of a sketch?

    The pilot already proves the candidates it hits plausible; the full
    sketch can at most keep home the ``n_unhit`` others, saving at most
    ``n_unhit * copy_bytes``. Ask only when that bound exceeds what the rest
    of the sketch costs.
    """
    return n_unhit * copy_bytes > n_rest * sketch_bytes

