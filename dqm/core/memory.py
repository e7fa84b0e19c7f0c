"""Memory budget of the centralized engine: the budget, what a run needs, and the plan.

The all-pairs pass (:func:`dqm.core.pairs.kernel_pass`) keeps every candidate
tree edge within ``rho * sigma`` of its child, which is fast while there are
few but grows with rho (on dense data almost every pair is a candidate at rho
2). The streaming parent pass (:func:`dqm.core.pairs.parent_pass`) needs memory
O(n) whatever rho is, at the cost of a second GEMM over all pairs. The engine
collects edges up to :func:`max_dense_edges` (the budget, or the point where
streaming is faster) and switches to the streaming pass beyond it; the
densities of the first pass are kept either way, so the switch wastes nothing
but the edges collected so far. Before any work, :func:`check_base` refuses in
one line an input whose O(n) arrays alone exceed the budget.

A budget the caller sets bounds the process's resident memory, so the engine
plans against it less what the process already holds when the run starts
(:func:`held_bytes`: the interpreter, its libraries and the caller's data, about
0.1 GiB in a bare ``dqm match``); the default budget is a fraction of the memory
still available, which already leaves that out.
"""
from __future__ import annotations

import os
import re
from typing import Optional, Union

from ..validation import InputError

#: peak bytes per directed candidate edge of the dense path: int32 while the pass runs, then int64 child and
#: candidate and the float64 distance, every other temporary taken in chunks (the radius filter, the rank
#: tests, the parents in one native pass): 28 measured on 300k generated features (19.6M edges, 0.92 GiB
#: peak of which 0.4 GiB held before the edges), with margin; 74 before the chunking
BYTES_PER_EDGE = 32
#: the dense path handles an edge in ~0.5 us (exact distance, sort); the
#: streaming pass costs a second GEMM over all pairs. On graf (21,691 SIFT) they
#: break even near n^2 / 117 edges (rho 1.2: 3.15 s dense, 2.95 s streaming);
#: past n^2 / BREAK_EVEN the engine streams even when memory would allow more
BREAK_EVEN = 128
#: fraction of the available memory used when no budget is given
DEFAULT_FRACTION = 0.7

_UNITS = {"": 1, "b": 1, "k": 1 << 10, "kb": 1 << 10, "kib": 1 << 10, "m": 1 << 20, "mb": 1 << 20,
          "mib": 1 << 20, "g": 1 << 30, "gb": 1 << 30, "gib": 1 << 30, "t": 1 << 40, "tb": 1 << 40,
          "tib": 1 << 40}


class MemoryBudgetError(InputError):
    """The input cannot be processed within the memory budget."""


def parse_size(text: Union[str, int, float]) -> int:
    """Bytes from ``"8G"``, ``"512MiB"``, ``"1.5 GB"`` or a plain number (binary units)."""
    if isinstance(text, (int, float)) and not isinstance(text, bool):
        value = float(text)
    else:
        m = re.fullmatch(r"\s*([0-9]*\.?[0-9]+)\s*([a-zA-Z]*)\s*", str(text))
        if not m or m.group(2).lower() not in _UNITS:
            raise InputError(f"memory size {text!r} is not understood; write e.g. 8G, 512M or 2.5GiB")
        value = float(m.group(1)) * _UNITS[m.group(2).lower()]
    if not (value > 0 and value < float(1 << 62)):
        raise InputError(f"memory size must be positive and finite, got {text!r}")
    return int(value)


def available_bytes() -> int:
    """Memory this process can still use: MemAvailable, or the cgroup's limit minus its usage if lower."""
    avail = None
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    avail = int(line.split()[1]) * 1024
                    break
    except OSError:
        pass
    if avail is None:
        try:
            avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (ValueError, OSError, AttributeError):
            avail = 8 << 30
    try:
        with open("/sys/fs/cgroup/memory.max") as fh:
            limit = fh.read().strip()
        if limit != "max":
            with open("/sys/fs/cgroup/memory.current") as fh:
                used = int(fh.read().strip())
            avail = min(avail, max(0, int(limit) - used))
    except (OSError, ValueError):
        pass
    return int(avail)


def resolve_budget(max_memory: Union[None, str, int, float]) -> int:
    """The budget in bytes: ``max_memory`` if given, else 70% of the available memory."""
    if max_memory is None:
        return int(DEFAULT_FRACTION * available_bytes())
    return parse_size(max_memory)


def process_bytes() -> int:
    """Resident memory of this process now (bytes; 0 where /proc is not available)."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError, AttributeError):
        return 0


def restart_peak() -> None:
    """Start :func:`peak_bytes` over from the present resident memory (Linux: 5 to /proc/self/clear_refs; elsewhere
    nothing: the peak then stays the process's)."""
    try:
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:
        pass


def peak_bytes() -> int:
    """Peak resident memory of this process (bytes): VmHWM, which writing 5 to /proc/self/clear_refs restarts
    from the present; else the resource module's ru_maxrss (KiB on Linux); 0 where neither is there."""
    try:
        with open("/proc/self/status") as fh:
            return int(next(line for line in fh if line.startswith("VmHWM")).split()[1]) * 1024
    except (OSError, StopIteration, ValueError, IndexError):
        pass
    try:
        import resource

        return int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024
    except (ImportError, OSError):
        return 0


def held_bytes(max_memory, *inputs) -> int:
    """What a run must leave out of the budget ``max_memory``: the process's resident memory now,
    less the ``inputs`` arrays (the models count them); 0 without a budget of the caller's (the default
    budget comes from the memory still available, which leaves the process out already)."""
    if max_memory is None:
        return 0
    arrays = {}
    for x in inputs:
        while getattr(x, "base", None) is not None:  # a view: count the array it views, once
            x = x.base
        if hasattr(x, "nbytes"):
            arrays[id(x)] = int(x.nbytes)
    return max(0, process_bytes() - sum(arrays.values()))


def _beside(held: int) -> str:
    return f" beside the {format_bytes(held)} this process already holds," if held else ""


def format_bytes(b: float) -> str:
    """``1.5 GiB``, ``320 MiB``."""
    if b >= 1 << 30:
        return f"{b / (1 << 30):.1f} GiB"
    return f"{b / (1 << 20):.0f} MiB"


def base_bytes(n: int, dim: int, n_threads: int, itemsize: Optional[int] = None, float_operands: bool = True) -> int:
    """Peak memory of an exact run apart from the candidate edges: the input and its copies, about
    twenty per-feature arrays, and each worker's tiles and buffers.

    ``itemsize``: the bytes per value of integer descriptors that the engine keeps as they are
    (:attr:`dqm.core.pairs.Augmented.exact_d2`): the input, a compact copy or the packed operands of
    the integer kernel (2 bytes a value at most), and the float32 GEMM operands. None: float
    descriptors, held as a float64 input, its float64 centred copy, the float32 operands and a
    compact copy. ``float_operands`` False: the float32 operands are never made whole (the fast engine on the
    integer kernel, :func:`check_fast`)."""
    per_value = 8 + 8 + 4 + 4 + 1 if itemsize is None else int(itemsize) + 2 + (4 + 4 if float_operands else 0)
    per_feature = dim * per_value + 8 + 20 * 8
    per_thread = (48 << 20) * min(1.0, n / 1024)  # a tile and its buffers; smaller inputs, smaller tiles
    return int(n * per_feature + n_threads * per_thread + (16 << 20))


def check_base(n: int, dim: int, n_threads: int, budget: int, what: str = "quickmatch",
               itemsize: Optional[int] = None, held: int = 0) -> int:
    """Refuse, in one line, an input whose arrays alone exceed the budget (less ``held``, see
    :func:`held_bytes`); returns the base bytes (``itemsize``: see :func:`base_bytes`)."""
    base = base_bytes(n, dim, n_threads, itemsize)
    if base + held > budget:
        raise MemoryBudgetError(
            f"{what}: {n:,} features of dimension {dim} need about {format_bytes(base)} even with the "
            f"streaming parent pass,{_beside(held)} more than the memory budget of {format_bytes(budget)} "
            "(max_memory / --max-memory); raise the budget, use fewer features, or the approximate mode"
        )
    return base


def check_approximate(n: int, dim: int, k: int, n_threads: int, budget: int, held: int = 0) -> int:
    """Refuse, in one line, an approximate run that would not fit the budget; returns its estimate.

    The exact run's base arrays (sigma is exact), faiss' float32 copy of the
    data, and the neighbour graph with its kernel-term temporaries (~40 bytes
    per edge)."""
    need = base_bytes(n, dim, n_threads) + n * dim * 4 + 40 * n * k
    if need + held > budget:
        raise MemoryBudgetError(
            f"quickmatch: the approximate mode with {k} neighbours needs about {format_bytes(need)} for "
            f"{n:,} features of dimension {dim},{_beside(held)} more than the memory budget of {format_bytes(budget)} "
            "(max_memory / --max-memory); raise the budget or lower n_neighbors")
    return need


def fast_bytes(n: int, dim: int, n_probe: int, n_lists: int, n_threads: int, itemsize: Optional[int] = None,
               max_candidates: int = 32, integer_kernel: bool = False) -> int:
    """Peak memory of a fast-engine run (:mod:`dqm.core.inverted_lists`), counted from what its largest step holds.

    The exact run's base arrays (sigma is exact; :func:`base_bytes`, without whole float32 operands on the
    ``integer_kernel``: :attr:`dqm.core.pairs.Augmented.integer_kernel`, uint8 descriptors and AVX-512 VNNI),
    beside the largest of, per feature (``t`` probes, ``w`` 64-bit words of a bitset of the lists, ``m``
    ``max_candidates``): the lists' set-up (each feature's ``t`` nearest lists, int32, which it scans, twice, its
    bitset and the scans list by list, int32: ``10 t + 8 w``); the scan (the operands in list order: the packed
    integer rows, ``2 dim`` bytes, or both float32 GEMM operands, ``8 (dim + 2)``; the scans; the bitset; the
    ``m`` nearest candidates kept, 8 bytes each; about ten per-feature arrays); the candidates made edges
    (``25 m``) and their exact distances (``24 m``). A feature scans ``t - 1`` lists at most by the quota rule
    and the lists met whole add about as many scans as they drop, so ``t`` scans a feature bounds the mean: 22.7
    on 1M generated features (64 probes), 55.4 on 2M (128). Measured (scripts/bench_quickmatch.py --budgets,
    the peak above what the process held): 0.58 of this at 1M and 0.69 at 2M generated features on the integer
    kernel, 0.73 at 1M on the float32 GEMM (scripts/fast_memory_steps.py; docs/quickmatch.md)."""
    t, w, m = int(n_probe), (int(n_lists) + 63) // 64, int(max_candidates)
    operands = 2 * dim + 8 if integer_kernel else 8 * (dim + 2)
    setup = 10 * t + 8 * w
    scan = operands + 4 * t + 8 * w + 8 * m + 80
    edges = 25 * m + 80
    # the set-up's chunks of scans (inverted_lists.ENTRIES, or k^2 where the lists are more), 48 bytes a scan
    chunks = 48 * min(max(1 << 22, int(n_lists) ** 2), n * t)
    return (base_bytes(n, dim, n_threads, itemsize, float_operands=not integer_kernel)
            + n * max(setup, scan, edges) + chunks)


def check_fast(n: int, dim: int, n_probe: int, n_lists: int, n_threads: int, budget: int,
               itemsize: Optional[int] = None, held: int = 0, max_candidates: int = 32,
               integer_kernel: bool = False) -> int:
    """Refuse, in one line, a fast-engine run whose arrays would not fit the budget (less ``held``, see
    :func:`held_bytes`); returns its estimate (:func:`fast_bytes`)."""
    need = fast_bytes(n, dim, n_probe, n_lists, n_threads, itemsize, max_candidates, integer_kernel)
    if need + held > budget:
        raise MemoryBudgetError(
            f"quickmatch: the fast engine with {n_probe} probes needs about {format_bytes(need)} for {n:,} "
            f"features of dimension {dim},{_beside(held)} more than the memory budget of {format_bytes(budget)} "
            "(max_memory / --max-memory); raise the budget, lower n_probe, or use the exact engine "
            "(engine='exact', --exact)")
    return need


def max_dense_edges(n: int, base: int, budget: int) -> int:
    """Most candidate edges the dense pass may collect before the engine switches to the
    streaming parent pass: what fits the budget beside ``base`` (the base arrays and what the
    process held already), and no more than where the streaming pass becomes the faster one
    (``n^2 / BREAK_EVEN``)."""
    fits = max(0, budget - base) // BYTES_PER_EDGE
    return int(min(fits, n * n // BREAK_EVEN + (1 << 16)))
