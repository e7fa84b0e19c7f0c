"""The per-tile kernel of the all-pairs pass: a native (C, via ctypes) version and
the numpy version of the same computation.

A tile is a float32 block ``G`` of squared distances between ``m`` target
features (rows) and ``k`` contributor features (columns). For every row the tile
kernel

* adds the kernel terms ``sum_c s_c K(G[r, c] * w[c])`` to ``dens[r]``,
* adds ``sum_c s_c |dK/d(d^2)|`` to ``err[r]`` (times the error of a float32
  squared distance this bounds the error of the row's density),
* returns the pairs ``(r, c)`` with ``G[r, c] < rad2[r]`` (candidate tree edges),

skipping the self pair ``c == r + self_col``. The native kernel is loaded from
``_tilekernel*.so`` next to this file when it was built at install time (see
``setup.py``); otherwise, or with ``DQM_NATIVE=0`` in the environment, the numpy
version runs. Both give the same candidates and densities equal to float32
rounding (a test checks it).
"""
from __future__ import annotations

import ctypes
import glob
import logging
import os
from typing import Optional, Tuple

import numpy as np

KERNEL_CODES = {"gaussian": 0, "quadratic": 1}
_EXP_CLAMP = 87.0  # exp(-87) is the smallest normal float32 magnitude we produce


#: the kernel's contract with this module (``dqm_kernel_version`` in _tilekernel.c): a build of another one is not
#: loaded (2: the scan task's distances in strips, its G buffer one strip)
KERNEL_VERSION = 2


def _load() -> Optional[ctypes.CDLL]:
    if os.environ.get("DQM_NATIVE", "1") == "0":
        return None
    here = os.path.dirname(os.path.abspath(__file__))
    for path in sorted(glob.glob(os.path.join(here, "_tilekernel*.so"))):
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        try:
            version = lib.dqm_kernel_version
        except AttributeError:
            version = None
        else:
            version.restype = ctypes.c_int32
            version = int(version())
        if version != KERNEL_VERSION:
            logging.getLogger("dqm.core").warning(
                "%s is a native kernel built for another dqm (version %s, this one needs %d): the numpy version "
                "runs (slower); rebuild it with pip install -e .", path, version, KERNEL_VERSION)
            continue
        fn = lib.dqm_tile
        f32 = np.ctypeslib.ndpointer(np.float32, flags="C_CONTIGUOUS")
        f64 = np.ctypeslib.ndpointer(np.float64, flags="C_CONTIGUOUS")
        i32 = np.ctypeslib.ndpointer(np.int32, flags="C_CONTIGUOUS")
        fn.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
            f32, f32, ctypes.c_int32, f32, ctypes.c_int64, f64, f64, i32, i32, ctypes.c_int64,
        ]
        fn.restype = ctypes.c_int64
        sym = lib.dqm_tile_sym
        sym.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
            f32, f32, f32, f32, ctypes.c_int32, f32, f32, f64, f64, f64, f64, f32, f32,
            i32, i32, ctypes.c_int64,
        ]
        sym.restype = ctypes.c_int64
        nn = lib.dqm_nearest_sym
        nn.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
            ctypes.c_void_p, ctypes.c_void_p, f32, f32, i32, i32, f32, ctypes.c_int64,
        ]
        nn.restype = ctypes.c_int64
        aw = lib.dqm_any_within
        u8 = np.ctypeslib.ndpointer(np.uint8, flags="C_CONTIGUOUS")
        aw.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, f32, f32, u8]
        aw.restype = None
        pt = lib.dqm_parent_tile
        i64 = np.ctypeslib.ndpointer(np.int64, flags="C_CONTIGUOUS")
        pt.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64,
            ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, f64, f64, ctypes.c_void_p,
            f32, f32, f32, f32, f32, f32, f32, f32, i64, i64, f32, ctypes.c_int64,
        ]
        pt.restype = ctypes.c_int64
        lib.dqm_gemm_d2_u8.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64,
                                       ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                                       f32, ctypes.c_int64]
        lib.dqm_gemm_d2_u8.restype = ctypes.c_int32
        lib.dqm_pack_u8.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                                    ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p]
        lib.dqm_pack_u8.restype = None
        lib.dqm_min_tile_u8.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64,
                                        ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                                        ctypes.c_int32, f32, f32, f32]
        lib.dqm_min_tile_u8.restype = ctypes.c_int32
        lib.dqm_pass_tile_u8.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p,
            ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, f32, f32, f32, f32, f32, ctypes.c_int32, f32, f32,
            f64, f64, f64, f64, f32, f32, i32, i32, ctypes.c_int64]
        lib.dqm_pass_tile_u8.restype = ctypes.c_int64
        u64 = np.ctypeslib.ndpointer(np.uint64, flags="C_CONTIGUOUS")
        lib.dqm_scan_tile.argtypes = [
            ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, f32, f32, f32, f32, ctypes.c_int32,
            f32, f32, ctypes.c_int64, ctypes.c_int64, i32, u64, ctypes.c_int64, ctypes.c_int32, f64, f64, f32,
            i32, i32, f32, ctypes.c_int64]
        lib.dqm_scan_tile.restype = ctypes.c_int64
        vp, i64v = ctypes.c_void_p, ctypes.c_int64
        lib.dqm_scan_task.argtypes = [vp, i64v, vp, vp, vp, i64v, vp, i64v, i64v, i64v, i64v, i64v, vp, vp,
                                      ctypes.c_int32, vp, vp, vp, vp, i64v, ctypes.c_int32] + [vp] * 12 + [i64v]
        lib.dqm_scan_task.restype = ctypes.c_int64
        lib.dqm_keep_nearest.argtypes = [i32, i32, f32, ctypes.c_int64, i64, ctypes.c_void_p, ctypes.c_int32,
                                         f32, i32, i32, f32]
        lib.dqm_keep_nearest.restype = ctypes.c_int64
        lib.dqm_merge_clusters.argtypes = [ctypes.c_int64, ctypes.c_int64, i64, i64, f64, f64, i64, ctypes.c_double,
                                           i64]
        lib.dqm_merge_clusters.restype = ctypes.c_int64
        lib.dqm_sq_dist_u8.argtypes = [u8, ctypes.c_int64, i64, i64, ctypes.c_int64, f64]
        lib.dqm_sq_dist_u8.restype = None
        lib.dqm_nearest_above.argtypes = [ctypes.c_int64, i64, i64, f64, ctypes.c_void_p, ctypes.c_void_p, i64, f64,
                                          i64]
        lib.dqm_nearest_above.restype = None
        lib.dqm_smallest.argtypes = [f32, ctypes.c_int64, ctypes.c_int64, ctypes.c_int64, ctypes.c_int32, i32]
        lib.dqm_smallest.restype = None
        lib.dqm_sum_roundings.restype = ctypes.c_int32
        lib.dqm_simd_level.restype = ctypes.c_int32
        lib.dqm_set_simd_level.argtypes = [ctypes.c_int32]
        lib.dqm_set_simd_level.restype = ctypes.c_int32
        try:  # a kernel built before it lacks it: guided matching then runs in numpy
            es = lib.dqm_epipolar_scan
        except AttributeError:
            pass
        else:
            d, i64v = ctypes.c_double, ctypes.c_int64
            es.argtypes = [i64v, f64, i64, i64v, i64, f64, f64, i64, d, ctypes.c_int32, f64, f64, f64, f64, d, d, u8,
                           u8, i64v, i64, f64, f64, i64, f64, f64]
            es.restype = ctypes.c_int64
        return lib
    return None


_LIB = _load()

#: most columns of one tile row the native kernel takes (its sums' error bound assumes it)
MAX_ROW = 1024
#: how many times the native kernel rounds a kernel term in float32 before it reaches a
#: float64 sum (the numpy version rounds it fewer times): the tile kernel's contract
SUM_ROUNDINGS = int(_LIB.dqm_sum_roundings()) if _LIB is not None else 1
#: whether the loaded kernel has guided matching's epipolar pass (one built before it has not)
_HAS_EPIPOLAR = _LIB is not None and hasattr(_LIB, "dqm_epipolar_scan")


def native_available() -> bool:
    """True when the compiled tile kernel is loaded."""
    return _LIB is not None


def kernel_description() -> str:
    """Which tile kernel runs, in words (for ``dqm --version`` and ``dqm doctor``)."""
    if _LIB is None:
        why = "disabled by DQM_NATIVE=0" if os.environ.get("DQM_NATIVE", "1") == "0" else "not built"
        return f"numpy fallback (native kernel {why}; about 12x slower on large inputs)"
    return f"native C ({SIMD_NAMES[simd_level()]})"


#: the tile kernel's loops by level (:func:`simd_level`)
SIMD_NAMES = {0: "portable C", 1: "AVX2", 2: "AVX-512", 3: "AVX-512, VNNI uint8 distances"}


def simd_level() -> int:
    """Which loops the native kernel runs: 3 AVX-512 with VNNI (uint8 descriptors' distances by integer
    dot products, :class:`U8Operands`), 2 AVX-512, 1 AVX2, 0 portable C (-1: no native kernel)."""
    if _LIB is None:
        return -1
    return int(_LIB.dqm_simd_level())


def set_simd_level(cap: int) -> int:
    """Run at most the loops of level ``cap`` (never more than the CPU has); returns the level in use.

    For tests and benchmarks that compare the levels on one machine."""
    if _LIB is None:
        return -1
    return int(_LIB.dqm_set_simd_level(int(cap)))


_WARNED_FALLBACK = False


def warn_if_fallback(n: int, threshold: int = 20_000) -> None:
    """Warn once per process when the numpy fallback handles a large input."""
    global _WARNED_FALLBACK
    if _LIB is None and n >= threshold and not _WARNED_FALLBACK:
        import warnings

        _WARNED_FALLBACK = True
        warnings.warn(f"quickmatch: the native tile kernel is not in use ({kernel_description()}); "
                      "reinstall with a C compiler present (pip install -e .) and check with 'dqm doctor'",
                      stacklevel=3)


def _check_code(code: int, k: int) -> None:
    """Raise for the native kernel's error codes (-1, the caller's buffer being full, is not one)."""
    if code == -2:
        raise ValueError(f"tile rows of {k} columns: the native kernel takes at most {MAX_ROW}")
    if code == -3:
        raise RuntimeError("the VNNI kernel is not available on this CPU")


def tile_numpy(
    G: np.ndarray, w: np.ndarray, s: np.ndarray, kernel: str, rad2: np.ndarray,
    self_col: int, dens: np.ndarray, err: np.ndarray,
) -> Tuple[np.ndarray, np.ndarray]:
    """numpy version of the tile kernel (see the module docstring)."""
    m, k = G.shape
    d2 = np.maximum(G, 0.0)
    t = d2 * w[None, :]
    if kernel == "gaussian":
        np.minimum(t, _EXP_CLAMP, out=t)
        E = np.exp(-t)
        dE = E * w[None, :]
    else:
        q = 1.0 - t
        E = np.maximum(q, 0.0)
        dE = (q > -0.01) * w[None, :]
    E *= s[None, :]
    dE *= s[None, :]
    rows = np.arange(m)
    cols = rows + self_col
    has_self = (cols >= 0) & (cols < k)
    E[rows[has_self], cols[has_self]] = 0.0
    dE[rows[has_self], cols[has_self]] = 0.0
    dens += E.sum(axis=1, dtype=np.float64)
    err += dE.sum(axis=1, dtype=np.float64)
    mask = G < rad2[:, None]
    mask[rows[has_self], cols[has_self]] = False
    r, c = np.nonzero(mask)
    return r.astype(np.int32), c.astype(np.int32)


def _head(buffer: np.ndarray, got: int) -> np.ndarray:
    """The first ``got`` entries of an output buffer, copied when they fill less than half of it: a view
    keeps the whole buffer alive, and the streaming parent pass holds every tile's output until it prunes
    (4 * (m + k) entries of 20 bytes per tile: a peak RSS of 2.14 GiB under a budget of 1 GiB at 300k
    features, 0.69 GiB after)."""
    return buffer[:got].copy() if 2 * got < len(buffer) else buffer[:got]


def tile(
    G: np.ndarray, w: np.ndarray, s: np.ndarray, kernel: str, rad2: np.ndarray,
    self_col: int, dens: np.ndarray, err: np.ndarray, use_native: bool = True,
) -> Tuple[np.ndarray, np.ndarray]:
    """Run the tile kernel, natively when available. ``G`` must be C-contiguous float32."""
    if _LIB is None or not use_native:
        return tile_numpy(G, w, s, kernel, rad2, self_col, dens, err)
    m, k = G.shape
    cap = max(1024, 4 * m)
    ws = np.ascontiguousarray(w, dtype=np.float32)
    ss = np.ascontiguousarray(s, dtype=np.float32)
    while True:
        cr = np.empty(cap, dtype=np.int32)
        cc = np.empty(cap, dtype=np.int32)
        d_add = np.zeros(m, dtype=np.float64)
        e_add = np.zeros(m, dtype=np.float64)
        got = _LIB.dqm_tile(
            G.ctypes.data, m, k, G.strides[0] // 4, ws, ss, KERNEL_CODES[kernel],
            np.ascontiguousarray(rad2, dtype=np.float32), self_col, d_add, e_add, cr, cc, cap,
        )
        if got >= 0:
            dens += d_add
            err += e_add
            return _head(cr, got), _head(cc, got)
        _check_code(got, k)
        cap *= 4


def _scan_keep(col_bits: np.ndarray, row_list: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """[r, c]: column c does not scan the list of row ``rows[r]`` (bit row_list of its bitset)."""
    a = row_list[rows].astype(np.int64)
    word = col_bits[:, a >> 6].T  # (len(rows), k)
    return ((word >> (a & 63).astype(np.uint64)[:, None]) & np.uint64(1)) == 0


def scan_tile_numpy(G, wc, sc, wr, sr, kernel, rad2r, rad2c, n_own, self_col, row_list, col_bits, list_index,
                    dens_r, dens_c) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """numpy version of the fast engine's scan tile (see ``dqm_scan_tile`` in _tilekernel.c)."""
    m, k = G.shape
    g = np.maximum(G, 0.0)
    E, _ = _terms(g, wc[None, :], sc[None, :], kernel)
    keep = np.ones((m, k), dtype=bool)
    own = np.arange(m) < n_own
    rows = np.arange(m)
    cols = rows + self_col
    has_self = own & (cols >= 0) & (cols < k)
    keep[rows[has_self], cols[has_self]] = False
    other = np.flatnonzero(~own)
    test = other[row_list[other] > list_index]
    if len(test):
        keep[test] = _scan_keep(col_bits, row_list, test)
    E = E * keep
    dens_r += E.sum(axis=1, dtype=np.float64)
    fr, fc = np.nonzero((G < rad2r[:, None]) & keep)
    fg = G[fr, fc]
    if len(other):
        Er, _ = _terms(g[other], wr[other, None], sr[other, None], kernel)
        kept = keep[other]
        dens_c += (Er * kept).sum(axis=0, dtype=np.float64)
        rr, rc = np.nonzero((G[other] < rad2c[None, :]) & kept)
        fg = np.concatenate([fg, G[other[rr], rc]])
        fr = np.concatenate([fr, -1 - other[rr]])
        fc = np.concatenate([fc, rc])
    return fr.astype(np.int32), fc.astype(np.int32), fg.astype(np.float32)


def scan_tile(G, wc, sc, wr, sr, kernel, rad2r, rad2c, n_own, self_col, row_list, col_bits, list_index,
              dens_r, dens_c, use_native: bool = True) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The fast engine's scan tile, natively when available: adds kernel terms to ``dens_r`` (rows) and
    ``dens_c`` (columns) and returns the edges ``(r, c)`` (row r the child) and ``(-1 - r, c)`` (column c
    the child) with their ``G`` values. ``G`` must be C-contiguous float32 with at most :data:`MAX_ROW` columns."""
    if _LIB is None or not use_native:
        return scan_tile_numpy(G, wc, sc, wr, sr, kernel, rad2r, rad2c, n_own, self_col, row_list, col_bits,
                               list_index, dens_r, dens_c)
    m, k = G.shape
    cap = _scan_edge_cap(m)
    f = lambda a: np.ascontiguousarray(a, dtype=np.float32)  # noqa: E731
    args = (f(wc), f(sc), f(wr), f(sr), KERNEL_CODES[kernel], f(rad2r), f(rad2c), int(n_own), int(self_col),
            np.ascontiguousarray(row_list, dtype=np.int32), col_bits, col_bits.shape[1], int(list_index))
    cacc = np.empty(k, dtype=np.float32)
    while True:
        cr, cc, cg = _edge_buffers(cap)
        d_r = np.zeros(m)
        d_c = np.zeros(k)
        got = _LIB.dqm_scan_tile(G.ctypes.data, m, k, G.strides[0] // 4, *args, d_r, d_c, cacc, cr, cc, cg, cap)
        if got >= 0:
            dens_r += d_r
            dens_c += d_c
            return _head(cr, got), _head(cc, got), _head(cg, got)
        _check_code(got, k)
        cap *= 4


def keep_nearest_numpy(er, ec, eg, rows, image, best_g, best_c, count, lim) -> None:
    """numpy version of ``dqm_keep_nearest`` (see :func:`keep_nearest`)."""
    k = best_g.shape[1]
    rev = er < 0
    at = rows[np.where(rev, -1 - er.astype(np.int64), er)]
    child = np.where(rev, ec, at).astype(np.int64)
    cand = np.where(rev, at, ec).astype(np.int64)
    g = np.asarray(eg, dtype=np.float32)
    if image is not None:
        other = image[child] != image[cand]
        child, cand, g = child[other], cand[other], g[other]
    full = count[child] == k
    enter = ~full | (g < best_g[child, k - 1]) | ((g == best_g[child, k - 1]) & (cand < best_c[child, k - 1]))
    child, cand, g = child[enter], cand[enter], g[enter]
    if not len(child):
        return
    touched = np.unique(child)
    held = count[touched]
    hc = np.repeat(touched, held)
    slot = np.arange(len(hc)) - np.repeat(np.cumsum(held) - held, held)
    child = np.concatenate([hc, child])
    cand = np.concatenate([best_c[hc, slot].astype(np.int64), cand])
    g = np.concatenate([best_g[hc, slot], g])
    order = np.lexsort((cand, g, child))
    child, cand, g = child[order], cand[order], g[order]
    rank = np.arange(len(child)) - np.searchsorted(child, child, side="left")
    keep = rank < k
    best_g[child[keep], rank[keep]] = g[keep]
    best_c[child[keep], rank[keep]] = cand[keep]
    count[touched] = np.minimum(np.diff(np.searchsorted(child, touched, side="left"), append=len(child)), k)
    now_full = touched[count[touched] == k]
    lim[now_full] = np.nextafter(best_g[now_full, k - 1], np.float32(np.inf))


def keep_nearest(er, ec, eg, rows, image, best_g, best_c, count, lim, use_native: bool = True) -> None:
    """Offer the scan tile's edges (``(r, c)``: child ``rows[r]``, candidate ``c``; ``(-1 - r, c)``: child
    ``c``, candidate ``rows[-1 - r]``) to each child's ``k`` nearest, held in ``best_g`` / ``best_c`` ((n, k),
    ordered by (g, candidate)) with ``count`` filled; pairs within one ``image`` (if given) are skipped.
    ``lim[child]`` becomes the smallest float32 above the k-th g once k are held, a radius that the scan
    tile can test. The kept set does not depend on the order edges come in."""
    if _LIB is None or not use_native:
        keep_nearest_numpy(er, ec, eg, rows, image, best_g, best_c, count, lim)
        return
    img = None if image is None else np.ascontiguousarray(image, dtype=np.int32)
    _LIB.dqm_keep_nearest(
        np.ascontiguousarray(er, dtype=np.int32), np.ascontiguousarray(ec, dtype=np.int32),
        np.ascontiguousarray(eg, dtype=np.float32), len(er), np.ascontiguousarray(rows, dtype=np.int64),
        None if img is None else img.ctypes.data, best_g.shape[1], best_g, best_c, count, lim)


def smallest(D: np.ndarray, t: int, use_native: bool = True) -> np.ndarray:
    """Column indices of the ``t`` smallest entries of every row of the float32 matrix ``D``, ordered by
    (value, index), NaN as +inf: ``(m, t)`` int32 (``t <= D.shape[1]``)."""
    D = np.ascontiguousarray(D, dtype=np.float32)
    m, k = D.shape
    t = int(t)
    if not 1 <= t <= k:
        raise ValueError(f"smallest: t = {t} of {k} columns")
    if _LIB is None or not use_native:
        order = np.argsort(np.where(np.isnan(D), np.float32(np.inf), D), axis=1, kind="stable")
        return np.ascontiguousarray(order[:, :t], dtype=np.int32)
    out = np.empty((m, t), dtype=np.int32)
    if m:
        _LIB.dqm_smallest(D, m, k, k, t, out)
    return out


def sq_distances_u8(X: np.ndarray, a: np.ndarray, b: np.ndarray) -> Optional[np.ndarray]:
    """Exact squared distances ``|X[a_k] - X[b_k]|^2`` of uint8 rows natively (float64); None without the
    native kernel or for other inputs (the caller's numpy loop then)."""
    if _LIB is None or X.dtype != np.uint8 or X.ndim != 2 or X.shape[1] > 32768 or not X.flags.c_contiguous:
        return None
    a = np.ascontiguousarray(a, dtype=np.int64)
    b = np.ascontiguousarray(b, dtype=np.int64)
    out = np.empty(len(a), dtype=np.float64)
    if len(a):
        _LIB.dqm_sq_dist_u8(X, X.shape[1], a, b, len(a), out)
    return out


def epipolar_scan_takes(X: np.ndarray) -> bool:
    """Whether :func:`epipolar_scan` runs natively for these descriptors (the kernel has it; uint8 rows)."""
    return (_HAS_EPIPOLAR and X.dtype == np.uint8 and X.ndim == 2 and X.shape[1] <= 32768
            and X.flags.c_contiguous)


def epipolar_scan(windows, rows_are_lines: bool, lines: np.ndarray, norm_b: np.ndarray, norm_a: np.ndarray,
                  xb: np.ndarray, tol: float, t2: float, X: np.ndarray, line_rows: np.ndarray,
                  point_rows: np.ndarray, best_r: np.ndarray, bd_r: np.ndarray, sd_r: np.ndarray,
                  best_c: np.ndarray, bd_c: np.ndarray, sd_c: np.ndarray) -> int:
    """One search of guided matching's epipolar candidates, fused with their descriptor distances and each
    side's two nearest (``dqm_epipolar_scan`` in ``_tilekernel.c`` says what it computes; the numpy
    version is :func:`dqm.vision.guided.consistent_pairs` with ``_best_two`` there). ``windows``: a
    ``_LineWindows`` of dqm.vision.guided; ``X``: uint8 descriptors, rows ``line_rows`` those of the
    lines' features, ``point_rows`` those of the points'; the six best / second arrays are updated in
    place. Returns the pairs kept. Only where :func:`epipolar_scan_takes` the descriptors (the caller's
    numpy path otherwise)."""
    if not epipolar_scan_takes(X):
        raise ValueError("epipolar_scan: no native kernel for these descriptors (check epipolar_scan_takes)")
    f64, i64, c = np.float64, np.int64, np.ascontiguousarray
    w = windows
    return int(_LIB.dqm_epipolar_scan(
        len(w.center), c(w.center, f64), np.argsort(w.center, kind="stable"), len(w.width),
        c(w.group_start, i64), c(w.width, f64), c(w.key, f64), c(w.point, i64), float(w.period),
        int(bool(rows_are_lines)), c(lines, f64), c(norm_b, f64), c(norm_a, f64), c(xb, f64), float(tol),
        float(t2), X[line_rows], X[point_rows[w.point]], X.shape[1], best_r, bd_r, sd_r, best_c, bd_c, sd_c))


def merge_roots(n: int, child: np.ndarray, parent: np.ndarray, d: np.ndarray, sigma: np.ndarray,
                image: np.ndarray, rho: float) -> Optional[np.ndarray]:
    """Break/merge natively (``dqm_merge_clusters``): every feature's root after merging along the edges
    ``child -> parent`` (already in increasing (d, child) order); None without the native kernel (the
    caller runs :func:`dqm.core.tree.merge_clusters`' Python loop)."""
    if _LIB is None:
        return None
    root = np.empty(n, dtype=np.int64)
    i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    code = _LIB.dqm_merge_clusters(n, len(child), i64(child), i64(parent), f64(d), f64(sigma), i64(image),
                                   float(rho), root)
    if code:
        raise MemoryError("dqm_merge_clusters: out of memory")
    return root


def nearest_above(n: int, child: np.ndarray, cand: np.ndarray, dist: np.ndarray, key: Optional[np.ndarray] = None,
                  density: Optional[np.ndarray] = None) -> Optional[Tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Every child's first edge in (distance, key, position) order, natively in one pass (``dqm_nearest_above``;
    with ``density``, only candidates that rank above their child): ``(parent, distance, row)`` as
    :func:`dqm.core.tree.nearest_candidates` returns them; None without the native kernel."""
    if _LIB is None:
        return None
    i64 = lambda a: np.ascontiguousarray(a, dtype=np.int64)  # noqa: E731
    child, cand = i64(child), i64(cand)
    dist = np.ascontiguousarray(dist, dtype=np.float64)
    key = None if key is None else i64(key)
    density = None if density is None else np.ascontiguousarray(density, dtype=np.float64)
    if len(child) and (child.min() < 0 or child.max() >= n):  # the C loop indexes with them unchecked
        raise IndexError(f"nearest_above: a child index outside 0..{n - 1}")
    if density is not None and len(cand) and (cand.min() < 0 or cand.max() >= len(density)):
        raise IndexError("nearest_above: a candidate index outside the densities")
    parent = np.full(n, -1, dtype=np.int64)
    pdist = np.full(n, np.inf)
    row = np.full(n, -1, dtype=np.int64)
    _LIB.dqm_nearest_above(len(child), child, cand, dist, None if key is None else key.ctypes.data,
                           None if density is None else density.ctypes.data, parent, pdist, row)
    return parent, pdist, row


def _terms(d2: np.ndarray, w, s, kernel: str) -> Tuple[np.ndarray, np.ndarray]:
    """Kernel terms and error weights of float32 squared distances (numpy)."""
    t = np.maximum(d2, 0.0) * w
    if kernel == "gaussian":
        np.minimum(t, _EXP_CLAMP, out=t)
        E = np.exp(-t) * s
        dE = E * w
    else:
        q = 1.0 - t
        E = np.maximum(q, 0.0) * s
        dE = (q > -0.01) * (w * s)
    return E, dE


def tile_sym_numpy(G, wc, sc, wr, sr, kernel, rad2r, rad2c, dens_r, err_r, dens_c, err_c):
    """numpy version of the symmetric off-diagonal tile (rows and columns disjoint)."""
    E, dE = _terms(G, wc[None, :], sc[None, :], kernel)
    dens_r += E.sum(axis=1, dtype=np.float64)
    err_r += dE.sum(axis=1, dtype=np.float64)
    E, dE = _terms(G, wr[:, None], sr[:, None], kernel)
    dens_c += E.sum(axis=0, dtype=np.float64)
    err_c += dE.sum(axis=0, dtype=np.float64)
    r, c = np.nonzero((G < rad2r[:, None]) | (G < rad2c[None, :]))
    return r.astype(np.int32), c.astype(np.int32)


def tile_sym(G, wc, sc, wr, sr, kernel, rad2r, rad2c, dens_r, err_r, dens_c, err_c, use_native=True):
    """Symmetric off-diagonal tile: densities of rows and of columns, candidate pairs
    ``(r, c)`` with ``G < max(rad2r[r], rad2c[c])``. ``G`` C-contiguous float32."""
    if _LIB is None or not use_native:
        return tile_sym_numpy(G, wc, sc, wr, sr, kernel, rad2r, rad2c, dens_r, err_r, dens_c, err_c)
    m, k = G.shape
    cap = max(1024, 4 * (m + k))
    scratch_a = np.empty(k, dtype=np.float32)
    scratch_e = np.empty(k, dtype=np.float32)
    while True:
        cr = np.empty(cap, dtype=np.int32)
        cc = np.empty(cap, dtype=np.int32)
        dr = np.zeros(m)
        er = np.zeros(m)
        dc = np.zeros(k)
        ec = np.zeros(k)
        got = _LIB.dqm_tile_sym(
            G.ctypes.data, m, k, G.strides[0] // 4, wc, sc, wr, sr, KERNEL_CODES[kernel],
            rad2r, rad2c, dr, er, dc, ec, scratch_a, scratch_e, cr, cc, cap,
        )
        if got >= 0:
            dens_r += dr
            err_r += er
            dens_c += dc
            err_c += ec
            return _head(cr, got), _head(cc, got)
        _check_code(got, k)
        cap *= 4


def nearest_sym(G: np.ndarray, slack_r: Optional[np.ndarray], slack_c: Optional[np.ndarray],
                use_native: bool = True):
    """Tile of the distinctiveness pass (self pairs already set to a huge value in ``G``).

    Returns ``(rmin, cmin, r, c, g)``: row and column minima of the tile and
    every entry within ``slack`` of its row's or its column's minimum; with
    ``slack_r`` None the minima only (``r``, ``c``, ``g`` empty).
    """
    m, k = G.shape
    none = np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros(0, np.float32)
    if _LIB is None or not use_native:
        rmin = G.min(axis=1)
        cmin = G.min(axis=0)
        if slack_r is None:
            return (rmin, cmin) + none
        near = (G <= (rmin + slack_r)[:, None]) | (G <= (cmin + slack_c)[None, :])
        r, c = np.nonzero(near & (G < np.finfo(np.float32).max))
        return rmin, cmin, r, c, G[r, c]
    rmin = np.empty(m, dtype=np.float32)
    cmin = np.empty(k, dtype=np.float32)
    if slack_r is None:
        _check_code(_LIB.dqm_nearest_sym(G.ctypes.data, m, k, G.strides[0] // 4, None, None, rmin, cmin, *none, 0),
                    k)
        return (rmin, cmin) + none
    sr = np.ascontiguousarray(slack_r, dtype=np.float32)
    sc = np.ascontiguousarray(slack_c, dtype=np.float32)
    cap = max(1024, 4 * (m + k))
    while True:
        cr = np.empty(cap, dtype=np.int32)
        cc = np.empty(cap, dtype=np.int32)
        cg = np.empty(cap, dtype=np.float32)
        got = _LIB.dqm_nearest_sym(G.ctypes.data, m, k, G.strides[0] // 4, sr.ctypes.data, sc.ctypes.data, rmin,
                                   cmin, cr, cc, cg, cap)
        if got >= 0:
            return rmin, cmin, _head(cr, got), _head(cc, got), _head(cg, got)
        _check_code(got, k)
        cap *= 4


def any_within(G: np.ndarray, rad2r: np.ndarray, rad2c: np.ndarray, hit: np.ndarray,
               use_native: bool = True) -> None:
    """Set ``hit[r]`` where some column has ``G[r, c] < max(rad2r[r], rad2c[c])`` (rows already hit stay).

    ``G`` C-contiguous float32; ``hit`` uint8, updated in place.
    """
    m, k = G.shape
    if _LIB is None or not use_native:
        todo = hit == 0
        if todo.any():
            g = G[todo]
            hit[todo] |= ((g < rad2r[todo][:, None]) | (g < rad2c[None, :])).any(axis=1).astype(np.uint8)
        return
    _LIB.dqm_any_within(G.ctypes.data, m, k, G.strides[0] // 4, np.ascontiguousarray(rad2r, dtype=np.float32),
                        np.ascontiguousarray(rad2c, dtype=np.float32), hit)


def rank_relation(lo: np.ndarray, hi: np.ndarray, cand: np.ndarray, child: np.ndarray) -> np.ndarray:
    """Rank of ``cand`` relative to ``child`` from density intervals ``[lo, hi]``:
    1 certainly above, -1 certainly below, 0 uncertain (exact densities decide).
    Two exact (degenerate) equal intervals are certain: equal densities rank by index."""
    lc, hc, lj, hj = lo[cand], hi[cand], lo[child], hi[child]
    rel = np.zeros(len(cand), dtype=np.int8)
    tie = (lc == hc) & (lj == hj) & (lc == lj)
    rel[tie] = np.where(cand[tie] < child[tie], 1, -1)
    rel[lc > hj] = 1
    rel[hc < lj] = -1
    return rel


def parent_tile_numpy(G, ra, cb, diag, lo, hi, img, rad2r, rad2c, limr, limc, slackr, slackc):
    """numpy version of the parent tile (see :func:`parent_tile`)."""
    m, k = G.shape
    out_child, out_cand, out_g = [], [], []
    rmin = np.full(m, np.finfo(np.float32).max, dtype=np.float32)
    cmin = np.full(k, np.finfo(np.float32).max, dtype=np.float32)
    directions = [(G < rad2r[:, None], False)]
    if not diag:
        directions.append((G < rad2c[None, :], True))
    for mask, col_child in directions:
        if diag:
            np.fill_diagonal(mask, False)
        r, c = np.nonzero(mask)
        g = G[r, c]
        jr, jc = r + ra, c + cb
        child, cand, loc = (jc, jr, c) if col_child else (jr, jc, r)
        if img is not None:
            other = img[child] != img[cand]
            child, cand, loc, g = child[other], cand[other], loc[other], g[other]
        rel = rank_relation(lo, hi, cand, child)
        above = rel > 0
        tmin = cmin if col_child else rmin
        np.minimum.at(tmin, loc[above], g[above])
        lim = np.minimum((limc if col_child else limr)[loc], tmin[loc] + (slackc if col_child else slackr)[loc])
        keep = (rel == 0) | (above & (g <= lim))
        out_child.append(child[keep])
        out_cand.append(cand[keep])
        out_g.append(g[keep])
    return rmin, cmin, np.concatenate(out_child), np.concatenate(out_cand), np.concatenate(out_g)


def parent_tile(G, ra, cb, diag, lo, hi, img, rad2r, rad2c, limr, limc, slackr, slackc, use_native=True):
    """Tile of the streaming parent pass: rows are features ``ra..``, columns ``cb..``.

    For every child (row; on an off-diagonal tile also column) returns the
    tile minimum of ``G`` over candidates within its radius that certainly rank
    above it (``rmin``, ``cmin``; float32 max when none), and writes out
    ``(child, cand, g)`` (global indices) for those candidates within
    ``min(lim, tile minimum + slack)`` of the child and for every candidate of
    uncertain rank. ``img`` (int32 image index per feature, or None) excludes
    same-image candidates. ``G`` C-contiguous float32.
    """
    m, k = G.shape
    if _LIB is None or not use_native:
        return parent_tile_numpy(G, ra, cb, diag, lo, hi, img, rad2r, rad2c, limr, limc, slackr, slackc)
    cap = max(4096, 4 * (m + k))
    rmin = np.empty(m, dtype=np.float32)
    cmin = np.empty(k, dtype=np.float32)
    img_ptr = None if img is None else img.ctypes.data
    while True:
        oc = np.empty(cap, dtype=np.int64)
        od = np.empty(cap, dtype=np.int64)
        og = np.empty(cap, dtype=np.float32)
        got = _LIB.dqm_parent_tile(G.ctypes.data, m, k, G.strides[0] // 4, ra, cb, int(bool(diag)), lo, hi,
                                   img_ptr, rad2r, rad2c, limr, limc, slackr, slackc, rmin, cmin, oc, od, og, cap)
        if got >= 0:
            return rmin, cmin, _head(oc, got), _head(od, got), _head(og, got)
        cap *= 4


def _openblas_paths():
    """Paths of the OpenBLAS libraries loaded in this process (Linux; empty elsewhere)."""
    np.ones((2, 2)) @ np.ones((2, 2))  # make sure BLAS is loaded
    try:
        with open("/proc/self/maps") as fh:
            return sorted({line.split()[-1] for line in fh if "openblas" in line.split()[-1].lower()})
    except OSError:
        return []


def blas_description() -> str:
    """Which BLAS kernels numpy's GEMMs run, in words (for ``dqm doctor``)."""
    forced = os.environ.get("OPENBLAS_CORETYPE")
    note = f" (OPENBLAS_CORETYPE={forced} in the environment)" if forced else ""
    paths = _openblas_paths()
    for path in paths:
        lib = ctypes.CDLL(path)
        for name in ("scipy_openblas_get_corename64_", "scipy_openblas_get_corename", "openblas_get_corename64_",
                     "openblas_get_corename"):
            fn = getattr(lib, name, None)
            if fn is not None:
                fn.restype = ctypes.c_char_p
                core = fn().decode()
                return f"OpenBLAS, {core} kernels{note}"
    return f"an OpenBLAS without a core name: {', '.join(paths)}" if paths else "not OpenBLAS, or not found"


def _blas_local_threads():
    """``openblas_set_num_threads_local`` of the OpenBLAS numpy uses, if any (else None)."""
    for path in _openblas_paths():
        try:
            fn = ctypes.CDLL(path).openblas_set_num_threads_local
        except (OSError, AttributeError):
            continue
        fn.argtypes = [ctypes.c_int]
        fn.restype = ctypes.c_int
        return fn
    return None


_BLAS_LOCAL = None
_BLAS_CHECKED = False


def single_threaded_blas_in_this_thread() -> bool:
    """Make BLAS calls from the calling thread single-threaded (OpenBLAS >= 0.3.27).

    The all-pairs pass runs one tile per worker thread; letting each tile's
    GEMM spawn its own BLAS threads as well would oversubscribe the cores.
    Returns False when the BLAS offers no per-thread setting.
    """
    global _BLAS_LOCAL, _BLAS_CHECKED
    if not _BLAS_CHECKED:
        _BLAS_LOCAL = _blas_local_threads()
        _BLAS_CHECKED = True
    if _BLAS_LOCAL is None:
        return False
    _BLAS_LOCAL(1)
    return True


#: rows of the VNNI kernel's register block (its operands hold this many rows of padding)
_VNNI_ROWS = 8


class U8Operands:
    """uint8 descriptors packed for the VNNI distance kernel (``simd_level() == 3``).

    Rows: ``x - 128`` as int8 (row-major, padded to a multiple of 4 bytes and by
    8 rows); columns: the raw bytes in groups of 16 features, 4 bytes of each
    at a time. With ``na = |x|^2`` and ``nb = |y|^2 - 256 sum(y)``, the kernel's
    int32 ``na + nb - 2 (x - 128) . y`` is the exact squared distance. 256 bytes
    a feature. Tiles start at multiples of 32 features.
    """

    def __init__(self, X: np.ndarray, rows: Optional[np.ndarray] = None):
        """Pack ``X`` (uint8, (n, dim)), or its rows ``rows`` (indices) in that order: one pass in C
        (``dqm_pack_u8``), the rows gathered on the way."""
        if _LIB is None or X.dtype != np.uint8:
            raise ValueError("U8Operands: uint8 descriptors and the native kernel needed")
        if X.strides[1] != 1:
            X = np.ascontiguousarray(X)
        if rows is not None:
            rows = np.ascontiguousarray(rows, np.int64)
            if len(rows) and (rows.min() < 0 or rows.max() >= len(X)):
                raise IndexError(f"U8Operands: rows outside the {len(X)} descriptors")
        n, dim = (len(X) if rows is None else len(rows)), X.shape[1]
        self.n, self.nq = n, -(-dim // 4)
        groups = -(-n // 32) * 2
        self.rows = np.empty((n + _VNNI_ROWS, 4 * self.nq), np.int8)
        self.rows[n:] = 0
        self.cols = np.empty((groups, self.nq, 16, 4), np.uint8)
        self.cols[n // 16:] = 0  # the group holding feature n and those after it (filled again up to n)
        self.na = np.zeros(n + _VNNI_ROWS, np.int32)
        self.nb = np.zeros(groups * 16, np.int32)
        _LIB.dqm_pack_u8(X.ctypes.data, X.strides[0], None if rows is None else rows.ctypes.data, n, dim,
                         self.nq, self.rows.ctypes.data, self.cols.ctypes.data, self.na.ctypes.data,
                         self.nb.ctypes.data)

    def _args(self, a: int, b: int):
        if b % 32:
            raise ValueError(f"VNNI tiles start at multiples of 32 features, not {b}")
        return (self.rows[a:].ctypes.data, self.rows.shape[1], self.na[a:].ctypes.data,
                self.cols[b // 16:].ctypes.data, self.nb[b:].ctypes.data)

    def minima(self, a: int, a1: int, b: int, b1: int, diag: bool,
               scratch: Optional[np.ndarray] = None) -> Tuple[np.ndarray, np.ndarray]:
        """Row and column minima of :meth:`d2` of rows ``a..a1`` and columns ``b..b1`` (float32; ``diag``: the
        same features, the self pairs left out; FLT_MAX where nothing is left), without making the tile:
        strips of rows in ``scratch`` (:func:`minima_scratch`, one per thread), reduced at once."""
        if scratch is None:
            scratch = minima_scratch()
        rmin = np.empty(a1 - a, np.float32)
        cmin = np.empty(b1 - b, np.float32)
        A, lda, na, B, nb = self._args(a, b)
        _check_code(_LIB.dqm_min_tile_u8(A, lda, na, a1 - a, B, nb, b1 - b, self.nq, int(diag), scratch, rmin,
                                         cmin), b1 - b)
        return rmin, cmin

    def d2(self, a: int, a1: int, b: int, b1: int, cols: Optional["U8Operands"] = None) -> np.ndarray:
        """Exact squared distances of rows ``a..a1`` to columns ``b..b1`` (float32); the columns
        are those of ``cols`` when given (packed from other descriptors of the same dimension)."""
        G = np.empty((a1 - a, b1 - b), np.float32)
        A, lda, na, B, nb = self._args(a, b)
        if cols is not None:
            _, _, _, B, nb = cols._args(a, b)
        _check_code(_LIB.dqm_gemm_d2_u8(A, lda, na, a1 - a, B, nb, b1 - b, self.nq, G, b1 - b), b1 - b)
        return G


#: rows of a strip of :meth:`U8Operands.minima` (PASS_STRIP of the C kernel)
_MIN_STRIP = 64


#: rows of a strip of a scan task's distances (SUM_CHAIN of the C kernel): the task's G holds one strip
_SCAN_STRIP = 64


def minima_scratch() -> np.ndarray:
    """A thread's scratch for :meth:`U8Operands.minima` (a strip of rows, 256 KiB)."""
    return np.empty(_MIN_STRIP * MAX_ROW, np.float32)


class U8Scan:
    """The fast engine's scan tasks on :class:`U8Operands` (the features in list order), one native call
    each (``dqm_scan_task``: the task's rows gathered, their exact squared distances to the list's columns
    and the scan tile, block by block; the same bits as :func:`scan_tile` on :meth:`U8Operands.d2` of the
    same rows). ``w``, ``s``: the features' kernel weights and activity (float32); ``rad2``: their float32
    search radii; ``limit``: the live array of radii the candidate keeper tightens (read, never copied);
    ``lists``: each feature's list (int32); ``bits``: its scanned lists ((n, words) uint64)."""

    def __init__(self, ops: U8Operands, w, s, kernel: str, rad2, limit, lists, bits):
        def c(a, dtype):
            a = np.asarray(a)
            if a.dtype != dtype or not a.flags.c_contiguous or len(a) < ops.n:
                raise ValueError(f"U8Scan: a C-contiguous {np.dtype(dtype).name} array of {ops.n} rows needed")
            return a
        self.ops = ops
        self._keep = [c(w, np.float32), c(s, np.float32), c(rad2, np.float32), c(limit, np.float32),
                      c(lists, np.int32), c(bits, np.uint64)]
        self.words = int(bits.shape[1])
        self.kernel = KERNEL_CODES[kernel]
        self._operands = (ops.rows.ctypes.data, ops.rows.shape[1], ops.na.ctypes.data, ops.cols.ctypes.data,
                          ops.nb.ctypes.data, ops.nq)
        self._arrays = tuple(a.ctypes.data for a in self._keep)

    def buffers(self, m: int) -> dict:
        """A thread's workspace for tasks of up to ``m`` rows."""
        cap = _scan_edge_cap(m)
        return {"m": m, "A": np.zeros((m + _VNNI_ROWS, self.ops.rows.shape[1]), np.int8),
                "na": np.zeros(m + _VNNI_ROWS, np.int32), "G": np.empty(_SCAN_STRIP * (MAX_ROW + 32), np.float32),
                "row_f": np.empty(3 * m, np.float32), "row_list": np.empty(m, np.int32),
                "rad2c": np.empty(MAX_ROW, np.float32), "cacc": np.empty(MAX_ROW, np.float32),
                "edges": _edge_buffers(cap)}

    def run(self, idx: np.ndarray, lo: int, hi: int, n_own: int, r0: int, list_index: int, ws: dict):
        """One task: rows ``idx`` (int64, at most the workspace's ``m``) against the columns ``lo..hi``
        (list ``list_index``; the first ``n_own`` rows are the columns ``lo + r0 ...``). Returns ``(dens_r,
        dens_c, (r, c, g))``: the kernel sums of the rows and columns and the edges as :func:`scan_tile`'s,
        columns as feature indices; the edges are views of the workspace, valid until its next task."""
        idx = np.ascontiguousarray(idx, dtype=np.int64)
        m = len(idx)
        if m > ws["m"]:
            raise ValueError(f"U8Scan.run: {m} rows for a workspace of {ws['m']}")
        n = self.ops.n
        if not 0 <= lo <= hi <= n or (m and (idx.min() < 0 or idx.max() >= n)):
            raise IndexError(f"U8Scan.run: rows or columns {lo}..{hi} outside the {n} features")
        w, s, rad2, limit, lists, bits = self._arrays
        while True:
            cr, cc, cg = ws["edges"]
            dens_r, dens_c = np.zeros(m), np.zeros(hi - lo)
            got = _LIB.dqm_scan_task(*self._operands, idx.ctypes.data, m, lo, hi, n_own, r0, w, s, self.kernel, rad2,
                                     limit, lists, bits, self.words, list_index, ws["A"].ctypes.data,
                                     ws["na"].ctypes.data, ws["G"].ctypes.data, ws["row_f"].ctypes.data,
                                     ws["row_list"].ctypes.data, ws["rad2c"].ctypes.data, ws["cacc"].ctypes.data,
                                     dens_r.ctypes.data, dens_c.ctypes.data, cr.ctypes.data, cc.ctypes.data,
                                     cg.ctypes.data, len(cr))
            if got >= 0:
                return dens_r, dens_c, (cr[:got], cc[:got], cg[:got])
            _check_code(got, hi - lo)
            ws["edges"] = _edge_buffers(4 * len(cr))


def _scan_edge_cap(m: int) -> int:
    """First size of the edge buffers of a scan tile or task of ``m`` rows: a feature of a point seen in many
    images has many candidates, so room for 16 a row makes retries rare."""
    return max(1024, 16 * m)


def _edge_buffers(cap: int) -> Tuple[np.ndarray, np.ndarray, np.ndarray]:
    return np.empty(cap, np.int32), np.empty(cap, np.int32), np.empty(cap, np.float32)


def u8_kernel_runs(X: np.ndarray) -> bool:
    """Does the integer (VNNI) distance kernel run on these descriptors here (uint8, the CPU has AVX-512 VNNI)?"""
    return _LIB is not None and X.dtype == np.uint8 and simd_level() >= 3 and len(X) > 0


def pass_tile_u8(ops: U8Operands, a: int, a1: int, b: int, b1: int, w, s, kernel, rad2, dens_r, err_r,
                 dens_c=None, err_c=None, diag: Optional[bool] = None):
    """One tile of the all-pairs pass on :class:`U8Operands`, distances and kernel fused: as
    :func:`tile` (``diag``, by default ``a == b``: the self pairs skipped) or :func:`tile_sym`
    (rows and columns taken as different features). Returns the candidate pairs ``(r, c)`` (tile rows and
    columns)."""
    m, k = a1 - a, b1 - b
    A, lda, na, B, nb = ops._args(a, b)
    diag = a == b if diag is None else bool(diag)
    cap = max(1024, 4 * (m + k))
    scratch = np.empty(64 * k, np.float32)
    ca, ce = np.empty(k, np.float32), np.empty(k, np.float32)
    while True:
        cr, cc = np.empty(cap, np.int32), np.empty(cap, np.int32)
        dr, er = np.zeros(m), np.zeros(m)
        dc, ec = np.zeros(k), np.zeros(k)
        got = _LIB.dqm_pass_tile_u8(A, lda, na, m, B, nb, k, ops.nq, int(diag), scratch, w[b:b1], s[b:b1],
                                    w[a:a1], s[a:a1], KERNEL_CODES[kernel], rad2[a:a1], rad2[b:b1],
                                    dr, er, dc, ec, ca, ce, cr, cc, cap)
        if got >= 0:
            dens_r += dr
            err_r += er
            if not diag:
                dens_c += dc
                err_c += ec
            return _head(cr, got), _head(cc, got)
        _check_code(got, k)
        cap *= 4
