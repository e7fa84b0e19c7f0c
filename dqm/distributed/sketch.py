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

from typing import Dict, Tuple

import numpy as np

#: relative margin for float64 rounding in projections, norms and the bound
_REL = 1e-7


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
              use_their_reach: bool = True, block: int = 4096) -> np.ndarray:
    """(n,) bool: could x be within reach of some sketched feature?

    With ``w = (u, r)`` (k + 1 numbers), ``|x - y| >= |w_x - w_y| >= |w_x - ŵ_y| - e``
    where ŵ_y is y's decoded sketch and e bounds its quantization error (and
    float rounding on both sides). The bound is compared with
    ``max(reach(x), reach(y))`` (``use_their_reach``, the one-way rule) or
    ``reach(x)`` alone (the two-way rule): True whenever the true distance is
    within the threshold, possibly True otherwise. One GEMM per block; the
    thresholds are folded into column offsets so each block is two passes.
    """
    n = len(X)
    out = np.zeros(n, dtype=bool)
    codes = np.asarray(sketch["codes"])
    if n == 0 or len(codes) == 0:
        return out
    r_lo, r_step, e_u, e_r = (float(v) for v in sketch["bounds"])
    Wy = np.empty((len(codes), codes.shape[1] + 1))
    Wy[:, :-1] = codes.astype(np.float64) * np.asarray(sketch["scale"], np.float64)[None, :]
    Wy[:, -1] = r_lo + sketch["residual"].astype(np.float64) * r_step
    Ry = np.asarray(sketch["reach"], np.float64)
    ny = np.einsum("ij,ij->i", Wy, Wy)
    ux, rx, normx = space.project(X)
    Wx = np.concatenate([ux, rx[:, None]], axis=1)
    nx = np.einsum("ij,ij->i", Wx, Wx)
    # quantization of the sketch (e), rounding of x's own projection (mx, per row: a row's answer
    # must not depend on the other rows; it also covers QR differences between machines)
    e = float(np.hypot(e_u, e_r))
    mx = (_REL + 4.0 * np.sqrt(_REL)) * normx
    gamma = 8.0 * (Wx.shape[1] + 2) * np.finfo(np.float64).eps  # GEMM rounding, relative to |w_x|^2 + |w_y|^2
    reach_x = np.asarray(reach_x, np.float64)
    c_near = ny  # |w_x - ŵ_y|^2 = nx + ny - 2 w_x.ŵ_y
    c_theirs = ny - (Ry + e) ** 2 if use_their_reach else None
    ny_max = float(ny.max())
    ry_max = float(Ry.max()) + e
    for s in range(0, n, block):
        sl = slice(s, s + block)
        G = Wx[sl] @ Wy.T
        G *= -2.0
        low = nx[sl] - gamma * (nx[sl] + ny_max)  # with the column offsets: a lower bound of |w_x - ŵ_y|^2
        hit = (G + c_near[None, :]).min(axis=1) + low < (reach_x[sl] + e + mx[sl]) ** 2
        if c_theirs is not None:
            # |w_x - ŵ_y| < R_y + e + m  <=>  |.|^2 - (R_y + e)^2 < m (2 (R_y + e) + m) <= m (2 ry_max + m)
            G += c_theirs[None, :]
            hit |= G.min(axis=1) + low < mx[sl] * (2.0 * ry_max + mx[sl])
        out[sl] = hit
    return out


def empty_sketch(k: int) -> Dict[str, np.ndarray]:
    """A sketch payload with no features."""
    return {"codes": np.zeros((0, k), np.int8), "residual": np.zeros(0, np.uint8),
            "reach": np.zeros(0, np.float32), "scale": np.ones(k), "bounds": np.array([0.0, 1.0, 0.0, 0.0])}

