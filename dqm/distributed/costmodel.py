"""Predicted time to result of gather, lean and balanced, on either engine: what ``--mode auto`` picks from.

Pure (numpy only, no I/O). The coordinator of a ``--mode auto`` job knows, once every agent process
is ready, the number of features ``n``, the agents ``M``, the descriptor dimension and item size; it
measures the link rate to each process (:mod:`dqm.runtime.measure`) and knows the cores of the hosts.
:func:`predict` turns these into seconds per mode, :func:`choose` picks the fastest available mode, or among
those predicted within :data:`NEAR_WITHIN` of it the one that moves the fewest bytes.

The model follows the mechanisms, with constants fitted to the emulated-host benchmark
(``docs/bench_hosts_graf.json``, ``docs/bench_hosts_100k.json``; ``scripts/fit_costmodel.py``).
With ``raw = n * dim * itemsize`` (the descriptor bytes), ``W = n (n - 1) / 2 * dim`` (the pair work
of the all-pairs pass, in pair-dimensions), ``c`` the cores of a host and ``r`` a link rate (bytes/s):

* **gather** (agent 0 gathers: every other source sends it its features, and it runs centralized QuickMatch
  on them and its own):
  ``t = start + gather_link_factor * max(B / r_g, max_p B_p / r_p) + (pair_cpu_s * W + match_fixed_cpu_s) / c_g``
  with ``B = gather_bytes * raw * (M - 1) / M`` the wire bytes of the features not already on agent 0
  (``gather_bytes``: their bytes over their raw descriptor bytes, compressed, ids included), all of it into
  agent 0's link ``r_g`` (its rate, at most the median); ``B_p``: one source's part;
* **balanced** (cells; each agent computes about ``1/M`` of the pairs, times an imbalance):
  ``t = start + balanced_fixed_s + balanced_link_factor * b * raw / M / r_min
  + (balanced_imbalance * pair_cpu_s * W / M * k + balanced_fixed_cpu_s) / c_min`` with ``b`` the bytes
  over raw of a balanced job (``balanced_bytes_per_agent * M`` unless given), spread over the ``M``
  links and gated by the slowest one ``r_min``, and ``k`` the agents of the busiest process;
* **lean** (the hand-down cascade: the work gathers at agent 0):
  ``t = start + lean_fixed_s + lean_link_factor * l * raw / r_0
  + (lean_work_share * pair_cpu_s * W + lean_fixed_cpu_s) / c_0`` with ``l`` its bytes over raw
  (``lean_bytes * (M - 1) / M`` unless given), into agent 0's link ``r_0`` (its rate, at most the
  median).

**The fast engine** (``JobShape.engine == "fast"``: ``--engine fast``, or ``auto`` from
:data:`~dqm.core.clustering.FAST_FROM` features) changes the compute terms and fast balanced's bytes:

* the centralized match (gather; lean's agent 0 at ``lean_work_share`` of it) is
  ``(fast_kernel_cpu_s * speed + fast_other_cpu_s) * (n / 1e5) ** fast_exponent``: the part that scales with the
  host's measured pair kernel (``speed``, below: the candidates' exact distances) and the part that does not
  (k-means, lists, scans), told apart by rows of machines whose kernels differ 10x (the exponent, 1.01, comes
  from 21,691 real features against 100,186 generated ones, which are easier per feature: on generated sets
  alone the engine grows as about n^1.25 from 60k to 1M, so jobs far beyond 100k are predicted too cheap);
* fast balanced's busiest agent pays its cell's own pairs and its copies' (``JobShape.cell_pair_work``,
  ``(n/M)^2 (1/2 + copies) dim``, ``copies`` the copy budget; where its cell is large enough for lists, the
  share of them its lists compute, from about 10,000 features a cell; every fit row ran the exact cell
  pass, ``JobShape.cell_share``) times
  ``fast_balanced_imbalance``, plus
  ``fast_balanced_other_cpu_s`` per 10,000 features of its cell and ``fast_balanced_fixed_cpu_s``; its bytes are
  the routed features and ``fast_copy_bytes`` per copy.

The engine is not the model's to choose: ``--engine auto`` is ``dqm match``'s quality rule (the fast engine
from ``FAST_FROM`` features; below it the exact clusters cost little), and the model picks the mode for that
engine. A speed rule would pick the fast engine at every size (it is never slower), and give approximate
clusters where the exact ones were cheap.

``pair_cpu_s`` is the fit machine's; a job measures its own host's all-pairs kernel
(:func:`dqm.core.pairs.pair_cpu_s_here`, a few milliseconds) and the model scales ``pair_cpu_s`` by it over
the fit machine's measurement ``kernel_cpu_s`` (:meth:`Hosts.pair_cpu_s`): the fitted constant alone
mispredicted the centralized pass 3x on a machine faster than the fit's, and picked balanced where gather
was faster.

``start`` is the processes' start-up, as the benchmark ran each mode: ``run_start_cpu_s / c_0`` for lean and
balanced, jobs of ``dqm run`` / ``dqm coordinator`` (host 0 holds agent 0 and the coordinator);
``(gather_start_cpu_s + gather_skew_cpu_s) / c_g`` for gather, the stand-alone gathering of
``dqm.runtime.gather`` (its own start-up, and its wait for the last source to start); 0 when the
processes are already running (``started=True``: the coordinator's case, whose start-up is paid
whatever it picks, gather inside ``dqm run`` included).

**Balanced is unavailable** when one link's share of its bytes (``b * raw / M``) takes longer than
``starve_s`` at the slowest measured rate: its processes then wait behind seconds of bulk traffic, and
beyond the liveliness lease the router takes them for lost. With the 2-s lease of issue 25, 100k
features at M = 8 over 10 Mbit/s (about 9.8 MB per link, 7.8 s) failed; with the 8-s lease
(dqm.runtime.bus.LEASE_MS) the same job (4.4x raw after compression, about 7 MB per link, 5.6 s)
finished first of all modes. ``starve_s = 16``, twice the lease, is the rule; no job has been seen
failing at this lease, so the threshold is a guard, not a measurement.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from typing import Callable, Dict, Optional, Sequence, Tuple

import numpy as np

from ..core import inverted_lists
from ..validation import InputError
from .ghosts import copy_budget

#: the modes :func:`choose` picks from, in the order that breaks an exact tie
AUTO_MODES = ("gather", "balanced", "lean")
#: the engines a job runs (``auto`` resolved: :meth:`dqm.distributed.config.DQMConfig.engine_for`), each predicted
ENGINES_RUN = ("exact", "fast")
#: link rates (bytes/s, 1 Mbit/s to 10 Gbit/s) over which ``--mode auto`` asks whether one mode is (about) the
#: fastest whatever the links: then it starts that mode without timing them (:func:`rate_free_choice`)
CLEAR_RATES_BYTES_S = tuple(mbit * 1e6 / 8 for mbit in (1, 3, 10, 30, 100, 300, 1000, 3000, 10000))
#: a mode is picked without timing the links when, at every rate of :data:`CLEAR_RATES_BYTES_S`, its predicted
#: time is at most this factor of the fastest mode's: the probes (0.1-0.2 s per process) would cost more than
#: they could save
CLEAR_WITHIN = 1.10
#: modes predicted within this factor of the fastest are taken as equally fast, and the one that moves the fewest
#: bytes runs: the model is no closer than that (docs/bench_hosts_graf.json: 0.84-1.18x of the measured times), a
#: measured pair rate in a small CPU quota varies 20-40% (on graf's 8 quarter-core hosts gather and balanced
#: trade places at 1.2x the fit machine's rate), and the links are what a team of robots has least of
NEAR_WITHIN = 1.10
#: where the pick is settled above some rate of :data:`CLEAR_RATES_BYTES_S` (:func:`settled_above`), a link that
#: one probe pair shows at least this many times faster than that rate needs no finer measurement
SETTLED_MARGIN = 2.0


@dataclass(frozen=True)
class CostConstants:
    """The model's constants (seconds, CPU-seconds at one core, and factors).

    Fitted by ``.venv/bin/python scripts/fit_costmodel.py`` (non-negative least squares per mechanism on
    relative residuals, on the rows of docs/bench_hosts_graf.json and docs/bench_hosts_100k.json: 2-core AMD
    EPYC Zen 4 with AVX-512 VNNI, uint8 SIFT descriptors of 128 dimensions, 2026-11-28); ``starve_s`` is set
    from the lease (above). The pair work scales with the kernel measured where a job runs (``kernel_cpu_s``).
    """

    #: CPU-seconds per pair-dimension of the centralized all-pairs pass (uint8, the VNNI tile kernel)
    pair_cpu_s: float = 1.259e-11
    #: :func:`dqm.core.pairs.pair_cpu_s_here` (uint8, 128 dimensions) on the machine of the fit: a job's
    #: pair work is predicted at ``pair_cpu_s`` times its own host's measurement over this
    kernel_cpu_s: float = 1.065e-11
    #: a gather's wire bytes over the raw descriptor bytes of the features sent (compressed, ids included;
    #: graf 0.77, 0.67, 0.73 at M = 2, 4, 8, 100k 0.80 at M = 8). Every byte constant here was fitted on rows
    #: of schema 7; schema 8 sends the sigmas of uint8 descriptors as integers (dqm.distributed.wire, roots),
    #: 3-5% fewer bytes in every mode, so these predict slightly more bytes than a job moves
    gather_bytes: float = 0.7394
    #: CPU-seconds of a centralized match beyond its pairs (imports, sigma, tree)
    match_fixed_cpu_s: float = 0
    #: CPU-seconds a stand-alone gathering host waits for its sources to start (start-up skew)
    gather_skew_cpu_s: float = 0.02187
    #: the gathered bytes' time over bytes / rate
    gather_link_factor: float = 1.178
    #: CPU-seconds a stand-alone gathering process spends starting
    gather_start_cpu_s: float = 0.2477
    #: CPU-seconds of host 0's start-up in a dqm run job (agent 0, the coordinator, the ready handshake)
    run_start_cpu_s: float = 0.416
    #: seconds of a balanced job beyond its work and bytes (the set-up's and the rounds' round trips)
    balanced_fixed_s: float = 0.009854
    #: the busiest agent's pair work over the centralized pass's / M (cells and ghost copies)
    balanced_imbalance: float = 2.061
    #: CPU-seconds of a balanced agent beyond its pairs (set-up, sketches, rounds)
    balanced_fixed_cpu_s: float = 0.3393
    #: one link's share of the balanced bytes: its time over bytes / rate (rounds wait for each other)
    balanced_link_factor: float = 1.467
    #: balanced bytes over raw, per agent (graf 0.50, 0.53, 0.46 at M = 2, 4, 8; 100k 0.55 at M = 8, the same
    #: at 10 Mbit/s)
    balanced_bytes_per_agent: float = 0.5089
    #: seconds of a lean job beyond its work and bytes
    lean_fixed_s: float = 0.1297
    #: agent 0's pair work in a lean job over the centralized pass's (the cascade gathers it there)
    lean_work_share: float = 1.177
    #: CPU-seconds of lean's agent 0 beyond its pairs
    lean_fixed_cpu_s: float = 0
    #: lean's bytes (into agent 0's link): their time over bytes / rate
    lean_link_factor: float = 0.8962
    #: lean bytes over raw, times M / (M - 1) (graf 1.39, 1.73, 1.67 at M = 2, 4, 8; 100k 1.76 at M = 8)
    lean_bytes: float = 1.637
    #: balanced is unavailable when one link's share of its bytes takes longer than this (seconds)
    starve_s: float = 16
    #: the fast engine's centralized match of 100,000 features (CPU-seconds at one core): the part that scales
    #: with the measured pair kernel (its exact distances of the candidates) ...
    fast_kernel_cpu_s: float = 1.049
    #: ... and the part that does not (k-means, lists, scans, the tree)
    fast_other_cpu_s: float = 3.594
    #: the fast engine's match grows as ``n ** fast_exponent``
    fast_exponent: float = 1.01
    #: fast balanced: the busiest agent's pair work over one cell's (:attr:`JobShape.cell_pair_work`)
    fast_balanced_imbalance: float = 0.9601
    #: CPU-seconds of a fast balanced agent beyond its pairs per 10,000 features of its cell (routing, the copies'
    #: choice, densities and parents: numpy work that does not scale with the pair kernel) ...
    fast_balanced_other_cpu_s: float = 0.8248
    #: ... and per agent (set-up, the rounds)
    fast_balanced_fixed_cpu_s: float = 0.2397
    #: fast balanced bytes over raw: the routed features (``gather_bytes * (M - 1) / M``) and this per copy
    fast_copy_bytes: float = 1.091


#: the fitted constants (see :class:`CostConstants`)
FITTED = CostConstants()


@dataclass(frozen=True)
class JobShape:
    """What the coordinator knows of a job once every process is ready."""

    n: int  #: features
    agents: int  #: agents M
    dim: int  #: descriptor dimension
    itemsize: int = 1  #: bytes per descriptor element (1: uint8, 4: float32)
    #: the engine the job runs (:data:`dqm.distributed.config.DISTRIBUTED_ENGINES`, ``auto`` already resolved)
    engine: str = "exact"
    #: fast balanced: copies per own feature at most (None: :func:`dqm.distributed.ghosts.copy_budget`)
    copies: Optional[float] = None
    #: fast balanced: the share of a cell's pairs it computes (None: its lists' rule,
    #: :func:`dqm.core.inverted_lists.cell_pairs_share`; a benchmark row of older code says what ran)
    cell_share: Optional[float] = None

    @property
    def copies_per_feature(self) -> float:
        """Fast balanced's copy budget per own feature."""
        return copy_budget(self.agents) if self.copies is None else float(self.copies)

    @property
    def cell_pair_work(self) -> float:
        """Fast balanced: pair-dimensions of one cell, its own pairs and its copies' with them (cells of n/M
        features, as many copies received as sent): ``(n/M)^2 (1/2 + copies) dim``, times the share of them the
        cell's lists compute where they pay (:func:`dqm.core.inverted_lists.cell_pairs_share`)."""
        cell = self.n / self.agents
        share = inverted_lists.cell_pairs_share(int(cell)) if self.cell_share is None else float(self.cell_share)
        return cell * cell * (0.5 + self.copies_per_feature) * self.dim * share

    @property
    def raw_bytes(self) -> float:
        """The descriptors' bytes."""
        return float(self.n) * self.dim * self.itemsize

    @property
    def pair_work(self) -> float:
        """Pair-dimensions of the all-pairs pass: n (n - 1) / 2 * dim."""
        return self.n * (self.n - 1) / 2.0 * self.dim


@dataclass(frozen=True)
class Hosts:
    """The hosts of a job as the coordinator sees them.

    ``rates``: the measured link rate (bytes/s) from the coordinator to each agent process (its
    link, or the coordinator's if slower; links taken as symmetric); ``cores``: the cores of each
    process's host (one number: every host); ``gather_cores``: the cores the gathering host gives
    the centralized match (default: host 0's); ``gather_rate``: the rate into the gathering host
    (default: the median measured: its own link bounds every path it measured, and the median is not
    misled by one process whose probes read high, e.g. one sharing the coordinator's host and link);
    ``kernel_cpu_s``: :func:`dqm.core.pairs.pair_cpu_s_here` measured where the job runs (None: the machine of
    the fit's speed is assumed). Process 0 hosts agent 0.
    """

    rates: Tuple[float, ...]
    cores: Tuple[float, ...]
    gather_cores: Optional[float] = None
    gather_rate: Optional[float] = None
    kernel_cpu_s: Optional[float] = None

    @classmethod
    def of(cls, rates: Sequence[float], cores, gather_cores: Optional[float] = None,
           gather_rate: Optional[float] = None, kernel_cpu_s: Optional[float] = None) -> "Hosts":
        """Hosts from a rate per process and the cores (one number, or one per process), checked."""
        rates = tuple(_positive(r, f"link rate of process {p}") for p, r in enumerate(_seq(rates, "rates")))
        if not rates:
            raise InputError("the cost model needs the link rate of at least one process")
        if isinstance(cores, (int, float, np.integer, np.floating)) and not isinstance(cores, bool):
            cores = (cores,) * len(rates)
        cores = tuple(_positive(c, f"cores of process {p}") for p, c in enumerate(_seq(cores, "cores")))
        if len(cores) != len(rates):
            raise InputError(f"the cost model got {len(rates)} link rates but cores for {len(cores)} processes")
        return cls(rates, cores, None if gather_cores is None else _positive(gather_cores, "gather_cores"),
                   None if gather_rate is None else _positive(gather_rate, "gather_rate"),
                   None if kernel_cpu_s is None else _positive(kernel_cpu_s, "kernel_cpu_s"))

    def pair_cpu_s(self, constants: "CostConstants") -> float:
        """CPU-seconds per pair-dimension on these hosts: the fitted value, scaled by the hosts' measured
        :attr:`kernel_cpu_s` over the fit machine's (the fitted value as it is when nothing was measured)."""
        if self.kernel_cpu_s is None:
            return constants.pair_cpu_s
        return constants.pair_cpu_s * self.kernel_cpu_s / constants.kernel_cpu_s


@dataclass(frozen=True)
class Prediction:
    """One mode's predicted time to result and its parts (seconds), its bytes, and whether it can run."""

    mode: str
    seconds: float
    parts: Dict[str, float]
    bytes: float
    available: bool = True
    why_not: str = ""

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass(frozen=True)
class Choice:
    """:func:`choose`'s answer: the mode, every mode's prediction and a one-line reason."""

    mode: str
    predictions: Dict[str, Prediction] = field(default_factory=dict)
    reason: str = ""

    @property
    def predicted_s(self) -> Dict[str, Optional[float]]:
        """Seconds per mode (None: unavailable), rounded to milliseconds."""
        return {m: (round(p.seconds, 3) if p.available else None) for m, p in self.predictions.items()}


def _seq(values, name: str) -> list:
    try:
        return list(values)
    except TypeError:
        raise InputError(f"the cost model's {name} must be a sequence of numbers, got {values!r}") from None


def _positive(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"the cost model's {name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"the cost model's {name} must be a positive finite number, got {value!r}")
    return v


def _count(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise InputError(f"the cost model's {name} must be an integer >= {low}, got {value!r}")
    return int(value)


def check_job(job: JobShape) -> JobShape:
    """Refuse a job shape the model cannot use (one line, naming the field)."""
    _count(job.n, "n (features)", 1)
    _count(job.agents, "agents", 1)
    _count(job.dim, "dim", 1)
    _count(job.itemsize, "itemsize", 1)
    if job.engine not in ENGINES_RUN:
        raise InputError(f"the cost model predicts the engines {', '.join(ENGINES_RUN)}, got engine {job.engine!r}")
    if job.copies is not None:
        _positive(job.copies, "copies per feature")
    return job


def default_balanced_bytes(agents: int, constants: CostConstants = FITTED) -> float:
    """Balanced bytes over raw at M agents (about ``balanced_bytes_per_agent * M`` on the benchmark)."""
    return constants.balanced_bytes_per_agent * agents if agents > 1 else 0.0


def default_fast_balanced_bytes(job: JobShape, constants: CostConstants = FITTED) -> float:
    """Fast balanced bytes over raw: the routed features and the copies (``gather_bytes * (M - 1) / M +
    fast_copy_bytes * copies``)."""
    m = job.agents
    if m < 2:
        return 0.0
    return constants.gather_bytes * (m - 1) / m + constants.fast_copy_bytes * job.copies_per_feature


def fast_match_cpu_s(n: int, speed: float, constants: CostConstants = FITTED) -> float:
    """CPU-seconds of the fast engine's centralized match of ``n`` features on a host whose pair kernel takes
    ``speed`` times the fit machine's time."""
    k = constants
    return (k.fast_kernel_cpu_s * speed + k.fast_other_cpu_s) * (n / 1e5) ** k.fast_exponent


def default_lean_bytes(agents: int, constants: CostConstants = FITTED) -> float:
    """Lean bytes over raw at M agents (``lean_bytes * (M - 1) / M``)."""
    return constants.lean_bytes * (agents - 1) / agents


def _median(values: np.ndarray) -> float:
    """``np.median`` of a few values, the same bits, without the import of ``numpy.ma`` that ``np.median``'s first
    call makes (about 20 ms of CPU in a coordinator on a quarter core: 80 ms before ``--mode auto`` decides)."""
    s = np.sort(np.asarray(values, float))
    k = len(s) // 2
    return float(s[k]) if len(s) % 2 else float((s[k - 1] + s[k]) / 2)


def predict(job: JobShape, hosts: Hosts, constants: CostConstants = FITTED, *, started: bool = False,
            gather_bytes_over_raw: Optional[float] = None, balanced_bytes_over_raw: Optional[float] = None,
            lean_bytes_over_raw: Optional[float] = None) -> Dict[str, Prediction]:
    """Predicted time to result of gather, balanced and lean (:data:`AUTO_MODES` order).

    ``started``: the processes are already running (start-up left out: the coordinator's case); else
    lean and balanced pay ``dqm run``'s start-up and gather that of ``dqm.runtime.gather``, the benchmark's
    stand-alone gathering (its agent 0 keeps its own features, as agent 0 does in ``dqm run``).
    ``gather_bytes_over_raw`` (of the features sent), ``balanced_bytes_over_raw``, ``lean_bytes_over_raw``: the
    modes' bytes over the raw descriptor bytes (default: the fitted ``gather_bytes``,
    :func:`default_balanced_bytes` and :func:`default_lean_bytes`): what a change of the wire format
    (compression) changes.
    """
    check_job(job)
    k = constants
    m, raw, W = job.agents, job.raw_bytes, job.pair_work
    pair = hosts.pair_cpu_s(k)
    procs = len(hosts.rates)
    rates, cores = np.asarray(hosts.rates, float), np.asarray(hosts.cores, float)
    r_mid = _median(rates)
    r_min, c_min, r0, c0 = float(rates.min()), float(cores.min()), min(float(rates[0]), r_mid), float(cores[0])
    c_g = hosts.gather_cores or c0
    r_g = hosts.gather_rate or r0  # agent 0's link
    fast = job.engine == "fast"
    b_bal = (default_fast_balanced_bytes(job, k) if fast else default_balanced_bytes(m, k)) \
        if balanced_bytes_over_raw is None else \
        _nonnegative(balanced_bytes_over_raw, "balanced_bytes_over_raw")
    b_lean = default_lean_bytes(m, k) if lean_bytes_over_raw is None else \
        _nonnegative(lean_bytes_over_raw, "lean_bytes_over_raw")
    run_start = 0.0 if started else k.run_start_cpu_s / c0
    # the centralized match on one core: all pairs, or the fast engine's lists
    match_cpu = fast_match_cpu_s(job.n, pair / k.pair_cpu_s, k) if fast else pair * W + k.match_fixed_cpu_s

    # gather: the other sources' rows into agent 0's link, then the centralized pass on its cores
    g_all = k.gather_bytes if gather_bytes_over_raw is None else \
        _nonnegative(gather_bytes_over_raw, "gather_bytes_over_raw")
    g_bytes = raw * g_all * (m - 1) / m
    per_source = max(g_bytes / (m - 1) / r for r in rates) if m > 1 else 0.0
    g_parts = {"start": 0.0 if started else k.gather_start_cpu_s / c_g,
               "fixed": k.gather_skew_cpu_s / c_g if not started and m > 1 else 0.0,
               "transfer": k.gather_link_factor * max(g_bytes / r_g, per_source),
               "compute": match_cpu / c_g}
    out = {"gather": Prediction("gather", sum(g_parts.values()), g_parts, g_bytes)}

    # balanced: 1/M of the pairs per agent (times the imbalance), the bytes spread over M links
    per_link = b_bal * raw / m
    busiest = math.ceil(m / procs)
    if fast:  # the cells' own pairs and their copies' (all of them, or their lists' share where those pay)
        b_cpu = (k.fast_balanced_imbalance * pair * job.cell_pair_work
                 + k.fast_balanced_other_cpu_s * job.n / m / 1e4) * busiest + k.fast_balanced_fixed_cpu_s
    else:
        b_cpu = k.balanced_imbalance * pair * W / m * busiest + k.balanced_fixed_cpu_s
    b_parts = {"start": run_start, "fixed": k.balanced_fixed_s,
               "transfer": k.balanced_link_factor * per_link / r_min,
               "compute": b_cpu / c_min}
    starve = per_link / r_min
    why = "" if starve <= k.starve_s else (
        f"its {per_link / 1e6:.1f} MB per link take {starve:.1f} s at {r_min / 1e6:.3g} MB/s, more than "
        f"{k.starve_s:g} s: keep-alives would starve behind its bulk traffic")
    out["balanced"] = Prediction("balanced", sum(b_parts.values()), b_parts, b_bal * raw, not why, why)

    # lean: the cascade gathers the work and the bytes at agent 0
    l_parts = {"start": run_start, "fixed": k.lean_fixed_s,
               "transfer": k.lean_link_factor * b_lean * raw / r0,
               "compute": (k.lean_work_share * (match_cpu if fast else pair * W) + k.lean_fixed_cpu_s) / c0}
    out["lean"] = Prediction("lean", sum(l_parts.values()), l_parts, b_lean * raw)
    return out


def _nonnegative(value, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"the cost model's {name} must be a number, got {value!r}") from None
    if not (math.isfinite(v) and v >= 0):
        raise InputError(f"the cost model's {name} must be a finite number >= 0, got {value!r}")
    return v


def mbit_text(bytes_s: float) -> str:
    """A link rate in Mbit/s for people, without the unit: ``1713``, ``95.4``, ``9.87``."""
    mbit = bytes_s * 8 / 1e6
    return f"{mbit:.0f}" if mbit >= 100 else f"{mbit:.3g}"


def speed_text(kernel_cpu_s: Optional[float], constants: CostConstants = FITTED) -> str:
    """``, pair work at 0.93x the fit's CPU time`` for a measured :attr:`Hosts.kernel_cpu_s`, else ``""``."""
    if kernel_cpu_s is None:
        return ""
    return f", pair work at {kernel_cpu_s / constants.kernel_cpu_s:.2f}x the fit's CPU time"


def _rate_text(bytes_s: float) -> str:
    return f"{mbit_text(bytes_s)} Mbit/s"


def choose(job: JobShape, hosts: Hosts, constants: CostConstants = FITTED, *, started: bool = True,
           modes: Sequence[str] = AUTO_MODES, **options) -> Choice:
    """The available mode of ``modes`` that moves the fewest bytes among those predicted within
    :data:`NEAR_WITHIN` of the fastest (ties: the order of :data:`AUTO_MODES`), every mode's prediction and a
    one-line reason. Deterministic: the same inputs give the same answer.
    ``options``: :func:`predict`'s (the bytes over raw)."""
    bad = [m for m in modes if m not in AUTO_MODES]
    if bad or not modes:
        raise InputError(f"the cost model picks from {', '.join(AUTO_MODES)}, got {list(modes)!r}")
    preds = predict(job, hosts, constants, started=started, **options)
    usable = [m for m in AUTO_MODES if m in modes and preds[m].available]
    if not usable:  # only balanced asked for and it cannot run: still answer, saying so
        usable = [m for m in AUTO_MODES if m in modes]
    fastest = min(usable, key=lambda m: (round(preds[m].seconds, 9), AUTO_MODES.index(m)))
    best = _fewest_bytes([m for m in usable if preds[m].seconds <= preds[fastest].seconds * NEAR_WITHIN], preds)
    others = ", ".join(f"{m} {preds[m].seconds:.1f} s" if preds[m].available else f"{m} unavailable"
                       for m in AUTO_MODES if m in modes and m != best)
    rates = np.asarray(hosts.rates)
    link = (_rate_text(float(rates.min())) if rates.min() == rates.max()
            else f"{_rate_text(float(rates.min()))} to {_rate_text(float(rates.max()))}")
    reason = (f"{best}: predicted {preds[best].seconds:.1f} s" + (f" against {others}" if others else "")
              + f" ({job.n} features of {job.dim} x {job.itemsize} B on {job.agents} agents, {job.engine} engine, "
              f"links {link}, "
              f"cores per host {min(hosts.cores):.3g}{speed_text(hosts.kernel_cpu_s, constants)})")
    if best != fastest:
        reason += (f"; within {100 * (NEAR_WITHIN - 1):.0f}% of {fastest}'s time with "
                   f"{preds[best].bytes / max(preds[fastest].bytes, 1.0):.2f}x its bytes")
    if not preds["balanced"].available and "balanced" in modes:
        reason += f"; balanced ruled out: {preds['balanced'].why_not}"
    return Choice(best, {m: preds[m] for m in AUTO_MODES if m in modes}, reason)


def _fewest_bytes(modes: Sequence[str], preds: Dict[str, Prediction]) -> str:
    """Of ``modes``, the one whose predicted bytes are the fewest (ties: :data:`AUTO_MODES` order)."""
    return min(modes, key=lambda m: (round(preds[m].bytes, 3), AUTO_MODES.index(m)))


def rate_free_choice(job: JobShape, hosts_at: Callable[[float], Hosts], constants: CostConstants = FITTED, *,
                     modes: Sequence[str] = AUTO_MODES, within: float = CLEAR_WITHIN,
                     rates: Sequence[float] = CLEAR_RATES_BYTES_S
                     ) -> Optional[Tuple[str, float, Tuple[float, float]]]:
    """The mode to run without timing the links, if there is one: of the available modes of ``modes`` whose predicted
    time (processes started) is at most ``within`` times the fastest's at every rate ``r`` of ``rates`` (default
    :data:`CLEAR_RATES_BYTES_S`; ``hosts_at(r)``: the hosts with their links at ``r``), the one that moves the
    fewest bytes (ties: :data:`AUTO_MODES` order). Returns ``(mode, worst ratio, (least, most) predicted seconds)``, or
    None when the answer turns on the links (then they are timed)."""
    return _free_of_rates([predict(job, hosts_at(r), constants, started=True) for r in rates], modes, within)


def _free_of_rates(preds: Sequence[Dict[str, Prediction]], modes: Sequence[str], within: float
                   ) -> Optional[Tuple[str, float, Tuple[float, float]]]:
    """:func:`rate_free_choice` on the predictions at each of its rates."""
    candidates = [m for m in AUTO_MODES if m in modes]
    worst: Dict[str, float] = {}
    for mode in candidates:
        ratios = []
        for p in preds:
            usable = [p[m].seconds for m in candidates if p[m].available]
            ratios.append(p[mode].seconds / min(usable) if p[mode].available and usable else math.inf)
        worst[mode] = 1.0 if len(candidates) == 1 else max(ratios)  # one mode to run: nothing to measure
    near = [m for m in worst if worst[m] <= within]
    if not near:
        return None
    best = _fewest_bytes(near, preds[0])  # the bytes do not depend on the rate
    seconds = [p[best].seconds for p in preds]
    return best, worst[best], (min(seconds), max(seconds))


def settled_above(job: JobShape, hosts_at: Callable[[float], Hosts], constants: CostConstants = FITTED, *,
                  modes: Sequence[str] = AUTO_MODES, within: float = CLEAR_WITHIN
                  ) -> Optional[Tuple[float, str, float]]:
    """Where the answer turns on the links only below some rate: the least rate ``floor`` of
    :data:`CLEAR_RATES_BYTES_S` such that :func:`rate_free_choice` over the rates from ``floor`` up finds a
    mode. Returns ``(floor, mode, worst ratio)``, or None when no rate settles it (10 Gbit/s alone does not). Links
    known to be at least ``floor`` fast need no finer timing (the coordinator's probes stop at
    :data:`SETTLED_MARGIN` times it)."""
    grid = list(CLEAR_RATES_BYTES_S)
    preds = [predict(job, hosts_at(r), constants, started=True) for r in grid]  # once per rate
    found = None
    for k in range(len(grid) - 1, -1, -1):  # the settled range only grows downwards until it breaks
        here = _free_of_rates(preds[k:], modes, within)
        if here is None or (found is not None and here[0] != found[1]):
            break
        found = (grid[k], here[0], here[1])
    return found
