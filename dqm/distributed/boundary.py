"""Distances from features to the Voronoi cells of other agents.

For a feature x in cell i and another cell a:

* **bisector (closed form)**: distance from x to the hyperplane
  ``H_ia = {z : |z - P_i| = |z - P_a|}``, i.e.
  ``(|x - P_a|^2 - |x - P_i|^2) / (2 |P_a - P_i|)``. It is a lower bound on the
  distance to cell a, and it is the exact distance when the foot of the
  perpendicular lies in cell a. It is also *additive*: for x in cell i and y in
  cell a, the segment xy crosses H_ia, so ``|x - y| >= h(x, H_ia) + h(y, H_ia)``.
  The contested test (dqm.distributed.contested) and the ghost rules
  (dqm.distributed.ghosts) rely on this.
* **exact distance to the cell** ``min |z - x| s.t. z in V_a`` (a QP with m-1
  linear constraints ``2 (P_b - P_a) . z <= |P_b|^2 - |P_a|^2``). All seeds lie in
  an affine subspace of dimension <= m-1, and the constraints only see the
  component of z in it, so the QP is solved in those <= m-1 coordinates (the
  orthogonal part of x is kept as is). Problems are batched per target cell:
  one piqp solver per cell, updated per point. It is a valid lower bound on
  ``|x - y|`` for every y in cell a (not additive across two cells).

Used where: the contested test uses the bisector bounds (cheap, additive); the
exact distance tightens it for the pairs that survive the bisector test and
whose perpendicular foot lies outside the cell (see ``cell_distances``).
"""
from __future__ import annotations

from typing import Optional

import numpy as np


def hyperplane_distances(X: np.ndarray, seeds: np.ndarray, cells: np.ndarray,
                         weights: Optional[np.ndarray] = None) -> np.ndarray:
    """(n, m) bisector distances of every x (in cell ``cells[k]``) to every cell; 0 for its own.

    With power-diagram ``weights`` the separating hyperplane of cells i and a is
    ``|z - P_a|^2 - w_a = |z - P_i|^2 - w_i``; the formula keeps its form.
    """
    X = np.asarray(X, dtype=np.float64)
    P = np.asarray(seeds, dtype=np.float64)
    n, m = len(X), len(P)
    if n == 0:
        return np.zeros((0, m))
    cells = np.asarray(cells, dtype=np.int64)
    # |x - P_a|^2 - w_a - |x - P_i|^2 + w_i = |P_a|^2 - w_a - |P_i|^2 + w_i - 2 x.(P_a - P_i)
    pn = (P ** 2).sum(1)
    if weights is not None:
        pn = pn - np.asarray(weights, dtype=np.float64)
    xp = X @ P.T  # (n, m)
    num = (pn[None, :] - pn[cells][:, None]) - 2.0 * (xp - xp[np.arange(n), cells][:, None])
    sep = seed_separation(P)[cells]
    with np.errstate(divide="ignore", invalid="ignore"):
        h = num / (2.0 * sep)
    h[np.arange(n), cells] = 0.0
    # coincident seeds (sep == 0): the lower index owns the whole cell; distance 0
    h[~np.isfinite(h)] = 0.0
    return np.maximum(h, 0.0)


def bisector_lower_bounds(X: np.ndarray, seeds: np.ndarray, cells: np.ndarray,
                          weights: Optional[np.ndarray] = None) -> np.ndarray:
    """(n, m) rigorous lower bounds of the bisector distances: float64 rounding taken off.

    The numerator of :func:`hyperplane_distances` sums terms of size up to
    ``(|x| + max|P|)^2 + max|w|``; its rounding error is below
    ``8 (dim + 4) eps`` times that, divided by the seeds' separation.
    """
    X = np.asarray(X, dtype=np.float64)
    P = np.asarray(seeds, dtype=np.float64)
    H = hyperplane_distances(X, P, cells, weights)
    if len(X) == 0:
        return H
    cells = np.asarray(cells, dtype=np.int64)
    wmax = 0.0 if weights is None else float(np.abs(weights).max())
    mag = (np.sqrt(np.einsum("ij,ij->i", X, X)) + float(np.sqrt((P ** 2).sum(1).max()))) ** 2 + wmax
    sep = seed_separation(P)[cells]
    with np.errstate(divide="ignore"):
        err = 8.0 * (X.shape[1] + 4) * np.finfo(np.float64).eps * mag[:, None] / (2.0 * sep)
    err[~np.isfinite(err)] = 0.0  # coincident seeds: distance already 0
    return np.maximum(H - err, 0.0)


def seed_separation(seeds: np.ndarray) -> np.ndarray:
    """(m, m) distances between seeds."""
    P = np.asarray(seeds, dtype=np.float64)
    return np.sqrt(((P[:, None, :] - P[None, :, :]) ** 2).sum(axis=2))


class CellGeometry:
    """The seeds in the coordinates of their own affine span (dimension <= m-1)."""

    def __init__(self, seeds: np.ndarray, weights: Optional[np.ndarray] = None):
        P = np.asarray(seeds, dtype=np.float64)
        self.weights = np.zeros(len(P)) if weights is None else np.asarray(weights, dtype=np.float64)
        self.seeds = P
        self.m = len(P)
        self.origin = P[0]
        D = (P[1:] - P[0]).T  # dim x (m-1)
        if D.size:
            U, s, _ = np.linalg.svd(D, full_matrices=False)
            keep = s > 1e-9 * max(1.0, s.max())
            self.basis = U[:, keep]
        else:
            self.basis = np.zeros((P.shape[1], 0))
        self.q = (P - self.origin) @ self.basis  # seeds in span coordinates
        self.qn = (self.q ** 2).sum(1)

    def coords(self, X: np.ndarray) -> np.ndarray:
        return (np.asarray(X, dtype=np.float64) - self.origin) @ self.basis

    def constraints(self, a: int):
        """(G, h) with V_a = {u : G u <= h} in span coordinates."""
        others = np.array([b for b in range(self.m) if b != a], dtype=np.int64)
        G = 2.0 * (self.q[others] - self.q[a])
        h = self.qn[others] - self.qn[a] - (self.weights[others] - self.weights[a])
        return G, h


def _dual_nnls(G: np.ndarray, h: np.ndarray, u: np.ndarray) -> Optional[float]:
    """Distance from u to {z : G z <= h} through the dual NNLS (exact active set); None if G is singular."""
    from scipy.optimize import nnls

    if np.all(G @ u <= h):
        return 0.0
    try:
        v = u - np.linalg.solve(G, h)
    except np.linalg.LinAlgError:
        return None
    lam, _ = nnls(G.T, v)
    z = u - G.T @ lam
    return float(np.linalg.norm(z - u))


def _solve_batch(geom: CellGeometry, U: np.ndarray, targets: np.ndarray) -> np.ndarray:
    """Exact distances of points (span coordinates ``U``) to cells ``targets`` with piqp.

    Batched by target cell: one solver is set up per cell (its constraint
    matrix is shared by every point) and only the linear term is updated per
    point, so the factorisation structure is reused. A problem piqp does not
    solve is solved again through its dual (non-negative least squares, exact
    active set); should that fail too, the bisector bound is kept (a lower
    bound, so the contested test stays conservative).
    """
    import piqp

    B, r = U.shape
    out = np.full(B, np.nan)
    if B == 0 or r == 0:
        return np.zeros(B)
    eye = np.asfortranarray(np.eye(r))
    for a in np.unique(targets).tolist():
        rows = np.flatnonzero(targets == a)
        G, h = geom.constraints(int(a))
        solver = piqp.DenseSolver()
        solver.settings.verbose = False
        solver.settings.max_iter = 500
        solver.setup(eye, -U[rows[0]], None, None, np.asfortranarray(G), None, h, None, None)
        for k in rows.tolist():
            solver.update(c=-U[k])
            status = solver.solve()
            if status == piqp.PIQP_SOLVED:
                out[k] = np.linalg.norm(solver.result.x - U[k])
            else:
                d = _dual_nnls(G, h, U[k]) if G.shape[0] == r else None
                if d is not None:
                    out[k] = d
    return out


def cell_distances(
    X: np.ndarray,
    seeds: np.ndarray,
    cells: np.ndarray,
    need: Optional[np.ndarray] = None,
    hyper: Optional[np.ndarray] = None,
    weights: Optional[np.ndarray] = None,
) -> np.ndarray:
    """(n, m) exact distances of every x to every other cell (0 for its own).

    ``need`` (n, m) bool limits the work: where False the bisector bound is
    returned instead. Where the foot of the perpendicular on the bisector lies
    in the target cell the bisector distance is exact and no QP is solved.
    """
    X = np.asarray(X, dtype=np.float64)
    P = np.asarray(seeds, dtype=np.float64)
    cells = np.asarray(cells, dtype=np.int64)
    n, m = len(X), len(P)
    H = hyperplane_distances(X, P, cells, weights) if hyper is None else hyper.copy()
    if n == 0 or m == 1:
        return H
    if need is None:
        need = np.ones((n, m), dtype=bool)
    need = need.copy()
    need[np.arange(n), cells] = False
    k_idx, a_idx = np.nonzero(need)
    if len(k_idx) == 0:
        return H
    # foot of the perpendicular on H_ia, checked against all of cell a's constraints
    i_idx = cells[k_idx]
    normal = P[a_idx] - P[i_idx]
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    Z = X[k_idx] + H[k_idx, a_idx][:, None] * normal
    w = np.zeros(m) if weights is None else np.asarray(weights, dtype=np.float64)
    dz = ((Z[:, None, :] - P[None, :, :]) ** 2).sum(2) if len(Z) * m * P.shape[1] < 2e7 else \
        np.stack([((Z - p) ** 2).sum(1) for p in P], axis=1)
    dz = dz - w[None, :]
    own = dz[np.arange(len(Z)), a_idx]
    scale = 1e-9 * np.maximum(1.0, dz.max(axis=1))
    inside = (own[:, None] <= dz + scale[:, None]).all(axis=1)
    hard = np.flatnonzero(~inside)
    if len(hard):
        geom = CellGeometry(P, weights)
        Uc = geom.coords(X[k_idx[hard]])
        out = _solve_batch(geom, Uc, a_idx[hard])
        ok = np.isfinite(out)  # unsolved problems keep the bisector bound (conservative)
        kk, aa = k_idx[hard][ok], a_idx[hard][ok]
        # numerical safety: never below the bisector bound
        H[kk, aa] = np.maximum(out[ok], H[kk, aa])
    return H
