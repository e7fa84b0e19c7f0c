"""Parameters of a distributed job, identical in the simulator and the runtime.

Modes (``mode=``):

* ``"balanced"`` (default): exact and spread. Features stay in their cells;
  copies of boundary features (ghosts) travel one way to the cells they may
  interact with, after a lower-bound sketch exchange that keeps implausible
  copies home. Densities are summed exactly across agents, parents are chosen
  at the feature's owner from every agent's proposals, and only the tree
  components that cross cells travel (as edge lists, no descriptors) to the
  lowest agent involved. Labels are identical to :func:`dqm.quickmatch` with
  the same kernel and rho (quadratic kernel only: its finite support is what
  lets cells work apart).
* ``"lean"``: the hand-down cascade (agent m-1 down to 0) of contested tree
  components. Fewest bytes on SIFT-like data at small m, but work gathers at
  agent 0 (docs/distributed.md).
* ``"paper"``: the seed paper's literal procedure (per-agent sigma, QP cell
  distances, local clusters as units).

Two more modes exist only in the runtime (``dqm run``, ``dqm coordinator``, ``dqm agent``:
:data:`RUNTIME_MODES`), not in the simulator:

* ``"gather"``: every other agent sends its features to agent 0, which keeps its own, runs
  :func:`dqm.quickmatch` with the job's kernel and rho (the balanced mode's clusters) and sends the
  coordinator the labels;
* ``"auto"``: the coordinator measures the link to every agent process once all are
  ready and picks gather, lean or balanced with :mod:`dqm.distributed.costmodel`.
"""
from __future__ import annotations

import hashlib
from dataclasses import Field, dataclass, field, fields, replace
from typing import Dict, List, Optional, Tuple, get_type_hints

from ..core.clustering import FAST_FROM
from ..core.params import DEFAULT_RATIO_DENSITY, DEFAULT_RHO, FINITE_KERNEL, KERNELS, QuickMatchParams
from ..validation import InputError, check_choice, check_positive
from . import ghosts, keys, partition
from .costmodel import AUTO_MODES

#: the distributed algorithms (the simulator runs these)
MODES = ("balanced", "lean", "paper")
#: how the coordinator recovers an agent process lost while the job runs: ``takeover`` (the next live
#: process runs the lost agents again from their start, fed again by the others, who keep their work) or
#: ``restart`` (every process starts the job again in the next epoch); docs/runtime.md
RECOVERY = ("takeover", "restart")
#: the modes a runtime job may be started with: the algorithms, ``gather`` (centralized at agent 0)
#: and ``auto`` (the coordinator picks gather, lean or balanced from measured links; docs/runtime.md)
RUNTIME_MODES = MODES + ("gather", "auto")
DEFAULT_MODE = "balanced"
GHOST_RULES = ("one-way", "two-way")
#: the default partition seed integer (every command and DQMConfig)
DEFAULT_SEED = 1
#: the default dimension of the lower-bound sketches (docs/distributed.md, frontier table)
DEFAULT_SKETCH_DIMS = 48
#: the engines a distributed job runs (``dqm match``'s vocabulary; docs/distributed.md "The fast engine"):
#: ``auto`` (the coordinator picks exact below FAST_FROM features in all, fast from there, as dqm match does,
#: and its ``go`` names the pick), ``exact`` (every pair within reach; balanced mode's labels are the
#: centralized ones bit for bit) or ``fast``
#: (gather, lean, paper: dqm.quickmatch's fast engine where they cluster; balanced: copies travel only where a
#: pair is likely, :func:`dqm.distributed.ghosts.likely_copies`, and a cell of 10,000 features or more meets the
#: pairs its lists' scans meet, :class:`dqm.core.inverted_lists.CellLists`; smaller cells meet every pair)
DISTRIBUTED_ENGINES = ("exact", "fast", "auto")
DEFAULT_ENGINE = "exact"


def _check_int(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise InputError(f"{name} must be an integer >= {low}, got {value!r}")
    return value


def _meta(help: str, flag: str, shared: Optional[int], **more) -> Dict[str, object]:
    """A field's metadata: ``help`` (its command-line help), ``flag`` (its command-line option),
    ``shared`` (its place in :meth:`DQMConfig.params_text`, 1 first; None: not a shared parameter)
    and optionally ``choices``, ``aliases`` (more option names), ``negation`` and ``negation_help``
    (the option that sets a tri-state flag False), ``own_option`` (each command defines the option
    itself, with its own default or none)."""
    return {"help": help, "flag": flag, "shared": shared, **more}


def _qm_help(name: str) -> str:
    """The help text of a QuickMatch parameter, as :class:`QuickMatchParams` defines it."""
    return next(f.metadata["help"] for f in fields(QuickMatchParams) if f.name == name)


@dataclass(frozen=True)
class DQMConfig:
    """Parameters of a distributed job.

    ``agents``, ``seed`` (the one partition integer), ``partition`` (``kmeans``:
    k-means on a sample pooled at agent 0; ``seeded``: seeds from the integer
    alone), ``mode`` (see the module doc), ``rho``, ``kernel`` (the QuickMatch
    parameters, :attr:`params`: only the finite quadratic kernel),
    ``samples_per_agent`` (descriptors each agent sends to agent 0 for the
    seeds, the cell weights and the sketch basis), ``halo`` (lean/paper:
    contested-test width, 1 = safe), ``seed_norm`` (seeded seeds' norm),
    ``job`` (keeps concurrent jobs apart), ``cell_weights`` (power-diagram
    weights that balance the cells; None = on in balanced mode only),
    ``ghost_rule`` (balanced: ``one-way`` ships each cross-cell pair one way;
    ``two-way`` is the plain bisector halo, for comparison), ``sketch_dims``
    (balanced: dimension of the lower-bound sketch pre-filter, 0 = off) and
    ``balance_rounds`` (most weight-refinement rounds on the full counts).

    Every field's ``metadata`` says its command-line option and help (the
    runtime commands' options are generated from it:
    :mod:`dqm.commands.runtime_options`) and whether every process of a job
    must agree on it (:data:`SHARED_PARAMS`).
    """

    agents: int = field(metadata=_meta("number of agents M", "--agents", 1, own_option=True))
    seed: int = field(default=DEFAULT_SEED, metadata=_meta(
        "partition seed integer (not shared: the coordinator broadcasts it)", "--seed", None, own_option=True))
    partition: str = field(default="kmeans", metadata=_meta(
        "how the cell seeds are drawn from the seed integer", "--partition", 3,
        choices=partition.PARTITION_MODES))
    mode: str = field(default=DEFAULT_MODE, metadata=_meta(
        "balanced (clusters identical to centralized, work spread evenly), lean (the hand-down cascade: fewer "
        "bytes, work gathers at agent 0), paper (the seed paper's literal procedure), gather (every other agent's "
        "features to agent 0, which matches them all centrally) or auto (the coordinator measures the links "
        "and picks gather, lean or balanced); docs/distributed.md, docs/runtime.md",
        "--mode", 2, choices=RUNTIME_MODES))
    rho: float = field(default=DEFAULT_RHO, metadata=_meta(_qm_help("rho"), "--rho", 5))
    kernel: str = field(default=FINITE_KERNEL, metadata=_meta(
        "density kernel: a distributed job takes only the finite quadratic one (a density never needs features "
        "beyond a cell's halo), while dqm match and dqm demo default to the reference code's Gaussian; with the "
        "same kernel the clusters equal dqm.quickmatch's", "--kernel", 4, choices=KERNELS))
    samples_per_agent: int = field(default=64, metadata=_meta(
        "set-up sample descriptors per agent", "--samples", 7, aliases=("--samples-per-agent",)))
    halo: float = field(default=1.0, metadata=_meta(
        "lean/paper: contested-test width factor (1 = safe)", "--halo", 6))
    seed_norm: float = field(default=512.0, metadata=_meta(
        "descriptor norm for seeded seeds (SIFT: 512)", "--seed-norm", 8))
    job: str = field(default="job", metadata=_meta(
        "job id; keeps concurrent jobs on one router apart (not shared: it names the key space)", "--job", None))
    cell_weights: Optional[bool] = field(default=None, metadata=_meta(
        "balance the cells with power-diagram weights (default: on in balanced mode)", "--cell-weights", 9,
        negation="--no-cell-weights", negation_help="plain Voronoi cells"))
    ghost_rule: str = field(default="one-way", metadata=_meta(
        "balanced: one-way (default) or two-way (the plain bisector halo, for comparison)", "--ghost-rule", 10,
        choices=GHOST_RULES))
    sketch_dims: int = field(default=DEFAULT_SKETCH_DIMS, metadata=_meta(
        "balanced: dimension of the lower-bound sketch pre-filter (0 = off)", "--sketch-dims", 11))
    balance_rounds: int = field(default=12, metadata=_meta(
        "most rounds of cell-weight refinement", "--balance-rounds", 12))
    engine: str = field(default=DEFAULT_ENGINE, metadata=_meta(
        "exact (default: every pair within reach; balanced gives dqm.quickmatch's labels bit for bit), fast "
        "(dqm match's fast engine, its default from {:,} features: gather, lean and paper cluster with it; "
        "balanced sends copies only where a pair is likely, without a certificate, and large cells scan lists; "
        "clusters close to the exact "
        "ones, not bit for bit) or auto (the coordinator picks fast from {:,} features in all, as dqm match "
        "does); docs/distributed.md".format(FAST_FROM, FAST_FROM),
        "--engine", 13, choices=DISTRIBUTED_ENGINES))
    copy_budget: float = field(default=0.0, metadata=_meta(
        "fast balanced: the most copies a cell sends per feature it owns, the nearest to a boundary first (0: the "
        "default, 0.2 + M/8; more copies, closer to the exact clusters, more bytes); docs/distributed.md",
        "--copy-budget", 14))
    auto_modes: str = field(default=",".join(AUTO_MODES), metadata=_meta(
        "--mode auto: the modes the coordinator may pick, comma-separated (of gather, balanced, lean; not shared: "
        "only the coordinator picks)", "--auto-modes", None))

    @property
    def params(self) -> QuickMatchParams:
        """The QuickMatch parameters of the job: ``quickmatch(X, ids, params=cfg.params)`` gives the labels a
        balanced job gives (parent ``any``, the default ratio_density, which the quadratic kernel ignores)."""
        return QuickMatchParams(rho=self.rho, kernel=self.kernel, parent="any", ratio_density=DEFAULT_RATIO_DENSITY)

    @property
    def auto_choices(self) -> Tuple[str, ...]:
        """The modes ``--mode auto`` may pick (:attr:`auto_modes` as a tuple)."""
        return tuple(m.strip() for m in str(self.auto_modes).split(",") if m.strip())

    @property
    def weighted(self) -> bool:
        """Whether the cells get power-diagram weights."""
        return self.mode == "balanced" if self.cell_weights is None else bool(self.cell_weights)

    @property
    def source_sigma(self) -> bool:
        """Whether sigma is computed at the source (exact) rather than per cell (paper)."""
        return self.mode != "paper"

    @property
    def fast(self) -> bool:
        """Whether the job runs the fast engine (:data:`DISTRIBUTED_ENGINES`)."""
        return self.engine == "fast"

    def engine_for(self, n_features: int) -> str:
        """The engine a job of ``n_features`` features in all runs: :attr:`engine`, or for ``auto`` exact below
        :data:`~dqm.core.clustering.FAST_FROM` features and fast from there (``dqm match``'s rule)."""
        if self.engine != "auto":
            return self.engine
        return "fast" if n_features >= FAST_FROM else "exact"

    @property
    def copies_per_feature(self) -> float:
        """Fast balanced: the most copies a cell sends per own feature (:attr:`copy_budget`, or for 0 the
        default :func:`dqm.distributed.ghosts.copy_budget` of the agents)."""
        return float(self.copy_budget) if self.copy_budget > 0 else ghosts.copy_budget(self.agents)

    @property
    def sketches(self) -> bool:
        """Whether the balanced rounds exchange lower-bound sketches (exact balanced with ``sketch_dims`` > 0;
        the fast engine's copies follow :func:`dqm.distributed.ghosts.likely_copies` and need none)."""
        return self.mode == "balanced" and self.sketch_dims > 0 and not self.fast

    @property
    def needs_sample(self) -> bool:
        """Whether agents send descriptor samples to agent 0 at set-up."""
        return self.partition == "kmeans" or self.weighted or self.sketches

    def validated(self, n_features: Optional[int] = None, runtime: bool = False) -> "DQMConfig":
        """Self, after checking every field (one clear line naming it). ``runtime``: also accept the modes
        only the runtime runs (:data:`RUNTIME_MODES`: gather, auto); the simulator takes :data:`MODES`."""
        partition.check_agents(self.agents, n_features)
        partition.check_seed(self.seed)
        if runtime:  # the job id names the key space on the bus
            keys.check_job(self.job)
        check_choice(self.partition, "partition", partition.PARTITION_MODES)
        if not runtime and self.mode in RUNTIME_MODES and self.mode not in MODES:
            raise InputError(f"mode {self.mode!r} runs only in the runtime (dqm run, dqm coordinator): the "
                             f"simulator takes {', '.join(repr(m) for m in MODES)}")
        check_choice(self.mode, "mode", RUNTIME_MODES if runtime else MODES)
        picks = self.auto_choices
        if not picks or any(m not in AUTO_MODES for m in picks) or len(set(picks)) != len(picks):
            raise InputError(f"auto_modes must name some of {', '.join(AUTO_MODES)} once each, comma-separated; "
                             f"got {self.auto_modes!r}")
        # balanced mode is exact only with a finite kernel (and auto, which may pick it); lean and paper are
        # approximate and take either; gather runs dqm.quickmatch, which takes either
        may_balance = self.mode == "auto" and "balanced" in self.auto_choices
        self.params.validated(finite=self.mode == "balanced" or may_balance,
                              engine="a --mode auto job that may pick balanced (--auto-modes)" if may_balance
                              else f"a {self.mode}-mode distributed job")
        check_choice(self.ghost_rule, "ghost_rule", GHOST_RULES)
        check_choice(self.engine, "engine", DISTRIBUTED_ENGINES)
        check_positive(self.halo, "halo")
        check_positive(self.seed_norm, "seed_norm")
        _check_int(self.samples_per_agent, "samples_per_agent", 1)
        _check_int(self.sketch_dims, "sketch_dims", 0)
        _check_int(self.balance_rounds, "balance_rounds", 0)
        if isinstance(self.copy_budget, bool) or not isinstance(self.copy_budget, (int, float)) or \
                not 0 <= self.copy_budget < float("inf"):
            raise InputError(f"copy_budget must be a number >= 0 (0: the default), got {self.copy_budget!r}")
        if self.cell_weights is not None and not isinstance(self.cell_weights, bool):
            raise InputError(f"cell_weights must be True, False or None, got {self.cell_weights!r}")
        return self

    def but(self, **changes) -> "DQMConfig":
        """A copy with some fields changed."""
        return replace(self, **changes)

    def params_text(self) -> str:
        """The shared parameters as ``name=value;...`` (the start message carries it and its hash)."""
        return ";".join(f"{k}={getattr(self, k)!r}" for k in SHARED_PARAMS)


def is_shared(f) -> bool:
    """Whether a :class:`DQMConfig` field is a shared parameter (every process of a job must agree on it)."""
    return f.metadata.get("shared") is not None


#: the parameters every process of a job must share (they change the result or the protocol), in the order
#: of :meth:`DQMConfig.params_text` (the fields' ``shared`` metadata); the seed integer is not among them (the
#: coordinator broadcasts it) nor the job id (it names the key space)
SHARED_PARAMS = tuple(f.name for f in sorted(filter(is_shared, fields(DQMConfig)), key=lambda f: f.metadata["shared"]))


def params_hash(text: str) -> str:
    """A short sha256 of a parameter text."""
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def parse_params(text: str) -> Dict[str, str]:
    return dict(item.partition("=")[::2] for item in text.split(";") if item)


def differing_param(mine: str, theirs: str) -> Optional[Tuple[str, str, str]]:
    """The first parameter whose value differs between two parameter texts: (name, mine, theirs), or None."""
    a, b = parse_params(mine), parse_params(theirs)
    for k in list(a) + [k for k in b if k not in a]:
        if a.get(k) != b.get(k):
            return k, a.get(k, "(absent)"), b.get(k, "(absent)")
    return None


def algorithm_fields() -> List[Field]:
    """The :class:`DQMConfig` fields that :func:`add_algorithm` makes options of: the shared parameters in
    the order of the parameter text, then the others; not ``agents`` and ``seed``, which each command
    defines itself (``own_option`` metadata)."""
    fs = [f for f in fields(DQMConfig) if not f.metadata.get("own_option")]
    return sorted(fs, key=lambda f: (f.metadata["shared"] is None, f.metadata["shared"] or 0))


def config_args(cfg: DQMConfig) -> List[str]:
    """The command-line options that give a process ``cfg``'s configuration: the inverse of
    :func:`config_from` (``agents`` and ``seed``, each command's own options, are not among them).
    Values are written as ``--flag=VALUE`` (a job id may start with '-') and floats in full precision."""
    types = get_type_hints(DQMConfig)
    out = []
    for f in algorithm_fields():
        m, v = f.metadata, getattr(cfg, f.name)
        if "negation" in m:
            if v is not None:
                out.append(m["flag"] if v else m["negation"])
            continue
        text = repr(float(v)) if types[f.name] is float else str(v)
        out.append(f"{m['flag']}={text}")
    return out
