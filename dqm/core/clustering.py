"""QuickMatch (Tron et al., ICCV 2017): density-based clustering of all features at once.

Semantics follow the authors' MATLAB code (``shared/notes/quickmatch-reference.md``):

1. ``sigma_j``: distance from feature j to the nearest other feature of its image.
2. density ``D_j = sum_i K_i(||x_i - x_j||)`` over all features, self included.
3. parent of j: nearest feature ranking above j (see :mod:`dqm.core.tree`).
4. break/merge edges shortest first under ``rho * min(scale)`` and disjoint images.

Kernels (``kernel=``):

* ``"gaussian"`` (default): ``K_i(d) = exp(-d^2 / (2 (ratio_density sigma_i)^2))``.
* ``"quadratic"``: the finite kernel of the distributed paper, whose equation
  reads ``1 - d^2/sigma`` inside ``sigma``. We read sigma there as a length, so
  the kernel is dimensionless and scale-free: ``K_i(d) = 1 - d^2/sigma_i^2`` for
  ``d < sigma_i`` and 0 beyond (support radius ``sigma_i``; ``ratio_density``
  does not enter). Taken literally (``1 - d^2/sigma_i``) the kernel would change
  with the descriptors' units and go negative for SIFT-scale data.

Defined edge cases:

* no features: an empty result;
* one image: no match is possible (C2), every feature is its own cluster;
* an image with a single feature: it has no intra-image distance, so its sigma
  is the median sigma of all features of multi-feature images (the data's
  typical distinctiveness); if no image has two features, sigma is 0 for all and
  nothing merges;
* duplicate descriptors in one image: sigma is 0, such a feature never merges,
  and its kernel is the indicator of distance 0 (the kernel's limit);
* exact duplicates have exactly equal densities (ties ranked by index).

``parent`` reports the tree parent only where it can matter: the nearest
higher-ranked feature within ``rho * sigma_j`` (an edge longer than that can
never merge); features without one get ``-1`` and ``parent_distance = inf``.
"""
from __future__ import annotations

import dataclasses
import logging
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Dict, List, Optional, Tuple, Union

import numpy as np

from .. import validation as V
from ..progress import ProgressArg, resolve_progress
from ..wording import count
from . import approximate, inverted_lists, memory, native, pairs, tree
from .pairs import duplicate_groups
from .params import (
    DEFAULT_KERNEL,
    DEFAULT_PARENT,
    DEFAULT_RATIO_DENSITY,
    DEFAULT_RHO,
    KERNELS,
    PARENT_MODES,
    QuickMatchParams,
)

LOG = logging.getLogger("dqm.core")

# the parameter vocabulary lives in dqm.core.params; these names stay importable from here
__all__ = ["DEFAULT_NEIGHBORS", "DEFAULT_RATIO_DENSITY", "DEFAULT_RHO", "KERNELS", "PARENT_MODES", "QuickMatch",
           "QuickMatchParams", "QuickMatchResult", "quickmatch"]

#: neighbours per feature in the approximate mode (scripts/bench_quickmatch.py --approximate)
DEFAULT_NEIGHBORS = 32
#: the engines of :func:`quickmatch`
ENGINES = ("exact", "fast", "auto")
#: ``engine="auto"`` runs the fast engine from this many features on (scripts/bench_quickmatch.py --fast)
FAST_FROM = 50_000


@dataclass(frozen=True)
class QuickMatchResult:
    """Clusters and the per-feature quantities that produced them.

    Attributes are numpy arrays of length n (number of features):
    ``labels`` (cluster id, 0..n_clusters-1 numbered by each cluster's lowest
    feature index), ``sigma``, ``density``, ``parent`` (-1: none within reach),
    ``parent_distance`` and ``image_ids`` (as given).
    """

    labels: np.ndarray
    sigma: np.ndarray
    density: np.ndarray
    parent: np.ndarray
    parent_distance: np.ndarray
    image_ids: np.ndarray
    rho: float
    ratio_density: float
    kernel: str
    parent_mode: str
    stats: Dict[str, float] = field(default_factory=dict, compare=False)

    @property
    def params(self) -> QuickMatchParams:
        """The parameters this result was computed with: ``quickmatch(X, ids, params=result.params)``
        reproduces its labels."""
        return QuickMatchParams(rho=self.rho, kernel=self.kernel, parent=self.parent_mode,
                                ratio_density=self.ratio_density)

    @property
    def n_features(self) -> int:
        return int(len(self.labels))

    @property
    def n_clusters(self) -> int:
        return int(self.labels.max() + 1) if len(self.labels) else 0

    @property
    def n_images(self) -> int:
        return int(len(np.unique(self.image_ids)))

    def cluster_sizes(self) -> np.ndarray:
        """Number of features of every cluster, indexed by label."""
        return np.bincount(self.labels, minlength=self.n_clusters)

    def clusters(self, min_size: int = 1) -> List[np.ndarray]:
        """Feature indices of every cluster with at least ``min_size`` members."""
        order = np.argsort(self.labels, kind="stable")
        bounds = np.searchsorted(self.labels[order], np.arange(self.n_clusters + 1))
        out = [order[bounds[k]:bounds[k + 1]] for k in range(self.n_clusters)]
        return [c for c in out if len(c) >= min_size]

    def summary(self) -> str:
        """One paragraph: features, images, clusters, size histogram, time."""
        sizes = self.cluster_sizes()
        hist = np.bincount(sizes) if len(sizes) else np.zeros(1, int)
        parts = ", ".join(f"{s}:{c}" for s, c in enumerate(hist) if s > 0 and c > 0)
        multi = int((sizes > 1).sum())
        matched = int(sizes[sizes > 1].sum())
        t = self.stats.get("time_total")
        tt = f" in {t:.2f} s" if t is not None else ""
        mode = f", approximate with {self.stats['n_neighbors']:.0f} neighbours" if "n_neighbors" in self.stats else ""
        if "engine_fast" in self.stats:
            mode = f", fast engine: {self.stats['n_lists']:.0f} lists, about {self.stats['n_probe']:.0f} probed"
        return (
            f"QuickMatch ({self.kernel} kernel, rho={self.rho:g}{mode}) clustered {self.n_features} features "
            f"from {count(self.n_images, 'image')} into {count(self.n_clusters, 'cluster')}{tt}; "
            f"{multi} clusters span 2+ images and hold {matched} features "
            f"({100.0 * matched / max(1, self.n_features):.1f}%). Cluster sizes (size:count): {parts or 'none'}."
        )


def _empty_result(image_ids: np.ndarray, rho, ratio, kernel, parent_mode) -> QuickMatchResult:
    z = np.zeros(0)
    return QuickMatchResult(
        labels=np.zeros(0, np.int64), sigma=z, density=z, parent=np.zeros(0, np.int64),
        parent_distance=z, image_ids=image_ids, rho=rho, ratio_density=ratio, kernel=kernel,
        parent_mode=parent_mode, stats={"time_total": 0.0},
    )


def distinctiveness(aug: pairs.Augmented, image_index: np.ndarray, n_images: int,
                    n_threads: Optional[int] = None, groups: Optional[np.ndarray] = None) -> np.ndarray:
    """sigma of every feature, with the documented fallback for single-feature images."""
    sigma = pairs.nearest_same_image(aug, image_index, n_images, n_threads=n_threads, groups=groups)
    lonely = np.isnan(sigma)
    if lonely.any():
        sigma[lonely] = lonely_sigma(sigma[~lonely])
    return sigma


def lonely_sigma(finite: np.ndarray) -> float:
    """sigma of a feature alone in its image: the median of every finite sigma (0 if there is none)."""
    return float(np.median(finite)) if len(finite) else 0.0


def zero_sigma_counts(groups: np.ndarray, gsize: np.ndarray, zero: np.ndarray) -> np.ndarray:
    """Per feature, the zero-sigma features identical to it, itself included.

    A zero-sigma feature's kernel is the indicator of distance 0, so it adds 1
    to each of its duplicates' densities (callers subtract the self term).
    """
    return np.bincount(groups[zero], minlength=len(gsize))[groups]


def equalize_duplicates(dens: np.ndarray, groups: np.ndarray, gsize: np.ndarray) -> np.ndarray:
    """Identical vectors have identical densities: each takes its group's first member's value (in place)."""
    in_dup = gsize[groups] > 1
    if in_dup.any():
        dup_idx = np.flatnonzero(in_dup)
        first_of = np.full(len(gsize), len(dens), dtype=np.int64)
        np.minimum.at(first_of, groups[dup_idx], dup_idx)
        dens[dup_idx] = dens[first_of[groups[dup_idx]]]
    return dens


def kernel_weights(sigma: np.ndarray, kernel: str, ratio_density: float):
    """Per-contributor weight ``w`` (argument ``d^2 w``) and on/off flag (sigma > 0)."""
    active = (sigma > 0).astype(np.float64)
    safe = np.where(sigma > 0, sigma, 1.0)
    if kernel == "gaussian":
        w = 1.0 / (2.0 * (ratio_density * safe) ** 2)
    else:
        w = 1.0 / safe ** 2
    return np.where(sigma > 0, w, 0.0), active


def _sigma(aug: pairs.Augmented, sigma, image_index: np.ndarray, n_images: int, threads: int,
           groups: Optional[np.ndarray] = None) -> np.ndarray:
    """Computed distinctiveness, or the caller's after checking it."""
    n = aug.n
    if sigma is None:
        return distinctiveness(aug, image_index, n_images, n_threads=threads, groups=groups)
    sig = np.asarray(sigma, dtype=np.float64)
    if sig.shape != (n,) or not np.isfinite(sig).all() or (sig < 0).any():
        raise V.InputError(f"sigma must be {n} finite non-negative values, one per descriptor")
    return sig


def _timed_sigma(aug: pairs.Augmented, sigma, image_index: np.ndarray, n_images: int, threads: int,
                 stats: Dict[str, float]):
    """Duplicate groups and sigma (computed, or the caller's checked), timed into ``stats["time_sigma"]``;
    every engine starts with them."""
    t = time.perf_counter()
    groups = duplicate_groups(aug.exact)
    sig = _sigma(aug, sigma, image_index, n_images, threads, groups)
    stats["time_sigma"] = time.perf_counter() - t
    LOG.info("sigma (nearest other feature of the same image): %.2f s", stats["time_sigma"])
    return groups, sig


#: edges handled at a time where every edge would otherwise need temporaries (exact distances, rank tests)
EDGE_CHUNK = 1 << 22


def _edge_chunks(cr: np.ndarray, cc: np.ndarray):
    """The edges ``(child, candidate)`` :data:`EDGE_CHUNK` at a time, as views."""
    for s in range(0, len(cr), EDGE_CHUNK):
        yield cr[s:s + EDGE_CHUNK], cc[s:s + EDGE_CHUNK]


def _edges_within_radius(aug: pairs.Augmented, cr: np.ndarray, cc: np.ndarray, radius: np.ndarray,
                         image_index: Optional[np.ndarray]):
    """Candidate edges ``cr -> cc`` at their exact distances, those within the child's radius (and, when
    ``image_index`` is given, between two images): ``(cr, cc, d)``. Chunk by chunk, the kept edges moved to
    the front of ``cr`` and ``cc`` (overwritten: views of them are returned), so that the edges are held
    once beside their distances (at 1M features, hundreds of millions of edges)."""
    d = np.empty(len(cr))
    kept = 0
    for r, c in _edge_chunks(cr, cc):
        dc = pairs.exact_distances(aug.exact, r, c)
        keep = dc < radius[r]
        if image_index is not None:
            keep &= image_index[r] != image_index[c]
        m = int(keep.sum())
        cr[kept:kept + m], cc[kept:kept + m], d[kept:kept + m] = r[keep], c[keep], dc[keep]  # copies first
        kept += m
    return cr[:kept], cc[:kept], d[:kept]


def final_density_bounds(dens_o: np.ndarray, err: np.ndarray):
    """Bounds ``[lo, hi]`` of every final density ``fl(1 + d)``, d within ``err`` of ``dens_o``.

    The tree ranks features on the float64 value ``1 + d``, in which densities
    closer than ~1e-16 are equal and rank by index. Bounding that value, not d,
    makes the pair relation (:func:`dqm.core.native.rank_relation`) agree with
    the final ranking: disjoint bounds order the pair, equal point bounds
    (``lo == hi``: exact, or rounding to one value) rank it by index, and any
    other pair is settled with exact densities. Rounding to nearest is
    monotone, so ``lo <= fl(1 + d) <= hi``; a one-ulp widening covers the
    rounding of ``dens_o -+ err`` itself.
    """
    exact = err == 0
    lo = np.where(exact, dens_o, np.nextafter(dens_o - err, -np.inf))
    hi = np.where(exact, dens_o, np.nextafter(dens_o + err, np.inf))
    return 1.0 + lo, 1.0 + hi


def feature_progress(progress: ProgressArg, label: str, n: int):
    """A stage's progress counted in features: its ``(done, total)`` work items map to
    ``n * done / total`` of the ``n`` features."""
    bar = resolve_progress(progress, label, unit="features")
    if bar is None:
        return None
    return lambda done, total: bar(n if done >= total else int(n * done / max(1, total)), n)


def resolve_params(params: Optional[QuickMatchParams] = None, **given) -> QuickMatchParams:
    """The validated :class:`QuickMatchParams` of a call that takes them as ``params`` or one by one
    (``given``: name -> value, None where not given); both at once is an error. The numbers come back
    as Python floats."""
    named = {k: v for k, v in given.items() if v is not None}
    if params is not None:
        if not isinstance(params, QuickMatchParams):
            raise V.InputError(f"params must be a QuickMatchParams, got {type(params).__name__}")
        if named:
            raise V.InputError(f"give the QuickMatch parameters either as params= or one by one, not both "
                               f"(params= and {', '.join(f'{k}=' for k in named)})")
        p = params
    else:
        p = QuickMatchParams(**named)
    p = p.validated()
    return p.but(rho=float(p.rho), ratio_density=float(p.ratio_density))


def quickmatch(
    descriptors,
    image_ids,
    *,
    params: Optional[QuickMatchParams] = None,
    rho: Optional[float] = None,
    ratio_density: Optional[float] = None,
    kernel: Optional[str] = None,
    parent: Optional[str] = None,
    sigma: Optional[np.ndarray] = None,
    n_threads: Optional[int] = None,
    progress: ProgressArg = None,
    max_memory: Union[None, str, int, float] = None,
    approximate: bool = False,
    n_neighbors: int = DEFAULT_NEIGHBORS,
    engine: str = "exact",
    n_probe: Optional[int] = None,
    seed: int = 0,
) -> QuickMatchResult:
    """Cluster features of many images so each cluster is one physical point.

    Parameters
    ----------
    descriptors : (n, dim) float or integer array (uint8 SIFT is fine).
    image_ids : (n,) integer array, the image of every feature.
    params : the four QuickMatch parameters as one
        :class:`~dqm.core.params.QuickMatchParams` (default: its defaults), or
        give them one by one (below), not both.
    rho : merge ratio; an edge merges iff shorter than ``rho * min(scale)``
        (default :data:`~dqm.core.params.DEFAULT_RHO`).
    ratio_density : Gaussian bandwidth as a fraction of sigma (reference: 0.25).
    kernel : ``"gaussian"`` (default) or ``"quadratic"`` (finite support, see module doc).
    parent : ``"any"`` (default) or ``"other-image"`` (parent must come from another image).
    sigma : optional precomputed per-feature distinctiveness (>= 0), e.g. an
        agent's own in the distributed algorithm; computed when None.
    n_threads : worker threads for the all-pairs pass (default: CPU count).
    progress : True for a terminal progress bar, or a callable ``(done, total)``
        counting features.
    max_memory : memory budget, bytes or a size such as ``"8G"`` (default: 70%
        of the available memory). An exact run whose candidate edges would not
        fit uses the streaming parent pass (same labels, a second GEMM over all
        pairs, memory O(n) whatever rho is); an input that cannot fit even so
        is refused with :class:`dqm.core.memory.MemoryBudgetError` before any
        work.
    approximate : use the approximate mode (:mod:`dqm.core.approximate`, needs
        faiss-cpu): densities and parents from each feature's ``n_neighbors``
        nearest neighbours, for sets too large for the exact O(n^2) pass.
    n_neighbors : neighbours per feature in the approximate mode.
    engine : ``"exact"`` (default: every pair), ``"fast"`` (only the pairs within
        each feature's ``n_probe`` nearest inverted lists, :mod:`dqm.core.inverted_lists`:
        densities leave far terms out, so clusters can differ slightly from
        exact ones) or ``"auto"`` (exact below :data:`FAST_FROM` features, fast
        from there; what ``dqm match`` does by default).
    n_probe : lists each feature scans in the fast engine (default: a sixteenth of them, at least 32:
        :func:`dqm.core.inverted_lists.default_probes`).
    seed : seed of the fast engine's k-means sample.

    Returns
    -------
    QuickMatchResult. Every feature gets exactly one label (C1) and no cluster
    holds two features of one image (C2). Deterministic for a given input.
    """
    t0 = time.perf_counter()
    X = V.check_descriptors(descriptors, keep_integer=True)  # uint8 SIFT stays uint8 (the integer kernels)
    ids = V.check_image_ids(image_ids, len(X))
    p = resolve_params(params, rho=rho, ratio_density=ratio_density, kernel=kernel, parent=parent)
    rho, ratio_density, kernel, parent = p.rho, p.ratio_density, p.kernel, p.parent
    scale = V.magnitude_exponent(X)
    if scale:  # absurd magnitudes: the same clusters on X / 2^scale (exact), distances scaled back
        r = quickmatch(np.ldexp(X, -scale), ids, params=p,
                       sigma=None if sigma is None else np.ldexp(np.asarray(sigma, np.float64), -scale),
                       n_threads=n_threads, progress=progress, max_memory=max_memory, approximate=approximate,
                       n_neighbors=n_neighbors)
        r.stats["descriptor_scale_exponent"] = float(scale)
        return dataclasses.replace(r, sigma=np.ldexp(r.sigma, scale),
                                   parent_distance=np.ldexp(r.parent_distance, scale))
    n = len(X)
    if n == 0:
        return _empty_result(ids, rho, ratio_density, kernel, parent)
    _, image_index = np.unique(ids, return_inverse=True)
    image_index = image_index.ravel().astype(np.int64)
    n_images = int(image_index.max()) + 1
    if n_images == 1:
        warnings.warn("quickmatch: all features come from one image, so no match is possible "
                      "(every feature is its own cluster)", stacklevel=2)
    stats: Dict[str, float] = {}

    if not isinstance(approximate, (bool, np.bool_)):
        raise V.InputError(f"approximate must be True or False, got {approximate!r}")
    threads = pairs.default_threads() if n_threads is None else max(1, int(n_threads))
    budget = memory.resolve_budget(max_memory)
    held = memory.held_bytes(max_memory, X, descriptors)
    if engine not in ENGINES:
        raise V.InputError(f"engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if approximate and engine == "fast":
        raise V.InputError("approximate=True is the k-nearest-neighbour engine: give engine='fast' or "
                           "approximate=True, not both")
    fast = engine == "fast" or (engine == "auto" and n >= FAST_FROM)
    if fast and not approximate and n > 2 and n_images > 1:
        n_probe = (inverted_lists.default_probes(inverted_lists.n_lists(n)) if n_probe is None
                   else V.check_positive_int(n_probe, "n_probe"))
        return _quickmatch_fast(X, ids, image_index, n_images, rho, ratio_density, kernel, parent, sigma, n_probe,
                                int(seed), threads, budget, held, progress, t0)
    if approximate and n > 2:
        X = X.astype(np.float64, copy=False)  # as the approximate mode's measurements were made
        return _quickmatch_approximate(X, ids, image_index, n_images, rho, ratio_density, kernel, parent, sigma,
                                       n_neighbors, threads, budget, held, progress, t0)
    if X.dtype.kind in "iu":  # integer rows: the operands hold no float copy of the data (exact mode)
        aug = pairs.Augmented(X)
        base = memory.check_base(n, X.shape[1], threads, budget, itemsize=X.dtype.itemsize if aug.exact_d2 else None,
                                 held=held)
    else:
        base = memory.check_base(n, X.shape[1], threads, budget, held=held)
        aug = pairs.Augmented(X)
    native.warn_if_fallback(n)
    LOG.info("QuickMatch: %s of %s (%d-D %s), rho %g, %s kernel, %s, memory budget %.2f GiB", count(n, "feature"),
             count(n_images, "image"), X.shape[1], X.dtype, rho, kernel, count(threads, "thread"), budget / 2 ** 30)

    groups, sig = _timed_sigma(aug, sigma, image_index, n_images, threads, stats)

    t = time.perf_counter()
    cpu = time.process_time()
    w, active = kernel_weights(sig, kernel, ratio_density)
    radius = rho * sig
    max_edges = memory.max_dense_edges(n, base + held, budget)
    stats["memory_budget"] = float(budget)
    stats["memory_held"] = float(held)
    dens_o, err, cr, cc = pairs.kernel_pass(aug, w, active, kernel, radius, n_threads=threads,
                                            progress=feature_progress(progress, "quickmatch", n),
                                            max_edges=max_edges)
    streaming = cr is None
    stats["streaming"] = float(streaming)
    stats["time_pass"] = time.perf_counter() - t
    stats["cpu_pass"] = time.process_time() - cpu  # CPU seconds of all threads: how busy the cores were
    LOG.info("kernel pass (densities and candidate parents): %.2f s wall, %.2f CPU s%s", stats["time_pass"],
             stats["cpu_pass"], ", parents streamed (the edges exceed the memory budget)" if streaming else "")

    density, cr, cc, d = _decide(aug, sig, groups, w, active, kernel, dens_o, err, cr, cc, radius, image_index,
                                 parent == "other-image", threads, progress, stats)

    t = time.perf_counter()
    par, pdist = tree.select_parents(n, cr, cc, d, density)
    labels = tree.merge_clusters(par, pdist, sig, image_index, rho)
    stats["time_tree"] = time.perf_counter() - t
    stats["time_total"] = time.perf_counter() - t0
    LOG.info("tree and merges: %.2f s; %.2f s in all", stats["time_tree"], stats["time_total"])
    LOG.debug("QuickMatch statistics: %s", ", ".join(f"{k}={v:.4g}" for k, v in sorted(stats.items())))
    return QuickMatchResult(labels, sig, density, par, pdist, ids, rho, ratio_density, kernel, parent, stats)


def _decide(aug, sig, groups, w, active, kernel, dens_o, err, cr, cc, radius, image_index, other_image: bool,
            threads: int, progress: ProgressArg, stats: Dict[str, float]):
    """From the pass's density estimates (with error bounds) and candidate edges (None: streaming) to
    exact decisions: zero-sigma and duplicate terms, the streaming parent pass where the edges did not
    fit, exact distances of the candidates within each child's radius, and exact densities wherever
    an order on a candidate edge is not certain. Returns ``(density, cr, cc, d)``."""
    n = len(sig)
    streaming = cr is None
    t = time.perf_counter()
    # zero-sigma features contribute only to their exact duplicates (kernel limit)
    gsize = np.bincount(groups)
    zero = sig == 0
    zcount = zero_sigma_counts(groups, gsize, zero) if zero.any() else None
    if zcount is not None:
        dens_o = dens_o + zcount - zero

    def exact_others(idx):
        exact = pairs.exact_density_others(aug, idx, w, active, kernel, threads)
        return exact if zcount is None else exact + zcount[idx] - zero[idx]

    # duplicates first: exact and equal, so their order is certain (by index) in both passes
    # (dens_o and err are this call's own arrays: updated in place)
    dup = np.flatnonzero(gsize[groups] > 1)
    if len(dup):
        dens_o[dup] = exact_others(dup)
        err[dup] = 0.0
        dens_o = equalize_duplicates(dens_o, groups, gsize)
    lo, hi = final_density_bounds(dens_o, err)
    if streaming:
        tp = time.perf_counter()
        cr, cc = pairs.parent_pass(aug, lo, hi, radius, image_index if other_image else None, n_threads=threads,
                                   progress=feature_progress(progress, "quickmatch parents", n))
        stats["time_parent_pass"] = time.perf_counter() - tp
    else:
        stats["n_pass_edges"] = float(len(cr))
    # the streaming pass has left same-image pairs out already; the dense pass has not
    cr, cc, d = _edges_within_radius(aug, cr, cc, radius, image_index if other_image else None)
    # refine densities whose order on some candidate edge is not certain (the same rule in both passes,
    # so both refine the same features and end with the same density values)
    refine = np.zeros(n, dtype=bool)
    for r, c in _edge_chunks(cr, cc):
        uncertain = native.rank_relation(lo, hi, c, r) == 0
        refine[r[uncertain]] = True
        refine[c[uncertain]] = True
    refine[dup] = False
    idx = np.flatnonzero(refine)
    if len(idx):
        dens_o[idx] = exact_others(idx)
    density = 1.0 + equalize_duplicates(dens_o, groups, gsize)  # remove rounding between duplicates
    stats["n_candidate_edges"] = float(len(cr))
    stats["n_refined"] = float(len(idx))
    stats["time_refine"] = time.perf_counter() - t
    return density, cr, cc, d


def _quickmatch_approximate(X, ids, image_index, n_images, rho, ratio_density, kernel, parent, sigma,
                            n_neighbors, threads, budget, held, progress, t0) -> QuickMatchResult:
    """The approximate mode (:mod:`dqm.core.approximate`); arguments already checked."""
    n, dim = X.shape
    k = min(V.check_positive_int(n_neighbors, "n_neighbors"), n - 1)
    memory.check_approximate(n, dim, k, threads, budget, held)
    approximate.require_faiss()
    stats: Dict[str, float] = {"n_neighbors": float(k), "memory_budget": float(budget)}
    aug = pairs.Augmented(X)
    groups, sig = _timed_sigma(aug, sigma, image_index, n_images, threads, stats)

    t = time.perf_counter()
    # keep only what the graph needs: uint8 SIFT as bytes, else float32 (the GEMM operands go)
    compact = aug.exact
    data = compact if compact.dtype == np.uint8 else np.ascontiguousarray(aug.left[:, :dim])
    del aug
    nbr, d2 = approximate.knn_graph(data, k, n_threads=threads,
                                    progress=feature_progress(progress, "quickmatch (approximate)", n))
    del data
    stats["time_knn"] = time.perf_counter() - t

    t = time.perf_counter()
    w, active = kernel_weights(sig, kernel, ratio_density)
    dens_o = approximate.knn_density_others(nbr, d2, w, active, kernel)
    stats["time_density"] = time.perf_counter() - t
    cr, cc, d = approximate.graph_edges(nbr, d2, rho * sig, image_index if parent == "other-image" else None)
    del nbr, d2
    return _truncated_result(dens_o, cr, cc, d, sig, groups, ids, image_index, rho, ratio_density, kernel, parent,
                             stats, t0)


#: a search for the parents a truncated engine's candidates lack: ``(density, parent)`` -> more candidate edges
#: ``(child, cand, distance)`` for some children without a parent
ParentSearch = Callable[[np.ndarray, np.ndarray], Tuple[np.ndarray, np.ndarray, np.ndarray]]


def _truncated_result(dens_o, cr, cc, d, sig, groups, ids, image_index, rho, ratio_density, kernel, parent,
                      stats: Dict[str, float], t0: float, search: Optional[ParentSearch] = None) -> QuickMatchResult:
    """The result of an engine whose densities leave far terms out (approximate, fast): zero-sigma and
    duplicate terms as in the exact engine, then parents among the candidate edges ``cr -> cc`` at exact
    distances ``d`` (and, for the children still without one, among the edges ``search`` finds) and the
    exact break/merge."""
    t = time.perf_counter()
    n = len(sig)
    gsize = np.bincount(groups)
    zero = sig == 0
    if zero.any():
        dens_o = dens_o + zero_sigma_counts(groups, gsize, zero) - zero
    density = 1.0 + equalize_duplicates(dens_o, groups, gsize)
    par, pdist = tree.select_parents(n, cr, cc, d, density)
    if search is not None:
        t_search = time.perf_counter()
        sr, sc, sd = search(density, par)
        more, more_d = tree.select_parents(n, sr, sc, sd, density)
        found = (par < 0) & (more >= 0)
        par[found], pdist[found] = more[found], more_d[found]
        stats["n_parents_searched"] = float(found.sum())
        stats["time_parent_search"] = time.perf_counter() - t_search
    labels = tree.merge_clusters(par, pdist, sig, image_index, rho)
    stats["n_candidate_edges"] = float(len(cr))
    stats["time_tree"] = time.perf_counter() - t
    stats["time_total"] = time.perf_counter() - t0
    LOG.info("tree and merges: %.2f s; %.2f s in all", stats["time_tree"], stats["time_total"])
    LOG.debug("QuickMatch statistics: %s", ", ".join(f"{k}={v:.4g}" for k, v in sorted(stats.items())))
    return QuickMatchResult(labels, sig, density, par, pdist, ids, rho, ratio_density, kernel, parent, stats)


def _quickmatch_fast(X, ids, image_index, n_images, rho, ratio_density, kernel, parent, sigma, n_probe, seed,
                     threads, budget, held, progress, t0) -> QuickMatchResult:
    """The fast engine (:mod:`dqm.core.inverted_lists`); arguments already checked."""
    n, dim = X.shape
    aug = pairs.Augmented(X)
    need = memory.check_fast(n, dim, n_probe, inverted_lists.n_lists(n), threads, budget,
                             itemsize=X.dtype.itemsize if aug.exact_d2 else None, held=held,
                             max_candidates=inverted_lists.MAX_CANDIDATES, integer_kernel=aug.integer_kernel)
    stats: Dict[str, float] = {"engine_fast": 1.0, "memory_budget": float(budget), "memory_estimate": float(need)}
    # the lists' k-means does not need sigma: it runs beside sigma's pass (the same centroids)
    with inverted_lists.centroids_meanwhile(aug, inverted_lists.n_lists(n), seed, threads) as centroids:
        groups, sig = _timed_sigma(aug, sigma, image_index, n_images, threads, stats)
        t = time.perf_counter()
        lists = centroids()
        waited = time.perf_counter() - t
    t = time.perf_counter()
    w, active = kernel_weights(sig, kernel, ratio_density)
    radius = rho * sig
    other_image = image_index if parent == "other-image" else None
    found = inverted_lists.scan(
        aug, w, active, kernel, radius, n_probe=n_probe, seed=seed, n_threads=threads, image_index=other_image,
        progress=feature_progress(progress, "quickmatch (fast)", n), centroids=lists)
    found.stats["time_lists"] += waited  # the k-means time not hidden behind sigma's
    stats.update(found.stats)
    stats["time_pass"] = time.perf_counter() - t + waited
    LOG.info("list scan (%d lists, %d probed each; %.1f%% of all pairs): %.2f s", found.stats["n_lists"],
             found.stats["n_probe"], 100.0 * found.stats["pairs_computed"] / max(1.0, n * (n - 1.0)),
             stats["time_pass"])
    t = time.perf_counter()
    # the scan kept other images' pairs only
    cr, cc, d = _edges_within_radius(aug, found.child, found.cand, radius, None)
    stats["time_edges"] = time.perf_counter() - t

    def capped_roots(density: np.ndarray, par: np.ndarray):
        """The children whose kept candidates were cut at the cap and all rank below them: their parent
        among every member of the lists they scan."""
        rows = np.flatnonzero(found.capped & (par < 0))
        sr, sc = inverted_lists.nearest_above(aug, found.index, rows, density, radius, other_image, threads)
        return _edges_within_radius(aug, sr, sc, radius, None)

    return _truncated_result(found.density_others, cr, cc, d, sig, groups, ids, image_index, rho, ratio_density,
                             kernel, parent, stats, t0, search=capped_roots)


class QuickMatch:
    """scikit-learn style estimator around :func:`quickmatch`.

    The constructor's arguments are attributes (scikit-learn's convention, so
    :meth:`get_params` / :meth:`set_params` and cloning work); :attr:`params`
    gathers the four QuickMatch parameters as a
    :class:`~dqm.core.params.QuickMatchParams`, and ``params_`` (after
    :meth:`fit`) holds the validated ones the fit ran with.

    >>> qm = QuickMatch(rho=0.75).fit(X, image_ids)   # doctest: +SKIP
    >>> qm.labels_                                     # doctest: +SKIP
    """

    def __init__(self, rho: float = DEFAULT_RHO, ratio_density: float = DEFAULT_RATIO_DENSITY,
                 kernel: str = DEFAULT_KERNEL, parent: str = DEFAULT_PARENT, n_threads: Optional[int] = None,
                 max_memory: Union[None, str, int, float] = None, approximate: bool = False,
                 n_neighbors: int = DEFAULT_NEIGHBORS):
        self.rho = rho
        self.ratio_density = ratio_density
        self.kernel = kernel
        self.parent = parent
        self.n_threads = n_threads
        self.max_memory = max_memory
        self.approximate = approximate
        self.n_neighbors = n_neighbors

    @property
    def params(self) -> QuickMatchParams:
        """The four QuickMatch parameters as set now (not validated: :meth:`fit` does that)."""
        return QuickMatchParams(**{k: getattr(self, k) for k in QuickMatchParams.names()})

    def get_params(self, deep: bool = True) -> Dict[str, object]:
        return {"rho": self.rho, "ratio_density": self.ratio_density, "kernel": self.kernel,
                "parent": self.parent, "n_threads": self.n_threads, "max_memory": self.max_memory,
                "approximate": self.approximate, "n_neighbors": self.n_neighbors}

    def set_params(self, **params) -> "QuickMatch":
        for k, v in params.items():
            if k not in self.get_params():
                raise V.InputError(f"unknown parameter {k!r} for QuickMatch")
            setattr(self, k, v)
        return self

    def fit(self, descriptors, image_ids, progress: ProgressArg = None) -> "QuickMatch":
        r = quickmatch(descriptors, image_ids, params=self.params, progress=progress, n_threads=self.n_threads,
                       max_memory=self.max_memory, approximate=self.approximate, n_neighbors=self.n_neighbors)
        self.result_ = r
        self.params_ = r.params
        self.labels_ = r.labels
        self.sigma_ = r.sigma
        self.density_ = r.density
        self.parent_ = r.parent
        self.parent_distance_ = r.parent_distance
        self.n_clusters_ = r.n_clusters
        return self

    def fit_predict(self, descriptors, image_ids) -> np.ndarray:
        return self.fit(descriptors, image_ids).labels_
