#!/usr/bin/env python
"""Benchmark dqm.quickmatch: wall time, peak memory, and ratios measured in one run.

For each data set (SIFT-like synthetic at 6,254 / 25k / 100k features; real SIFT
of ../shared/data/oxford/graf when present) it measures, each in a fresh
process so peak memory is that of the measured call alone:

* dqm.quickmatch (default parameters): wall time, peak RSS, phase times;
* the exact k-NN floor: one exact 2-NN pass over the same data (every feature
  against all), by faiss' IndexFlatL2 when faiss-cpu is installed and by a
  blocked numpy GEMM otherwise/also; the floor is the faster of the two;
* at 6,254 features, a dense numpy QuickMatch (n x n float64 distance matrix,
  the approach of the published Python port) as the slow baseline.

Prints a markdown table with ratios (quickmatch / floor, dense / quickmatch).

``--memory`` (issue 11): on graf's real SIFT at rho 0.9 ... 2, the dense
candidate-edge pass against the streaming parent pass (wall time, peak RSS,
identical labels); the dense pass at rho 2 is only estimated (it would need
more memory than this machine has).

``--approximate`` (issue 11): the approximate mode (faiss IVF k-NN graph)
against exact on generated sets and graf / wall / graf+wall real SIFT: wall
times, co-membership precision / recall / F1 against exact, the kernel mass
the truncation drops, and why parents differ; then 1M generated features
(``--million``): wall time, peak RSS and the growth from 100k.

    python scripts/bench_quickmatch.py [--sizes 6254,25000,100000] [--repeat 3]
    python scripts/bench_quickmatch.py --memory --sizes '' --no-graf
    python scripts/bench_quickmatch.py --approximate --million --sizes '' --no-graf
    python scripts/bench_quickmatch.py --budgets --fast-million --sizes '' --no-graf
"""
import argparse
import atexit
import json
import multiprocessing as mp
import os
import queue
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


CACHE = Path(os.environ.get("TMPDIR", "/tmp")) / "dqm-bench-cache"
REAL = ("graf", "wall")


def load(name):
    """Descriptors and image ids: generated (a number of features, 2,000 an image, or ``NxIMAGES``), real SIFT
    (graf, wall), graf+wall, a FEATURES file or a COLMAP database."""
    from dqm import synthetic

    if "+" in name:
        parts = [load(p) for p in name.split("+")]
        offsets = np.cumsum([0] + [int(ids.max()) + 1 for _, ids in parts[:-1]])
        return np.vstack([D for D, _ in parts]), np.concatenate([ids + o for (_, ids), o in zip(parts, offsets)])
    if name.endswith(".db"):  # a COLMAP database
        from dqm.vision.colmap import import_database

        fs = import_database(name)
        return fs.descriptors, fs.image_ids
    if name.endswith(".npz"):  # a FEATURES file
        z = np.load(name)
        return z["descriptors"], z["image_ids"]
    if name in REAL:
        cache = CACHE / f"{name}.npz"
        if cache.exists():
            z = np.load(cache)
            return z["D"], z["ids"]
        from dqm.vision import datasets, features

        seq = datasets.load_homography_sequence(ROOT.parent / "shared" / "data" / "oxford" / name)
        D, ids, _ = features.extract_many(seq.image_paths)
        CACHE.mkdir(parents=True, exist_ok=True)
        np.savez(cache, D=D, ids=ids)
        return D, ids
    n, images = generated_set(name)
    ds = synthetic.sized(n, features_per_image=n // images if images else 2000)
    return ds.descriptors, ds.image_ids


def generated_set(name: str):
    """A generated set's name, ``N`` (2,000 features an image) or ``NxIMAGES``: ``(N, IMAGES or None)``;
    ValueError for anything else."""
    m = re.fullmatch(r"(\d+)(?:x(\d+))?", name)
    if m is None:
        raise ValueError(f"{name!r} is not a generated set (N or NxIMAGES)")
    return int(m.group(1)), None if m.group(2) is None else int(m.group(2))


def knn_numpy(X):
    """Exact 2-NN of every row against all rows: blocked float32 GEMM + argpartition."""
    X = X.astype(np.float32)
    nrm = (X * X).sum(1)
    out = np.empty((len(X), 2), np.int64)
    for s in range(0, len(X), 1024):
        G = nrm[s:s + 1024, None] + nrm[None, :] - 2.0 * (X[s:s + 1024] @ X.T)
        out[s:s + 1024] = np.argpartition(G, 1, axis=1)[:, :2]
    return out


def knn_faiss(X):
    import faiss

    X = np.ascontiguousarray(X, dtype=np.float32)
    index = faiss.IndexFlatL2(X.shape[1])
    index.add(X)
    return index.search(X, 2)[1]


def dense_quickmatch(X, ids, rho):
    """The dense approach (n x n float64 matrices), vectorised numpy."""
    from scipy.spatial.distance import cdist

    X = X.astype(np.float64)
    D = cdist(X, X)
    same = ids[:, None] == ids[None, :]
    S = np.where(same, D, np.inf)
    np.fill_diagonal(S, np.inf)
    sigma = S.min(1)
    del S
    dens = np.exp(-D ** 2 / (2 * (0.25 * sigma[:, None]) ** 2)).sum(0)
    rank = np.lexsort((np.arange(len(X)), -dens))
    pos = np.empty(len(X), int)
    pos[rank] = np.arange(len(X))
    A = np.where(pos[None, :] < pos[:, None], D, np.inf)
    parent = A.argmin(1)
    pd = A[np.arange(len(X)), parent]
    return parent, pd, sigma


def measure(task, q):
    """One measurement in this (fresh) process, put on ``q``; a failure is put there too, as ``{"error": ...}``,
    so that the parent never waits for a result that will not come."""
    try:
        _measure(task, q)
    except Exception as exc:  # noqa: BLE001 - the bench reports it; the parent must not hang
        q.put({"error": f"{type(exc).__name__}: {exc}"})


def _measure(task, q):
    name, what = task[:2]
    opts = task[2] if len(task) > 2 else {}
    X, ids = load(name)
    import dqm

    _ = dqm.quickmatch  # the engine's modules load here, not inside the timed call
    reset_peak()
    base = peak_kib()
    t = time.perf_counter()
    info = {}
    if what == "quickmatch":
        save = opts.pop("save", None)
        recall_sample = opts.pop("recall_sample", 0)
        if opts.pop("force_dense", False):
            from dqm.core import memory

            memory.max_dense_edges = lambda *a: 10 ** 15
        r = dqm.quickmatch(X, ids, **opts)
        info = {k: v for k, v in r.stats.items()}
        info["wall"] = time.perf_counter() - t  # before saving and the recall check below
        info["clusters"] = r.n_clusters
        if save:
            np.savez(save, labels=r.labels, parent=r.parent, density=r.density)
        if opts.get("approximate") and recall_sample:
            peak = peak_kib()
            info["graph_recall"] = graph_recall(X, int(r.stats["n_neighbors"]), recall_sample)
            info["peak_before_recall_mib"] = peak / 1024
    elif what == "knn_numpy":
        knn_numpy(X)
    elif what == "knn_faiss":
        try:
            knn_faiss(X)
        except ImportError:
            q.put(None)
            return
    elif what == "dense":
        dense_quickmatch(X, ids, dqm.DEFAULT_RHO)
    wall = time.perf_counter() - t
    peak = peak_kib()
    q.put({"wall": wall, "peak_rss_mib": peak / 1024, "base_rss_mib": base / 1024, "n": len(X),
           "images": len(np.unique(ids)), **info})


def peak_kib():
    """Peak resident memory of this process in KiB (:func:`dqm.core.memory.peak_bytes`; ``reset_peak`` lowers it
    to the present)."""
    from dqm.core import memory

    return memory.peak_bytes() / 1024


def reset_peak():
    """Start the peak over from the present resident memory, so that the peak is the measured call's and not the
    data generation's before it."""
    from dqm.core import memory

    memory.restart_peak()


def run(task, repeat=1, target=None, errors=False):
    """``target(task, queue)`` (default :func:`measure`) in a fresh process, ``repeat`` times; the fastest result.
    A failed measurement ends the bench with its message, or is returned (``{"error": ...}``) with ``errors``."""
    ctx = mp.get_context("spawn")
    best = None
    for _ in range(repeat):
        q = ctx.Queue()
        p = ctx.Process(target=target or measure, args=(task, q))
        p.start()
        while True:
            try:
                res = q.get(timeout=1.0)
                break
            except queue.Empty:
                if not p.is_alive():  # killed (out of memory, a signal) before it could answer
                    res = {"error": f"the measuring process ended with exit code {p.exitcode}"}
                    break
        p.join()
        if res is None:
            return None
        if "error" in res:
            if errors:
                return res
            raise SystemExit(f"bench_quickmatch: {task[0]} {task[1]}: {res['error']}")
        if best is None or res["wall"] < best["wall"]:
            best = res
    return best


def graph_recall(X, k, sample):
    """recall@k of the approximate mode's k-NN graph against exact k-NN of ``sample`` random features."""
    from dqm.core import approximate, pairs

    nbr, _ = approximate.knn_graph(X, k, n_threads=pairs.default_threads())
    rng = np.random.default_rng(12345)
    q = np.sort(rng.choice(len(X), size=sample, replace=False))
    Xf = X.astype(np.float32)
    nrm = (Xf * Xf).sum(1)
    hits = 0
    for s in range(0, sample, 256):
        rows = q[s:s + 256]
        G = nrm[rows, None] + nrm[None, :] - 2.0 * (Xf[rows] @ Xf.T)
        G[np.arange(len(rows)), rows] = np.inf
        true = np.argpartition(G, k, axis=1)[:, :k]
        hits += sum(len(set(t.tolist()) & set(g.tolist())) for t, g in zip(true, nbr[rows]))
    return hits / (sample * k)


_SCRATCH: list = []


def scratch(tag):
    """A scratch file for the results a section compares, in a folder of this run removed when it ends."""
    if not _SCRATCH:
        _SCRATCH.append(tempfile.mkdtemp(prefix="dqm-bench-"))
        atexit.register(shutil.rmtree, _SCRATCH[0], True)
    return str(Path(_SCRATCH[0]) / f"{tag}.npz")


def memory_section():
    """Dense candidate edges against the streaming parent pass on graf's real SIFT."""
    from dqm.core import memory

    print("\n### Memory against rho (graf, 21,691 real SIFT)\n")
    print("| rho | dense s | dense peak RSS MiB | dense edges | auto s | auto peak RSS MiB | auto pass | "
          "labels identical |")
    print("|---|---|---|---|---|---|---|---|")
    for rho in (0.9, 1.2, 1.5, 2.0):
        auto = run(("graf", "quickmatch", {"rho": rho, "save": scratch("auto")}))
        a = np.load(scratch("auto"))["labels"]
        if rho < 2.0:
            dense = run(("graf", "quickmatch", {"rho": rho, "force_dense": True, "save": scratch("dense")}))
            same = bool(np.array_equal(np.load(scratch("dense"))["labels"], a))
            d = f"{dense['wall']:.2f} | {dense['peak_rss_mib']:.0f} | {int(dense['n_pass_edges']):,}"
        else:  # 387M edges (~18 GiB at 48 bytes each): more than this machine can give it
            d = f"not run | > {memory.format_bytes(0.7 * memory.available_bytes())} (the budget) | —"
            same = "—"
        mode = "streaming" if auto["streaming"] else "dense"
        print(f"| {rho} | {d} | {auto['wall']:.2f} | {auto['peak_rss_mib']:.0f} | {mode} | {same} |", flush=True)


def approximate_section(names, million):
    from dqm.evaluation import comembership_scores

    print("\n### Approximate mode against exact\n")
    print("| data | n | exact s | approx s | exact / approx | precision | recall | F1 | dropped kernel mass "
          "max (p99) | parents differ | of which: no parent in graph / order changed |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    times = {}
    for name in names:
        ex = run((name, "quickmatch", {"save": scratch("exact")}))
        ap = run((name, "quickmatch", {"approximate": True, "save": scratch("approx")}))
        e, a = np.load(scratch("exact")), np.load(scratch("approx"))
        sc = comembership_scores(a["labels"], e["labels"])
        missing = e["density"] - a["density"]
        differ = a["parent"] != e["parent"]
        no_parent = differ & (a["parent"] < 0) & (e["parent"] >= 0)
        flipped = differ & ~no_parent
        times[name] = (ex["wall"], ap["wall"])
        print(f"| {name} | {ex['n']:,} | {ex['wall']:.2f} | {ap['wall']:.2f} | {ex['wall'] / ap['wall']:.2f} | "
              f"{sc.precision:.4f} | {sc.recall:.4f} | {sc.f1:.4f} | {missing.max():.2e} "
              f"({np.quantile(missing, 0.99):.2e}) | {differ.mean():.2%} | {no_parent.mean():.2%} / "
              f"{flipped.mean():.2%} |", flush=True)
    if million:
        big = run(("1000000", "quickmatch", {"approximate": True, "recall_sample": 2000}))
        print(f"\n1M generated features, approximate: {big['wall']:.0f} s wall ({big['wall'] / 60:.1f} min), "
              f"peak RSS {big['peak_before_recall_mib'] / 1024:.2f} GiB ({big['base_rss_mib'] / 1024:.2f} GiB "
              f"held before the call: the generated data); phases: sigma {big['time_sigma']:.0f} s, k-NN "
              f"{big['time_knn']:.0f} s, density {big['time_density']:.0f} s, tree {big['time_tree']:.0f} s; "
              f"k-NN graph recall@{int(big['n_neighbors'])} {big['graph_recall']:.3f} (2,000 random features "
              "against exact)")
        if "100000" in times:
            ex100, ap100 = times["100000"]
            print(f"growth 100k -> 1M (10x features): approximate time x{big['wall'] / ap100:.1f}; "
                  f"exact would be x100 (O(n^2)): {ex100 * 100 / 60:.0f} min extrapolated from the exact "
                  f"100k run, {ex100 * 100 / big['wall']:.1f}x the approximate time")


def fast_section(names):
    """The fast engine against exact: times, pairs computed, co-membership against exact."""
    from dqm.evaluation import comembership_scores

    print("\n### Fast engine against exact\n")
    print("| data | n | images | exact s | fast s | fast / exact | pairs computed (of n^2) | lists (probed) | "
          "fast phases s: sigma / lists / scan / edges+tree | parents searched (s) | precision | recall | F1 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    rows = []
    for name in names:
        # the fast engine first: where it refuses (its memory budget), that is said before the exact engine's
        # hour at 2M, not after it (each engine runs in a fresh process, so the order changes no time)
        fa = run((name, "quickmatch", {"engine": "fast", "save": scratch("fast")}))
        ex = run((name, "quickmatch", {"engine": "exact", "save": scratch("exact")}))
        sc = comembership_scores(np.load(scratch("fast"))["labels"], np.load(scratch("exact"))["labels"])
        scan = fa["time_pass"] - fa["time_lists"]
        print(f"| {Path(name).stem} | {ex['n']:,} | {ex['images']:,} | {ex['wall']:.2f} | {fa['wall']:.2f} | "
              f"{fa['wall'] / ex['wall']:.3f} | "
              f"{fa['pairs_computed'] / ex['n'] ** 2:.3f} | {fa['n_lists']:.0f} ({fa['n_probe']:.0f}) | "
              f"{fa['time_sigma']:.2f} / {fa['time_lists']:.2f} / {scan:.2f} / "
              f"{fa['time_edges'] + fa['time_tree']:.2f} | {fa.get('n_parents_searched', 0):,.0f} "
              f"({fa.get('time_parent_search', 0.0):.2f}) | {sc.precision:.4f} | {sc.recall:.4f} | {sc.f1:.4f} |",
              flush=True)
        rows.append({"data": name, "exact": ex, "fast": fa, "precision": sc.precision, "recall": sc.recall,
                     "f1": sc.f1})
    return rows


def fast_million():
    """The fast engine (its defaults) on 1M generated features, in a fresh process: wall time, peak RSS, phases."""
    big = run(("1000000", "quickmatch", {"engine": "fast"}))
    scan = big["time_pass"] - big["time_lists"]
    print(f"\n1M generated features, fast engine: {big['wall']:.0f} s wall ({big['wall'] / 60:.1f} min), peak RSS "
          f"{big['peak_rss_mib'] / 1024:.2f} GiB ({big['base_rss_mib'] / 1024:.2f} GiB held before the call: the "
          f"generated data); phases: sigma {big['time_sigma']:.0f} s, lists {big['time_lists']:.0f} s, scan "
          f"{scan:.0f} s ({big['pairs_computed'] / big['n'] ** 2:.4f} of n^2 pairs, {big['n_lists']:.0f} lists), "
          f"edges and tree {big['time_edges'] + big['time_tree']:.0f} s", flush=True)


def exact_million():
    """The exact engine (its defaults: the default memory budget) on 1M generated features, in a fresh process:
    wall time, peak RSS, phases (issue 37: <= 15 min and under 8 GiB on 2 cores)."""
    big = run(("1000000", "quickmatch", {"engine": "exact"}))
    print(f"\n1M generated features, exact engine: {big['wall']:.0f} s wall ({big['wall'] / 60:.1f} min), peak RSS "
          f"{big['peak_rss_mib'] / 1024:.2f} GiB ({big['base_rss_mib'] / 1024:.2f} GiB held before the call: the "
          f"generated data); phases: sigma {big['time_sigma']:.0f} s, pass {big['time_pass']:.0f} s"
          f"{' (parents streamed)' if big.get('streaming') else ''}, refine {big.get('time_refine', 0.0):.0f} s, "
          f"tree {big['time_tree']:.0f} s", flush=True)


#: (generated features, engine, --max-memory) of --budgets: the exact engine streams to fit, the fast one fits or
#: refuses; the exact engine at 1M (about an hour on 2 AVX2 cores) is not run
BUDGET_ROWS = (("100000", "exact", "400M"), ("300000", "exact", "1G"), ("100000", "fast", "800M"),
               ("300000", "fast", "2G"), ("1000000", "fast", "6G"))


def budgets_section(rows=BUDGET_ROWS):
    """Issue 37: ``max_memory`` against the measured peak resident memory of the whole process (VmHWM, fresh
    process; its peak restarted after the data are generated, so what the process held before the call counts
    and the generator's temporaries do not)."""
    from dqm.core import memory
    from dqm.validation import InputError

    # every row checked before the first runs (a generated set as --fast names them: N or NxIMAGES)
    for row in rows:
        try:
            if len(row) != 3 or row[1] not in ("exact", "fast"):
                raise InputError("give N[xIMAGES]:exact|fast:SIZE")
            generated_set(row[0])
            memory.parse_size(row[2])
        except ValueError as e:  # InputError is one
            sys.exit(f"bench_quickmatch: --budgets {':'.join(row)}: {e}")
    print("\n### A memory budget against the measured peak\n")
    print("| generated n | engine | budget | peak RSS (whole process) | held before the call | peak / budget | "
          "parents | wall s |")
    print("|---|---|---|---|---|---|---|---|")
    for n, engine, budget in rows:
        r = run((n, "quickmatch", {"engine": engine, "max_memory": budget}), errors=True)
        b = memory.parse_size(budget)
        count, images = generated_set(n)
        label = f"{count:,}" + (f" ({images:,} images)" if images else "")
        if "error" in r:  # a refusal before any work is an answer too
            print(f"| {label} | {engine} | {memory.format_bytes(b)} | {r['error']} | | | | |", flush=True)
            continue
        how = "streamed" if r.get("streaming") else "kept" if engine == "exact" else "32 nearest kept"
        print(f"| {label} | {engine} | {memory.format_bytes(b)} | {r['peak_rss_mib'] / 1024:.2f} GiB | "
              f"{r['base_rss_mib'] / 1024:.2f} GiB | {r['peak_rss_mib'] * 2 ** 20 / b:.2f} | {how} | {r['wall']:.1f} |",
              flush=True)


def gemm_schedule(task, q):
    """The pass's own GEMMs (every unordered block pair, the same threads), nothing else: the
    float32 GEMM rate this machine's BLAS gives the pass (``task``: the data's name)."""
    X, _ = load(task[0])
    from dqm.core import pairs

    aug = pairs.Augmented(X)
    n, starts = aug.n, list(range(0, aug.n, pairs.BLOCK))
    tasks = [(a, b) for i, a in enumerate(starts) for b in starts[i:]]

    def gemm(tile):
        a, b = tile
        aug.left[a:a + pairs.BLOCK] @ aug.right[b:b + pairs.BLOCK].T

    t = time.perf_counter()
    with pairs.tile_pool() as pool:
        for _ in pool(gemm, tasks):
            pass
    wall = time.perf_counter() - t
    flops = sum(2.0 * min(pairs.BLOCK, n - a) * min(pairs.BLOCK, n - b) * aug.left.shape[1] for a, b in tasks)
    q.put({"wall": wall, "flops": flops, "n": n})


#: COLMAP SIFT settings of the --real rows: its defaults, and denser features (a set of >= 100k
#: features from ten ~1000-pixel photos: twice the keypoints, half the peak threshold)
SIFT_ROWS = {"defaults": {}, "dense": {"max_num_features": 16384, "peak_threshold": 0.02 / 6}}


def colmap_database(images, workdir, row):
    """pycolmap's SIFT of ``images`` into a new database (COLMAP's defaults, changed by SIFT_ROWS[row])."""
    import pycolmap

    db = Path(workdir) / f"{Path(images).name}-{row}.db"
    if not db.exists():
        opts = pycolmap.FeatureExtractionOptions()
        for key, value in SIFT_ROWS[row].items():
            setattr(opts.sift, key, value)
        pycolmap.extract_features(str(db), str(images), extraction_options=opts)
    return db


def timed(cmd):
    t = time.perf_counter()
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t


def photo_folder(folders, work):
    """One folder of photos: the given one, or several folders' photos linked into one (names prefixed by
    their folder's)."""
    if len(folders) == 1:
        return Path(folders[0])
    joined = Path(work) / "photos"
    joined.mkdir()
    for folder in map(Path, folders):
        for p in sorted(folder.glob("*.jpg")) + sorted(folder.glob("*.png")):
            tag = folder.parent.name if folder.name == "images" else folder.name
            (joined / f"{tag}-{p.name}").symlink_to(p.resolve())
    return joined


def alternated_matching(db, work, repeat):
    """Medians of ``repeat`` runs each of COLMAP's exhaustive matcher and ``dqm match --into-database`` on fresh
    copies (under ``work``) of the features' database ``db``, each side going first every other time (on some
    VMs the run right after the other's is the slower). Returns (COLMAP s, dqm s)."""
    import shutil

    import pycolmap

    Path(work).mkdir(parents=True, exist_ok=True)
    times = {"colmap": [], "dqm": []}
    for k in range(repeat):
        for side in (("colmap", "dqm") if k % 2 == 0 else ("dqm", "colmap")):
            copy = Path(work) / f"{side}-{k}.db"
            shutil.copy(db, copy)
            if side == "dqm":
                times[side].append(timed([sys.executable, "-m", "dqm", "match", str(copy), "--into-database",
                                          "--quiet"]))
                continue
            t = time.perf_counter()
            pycolmap.match_exhaustive(str(copy))
            times[side].append(time.perf_counter() - t)
    return float(np.median(times["colmap"])), float(np.median(times["dqm"]))


def real_section(folders, rows, brute_images, rates=True, repeat=4):
    """dqm's matching into COLMAP's database (its default engine; medians of ``repeat`` runs alternated with
    COLMAP's matcher on the same COLMAP features, each going first every other time; then once --exact) and
    the CLUSTERS route (dqm match, then dqm export colmap), F1 of the default against exact, and (``rates``)
    the exact pass's rate against the GEMM's."""
    import shutil

    import pycolmap

    from dqm.evaluation import comembership_scores

    work = Path(tempfile.mkdtemp(prefix="dqm-bench-real-"))
    images = photo_folder(folders, work)
    n_photos = sum(p.suffix.lower() in (".jpg", ".png") for p in images.iterdir())
    print(f"\n### Real photo SIFT: {' + '.join(map(str, folders))} ({n_photos} photos; COLMAP's "
          f"features, pycolmap {pycolmap.__version__})\n")
    print("| COLMAP SIFT | n | COLMAP exhaustive s | dqm match --into-database s | dqm / COLMAP | "
          "dqm match s (engine) | dqm export s | match + export / COLMAP | dqm match --exact --into-database s | "
          "exact / COLMAP | F1 default vs exact | pass GFLOP/s | GEMM GFLOP/s (same tiles) | pass / GEMM |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    dqm_cli = [sys.executable, "-m", "dqm"]
    for mf in rows:
        db = colmap_database(images, work, mf)
        t_colmap, t_into = alternated_matching(db, work / mf, repeat)
        default, exact, exported = work / f"c-{mf}.npz", work / f"x-{mf}.npz", work / f"e-{mf}.db"
        t_match = timed(dqm_cli + ["match", str(db), "--image-dir", str(images), "--out", str(default), "--quiet"])
        t_exp = timed(dqm_cli + ["export", "colmap", str(default), "--database", str(exported)])
        into = work / f"into-{mf}-exact.db"
        shutil.copy(db, into)
        t_exact = timed(dqm_cli + ["match", str(into), "--into-database", "--out", str(exact), "--quiet", "--exact"])
        d, x = np.load(default, allow_pickle=False), np.load(exact, allow_pickle=False)
        engine = json.loads(str(d["params"]))["engine"] if "params" in d.files else "?"
        f1 = comembership_scores(d["labels"], x["labels"]).f1
        n = len(x["labels"])
        head = (f"| {mf} | {n:,} | {t_colmap:.2f} | {t_into:.2f} | **{t_into / t_colmap:.2f}** | "
                f"{t_match:.2f} ({engine}) | {t_exp:.2f} | {(t_match + t_exp) / t_colmap:.2f} | {t_exact:.2f} | "
                f"{t_exact / t_colmap:.2f} | {f1:.4f} |")
        if not rates:  # the exact pass again, in-process, and the GEMM schedule: two more exact runs' time
            print(head + " — | — | — |", flush=True)
            continue
        name = str(db)
        qm = run((name, "quickmatch", {"save": scratch("real")}))
        same = bool(np.array_equal(np.load(scratch("real"))["labels"], x["labels"]))
        gm = run((name,), target=gemm_schedule)
        rate_pass = gm["flops"] / qm["time_pass"] / 1e9  # the same tiles' flops, in the pass's own time
        rate_gemm = gm["flops"] / gm["wall"] / 1e9
        print(head + f" {rate_pass:.0f} | {rate_gemm:.0f} | {rate_pass / rate_gemm:.2f} |", flush=True)
        print(f"  phases of exact quickmatch (s): sigma {qm['time_sigma']:.2f}, pass {qm['time_pass']:.2f}, refine "
              f"{qm['time_refine']:.2f} ({int(qm['n_refined'])} refined), tree {qm['time_tree']:.2f}; "
              f"wall {qm['wall']:.2f}, {qm['cpu_pass'] / qm['time_pass']:.2f} of {os.cpu_count()} cores busy in "
              f"the pass; dqm match --exact's labels identical to quickmatch's: {same}", flush=True)
    if brute_images:
        sub = work / "subset"
        sub.mkdir()
        for p in sorted(Path(images).iterdir())[:brute_images]:
            (sub / p.name).symlink_to(p.resolve())
        db = colmap_database(sub, work, "defaults")
        bf = work / "bf.db"
        shutil.copy(db, bf)
        opts = pycolmap.FeatureMatchingOptions()
        opts.sift.cpu_brute_force_matcher = True
        t = time.perf_counter()
        pycolmap.match_exhaustive(str(bf), matching_options=opts)
        t_bf = time.perf_counter() - t
        feats, clusters = work / "f-sub.npz", work / "c-sub.npz"
        timed(dqm_cli + ["import", "colmap", str(db), "--out", str(feats)])
        t_match = timed(dqm_cli + ["match", str(feats), "--out", str(clusters), "--quiet", "--no-guided"])
        n = len(np.load(feats)["descriptors"])
        print(f"\nExact against exact, {brute_images} images ({n:,} features): COLMAP's brute-force matcher "
              f"(cpu_brute_force_matcher, with its verification) {t_bf:.2f} s, dqm match {t_match:.2f} s: "
              f"dqm / COLMAP {t_match / t_bf:.2f}")
    shutil.rmtree(work, ignore_errors=True)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", default="6254,25000,100000")
    ap.add_argument("--repeat", type=int, default=3, help="runs per small case (best is kept); 1 for >= 50k")
    ap.add_argument("--no-graf", action="store_true")
    ap.add_argument("--json", help="also write the raw numbers here")
    ap.add_argument("--memory", action="store_true", help="dense edges against the streaming pass on graf")
    ap.add_argument("--approximate", action="store_true", help="approximate mode against exact")
    ap.add_argument("--approx-sets", default="25000,100000,graf,wall,graf+wall",
                    help="data sets of --approximate (numbers are generated sizes)")
    ap.add_argument("--fast", default=None, metavar="SETS",
                    help="the fast engine against exact on these sets (comma-separated: generated sizes, graf, wall, "
                         "graf+wall, FEATURES .npz files or COLMAP databases)")
    ap.add_argument("--fast-million", action="store_true",
                    help="the fast engine on 1M generated features (wall time, peak RSS; exact takes an hour here)")
    ap.add_argument("--exact-million", action="store_true",
                    help="the exact engine on 1M generated features (wall time, peak RSS; about an hour on 2 AVX2 "
                         "cores)")
    ap.add_argument("--million", action="store_true", help="with --approximate: also 1M generated features")
    ap.add_argument("--budgets", nargs="?", const=",".join(":".join(r) for r in BUDGET_ROWS), default=None,
                    metavar="N:ENGINE:BUDGET,...",
                    help="--max-memory against the measured peak RSS (default: 100k, 300k and 1M generated features)")
    ap.add_argument("--real", nargs="?", const=str(ROOT.parent / "shared" / "data" / "sacre_coeur"), default=None,
                    metavar="IMAGES", help="real photos (default sacre_coeur): dqm match --into-database (and dqm "
                    "match + export) against COLMAP's exhaustive matcher on COLMAP's features, and the pass against "
                    "the GEMM rate")
    ap.add_argument("--real-repeat", type=int, default=4,
                    help="with --real: runs of COLMAP's matcher and dqm match --into-database, each first every "
                         "other time (a run after the other's is slower on some VMs); medians")
    ap.add_argument("--real-sift", default="defaults,dense",
                    help="COLMAP SIFT settings, one row each: " + "; ".join(f"{k}: {v or 'COLMAP defaults'}"
                                                                             for k, v in SIFT_ROWS.items()))
    ap.add_argument("--large", action="store_true",
                    help="with --real: also the 20 photos of sacre_coeur and strecha/entry-P10 with the dense SIFT "
                         "setting (a set above 250k features)")
    ap.add_argument("--brute-images", type=int, default=2,
                    help="with --real: COLMAP's brute-force matcher against dqm on this many images (0: skip)")
    args = ap.parse_args(argv)
    if args.memory:
        memory_section()
    if args.fast:
        fast_section([x for x in args.fast.split(",") if x])
    if args.fast_million:
        fast_million()
    if args.exact_million:
        exact_million()
    if args.budgets:
        budgets_section([tuple(row.split(":")) for row in args.budgets.split(",") if row])
    if args.approximate:
        approximate_section([x for x in args.approx_sets.split(",") if x], args.million)
    names = [x for x in args.sizes.split(",") if x]
    if not args.no_graf and (ROOT.parent / "shared" / "data" / "oxford" / "graf").exists():
        names.append("graf")
    rows, raw = [], {}
    for name in names:
        small = name == "graf" or int(name) < 50000
        rep = args.repeat if small else 1
        qm = run((name, "quickmatch"), rep)
        kn = run((name, "knn_numpy"), rep)
        kf = run((name, "knn_faiss"), rep)
        floor = min(x["wall"] for x in (kn, kf) if x)
        dense = run((name, "dense"), rep) if name in ("6254", "graf") else None
        raw[name] = {"quickmatch": qm, "knn_numpy": kn, "knn_faiss": kf, "dense": dense}
        rows.append((name, qm, kn, kf, floor, dense))
        print(f"{name}: quickmatch {qm['wall']:.2f}s, floor {floor:.2f}s", file=sys.stderr, flush=True)
    if not rows:
        if args.real:
            real_sections(args)
        return
    print("| data | n | quickmatch s | peak RSS MiB (base) | k-NN numpy s | k-NN faiss s | qm / floor | dense s | "
          "dense / qm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name, qm, kn, kf, floor, dense in rows:
        label = "graf (real SIFT)" if name == "graf" else "synthetic"
        print(f"| {label} | {qm['n']} | {qm['wall']:.3f} | {qm['peak_rss_mib']:.0f} ({qm['base_rss_mib']:.0f}) | "
              f"{kn['wall']:.3f} | {kf['wall'] if kf else float('nan'):.3f} | {qm['wall'] / floor:.2f} | "
              f"{dense['wall'] if dense else float('nan'):.2f} | "
              f"{(dense['wall'] / qm['wall']) if dense else float('nan'):.1f} |")
    print()
    print("phases (s): " + "; ".join(
        f"{name}: sigma {qm['time_sigma']:.2f}, pass {qm['time_pass']:.2f}, refine {qm['time_refine']:.2f} "
        f"({int(qm['n_refined'])} refined), tree {qm['time_tree']:.2f}" for name, qm, *_ in rows))
    if "6254" in names:  # issue 23: rho above 1 (more candidate edges) at the paper's size
        hi = run(("6254", "quickmatch", {"rho": 1.1}), args.repeat)
        print(f"\nrho 1.1 at {hi['n']:,} generated features: {hi['wall']:.3f} s (best of {args.repeat}; target "
              f"<= 0.2 s), {'streaming' if hi['streaming'] else 'dense'} pass, {int(hi['n_refined'])} refined")
    if args.json:
        Path(args.json).write_text(json.dumps(raw, indent=1))
    if args.real:  # last: its arrays would raise the peak RSS the fresh processes above inherit
        real_sections(args)


def real_sections(args):
    real_section([Path(args.real)], [x for x in args.real_sift.split(",") if x], args.brute_images,
                 repeat=args.real_repeat)
    if args.large:
        data = ROOT.parent / "shared" / "data"
        real_section([data / "sacre_coeur", data / "strecha" / "entry-P10" / "images"], ["dense"], 0, rates=False,
                     repeat=args.real_repeat)


if __name__ == "__main__":
    main()
