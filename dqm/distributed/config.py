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
"""
from __future__ import annotations

import hashlib
from dataclasses import dataclass, replace
from typing import Dict, Optional, Tuple

from ..core.clustering import DEFAULT_RHO, KERNELS
from ..validation import InputError, check_choice, check_positive
from . import partition

MODES = ("balanced", "lean", "paper")
DEFAULT_MODE = "balanced"
GHOST_RULES = ("one-way", "two-way")
#: the default partition seed integer (every command and DQMConfig)
DEFAULT_SEED = 1
#: the default dimension of the lower-bound sketches (docs/distributed.md, frontier table)
DEFAULT_SKETCH_DIMS = 48
#: the parameters every process of a job must share (they change the result or the protocol); the
#: seed integer is not among them (the coordinator broadcasts it) nor the job id (it names the key space)
SHARED_PARAMS = ("agents", "mode", "partition", "kernel", "rho", "halo", "samples_per_agent", "seed_norm",
                 "cell_weights", "ghost_rule", "sketch_dims", "balance_rounds")


def _check_int(value, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise InputError(f"{name} must be an integer >= {low}, got {value!r}")
    return value


@dataclass(frozen=True)
class DQMConfig:
    """Parameters of a distributed job.

    ``agents``, ``seed`` (the one partition integer), ``partition`` (``kmeans``:
    k-means on a sample pooled at agent 0; ``seeded``: seeds from the integer
    alone), ``mode`` (see the module doc), ``rho``, ``kernel``,
    ``samples_per_agent`` (descriptors each agent sends to agent 0 for the
    seeds, the cell weights and the sketch basis), ``halo`` (lean/paper:
    contested-test width, 1 = safe), ``seed_norm`` (seeded seeds' norm),
    ``job`` (keeps concurrent jobs apart), ``cell_weights`` (power-diagram
    weights that balance the cells; None = on in balanced mode only),
    ``ghost_rule`` (balanced: ``one-way`` ships each cross-cell pair one way;
    ``two-way`` is the plain bisector halo, for comparison), ``sketch_dims``
    (balanced: dimension of the lower-bound sketch pre-filter, 0 = off) and
    ``balance_rounds`` (most weight-refinement rounds on the full counts).
    """

    agents: int
    seed: int = DEFAULT_SEED
    partition: str = "kmeans"
    mode: str = DEFAULT_MODE
    rho: float = DEFAULT_RHO
    kernel: str = "quadratic"
    samples_per_agent: int = 64
    halo: float = 1.0
    seed_norm: float = 512.0
    job: str = "job"
    cell_weights: Optional[bool] = None
    ghost_rule: str = "one-way"
    sketch_dims: int = DEFAULT_SKETCH_DIMS
    balance_rounds: int = 12

    @property
    def weighted(self) -> bool:
        """Whether the cells get power-diagram weights."""
        return self.mode == "balanced" if self.cell_weights is None else bool(self.cell_weights)

    @property
    def source_sigma(self) -> bool:
        """Whether sigma is computed at the source (exact) rather than per cell (paper)."""
        return self.mode != "paper"

    @property
    def needs_sample(self) -> bool:
        """Whether agents send descriptor samples to agent 0 at set-up."""
        return self.partition == "kmeans" or self.weighted or (self.mode == "balanced" and self.sketch_dims > 0)

    def validated(self, n_features: Optional[int] = None) -> "DQMConfig":
        partition.check_agents(self.agents, n_features)
        partition.check_seed(self.seed)
        check_choice(self.partition, "partition", partition.PARTITION_MODES)
        check_choice(self.mode, "mode", MODES)
        check_choice(self.kernel, "kernel", KERNELS)
        check_choice(self.ghost_rule, "ghost_rule", GHOST_RULES)
        check_positive(self.rho, "rho")
        check_positive(self.halo, "halo")
        check_positive(self.seed_norm, "seed_norm")
        _check_int(self.samples_per_agent, "samples_per_agent", 1)
        _check_int(self.sketch_dims, "sketch_dims", 0)
        _check_int(self.balance_rounds, "balance_rounds", 0)
        if self.cell_weights is not None and not isinstance(self.cell_weights, bool):
            raise InputError(f"cell_weights must be True, False or None, got {self.cell_weights!r}")
        if self.mode == "balanced" and self.kernel != "quadratic":
            raise InputError("balanced mode needs the finite quadratic kernel (kernel='quadratic'): the Gaussian "
                             "kernel has unbounded support, so no cell could finish a density on its own")
        return self

    def but(self, **changes) -> "DQMConfig":
        """A copy with some fields changed."""
        return replace(self, **changes)

    def params_text(self) -> str:
        """The shared parameters as ``name=value;...`` (the start message carries it and its hash)."""
        return ";".join(f"{k}={getattr(self, k)!r}" for k in SHARED_PARAMS)


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
