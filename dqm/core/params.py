"""The QuickMatch parameter vocabulary, defined and validated once.

Every engine reads the same four parameters from one :class:`QuickMatchParams`:
batch :func:`dqm.quickmatch` / :class:`dqm.QuickMatch`, online
:class:`dqm.core.online.OnlineQuickMatch`, and a distributed job
(:class:`dqm.distributed.DQMConfig` holds one).

The kernel story, in one place: the batch engine defaults to the reference
code's Gaussian kernel (:data:`DEFAULT_KERNEL`). The online and distributed
engines need a kernel of finite support, so that an update or a cell can finish
a density from the features within reach; they take only the quadratic kernel
(:data:`FINITE_KERNEL`) and say so when given another. Each result carries the
:class:`QuickMatchParams` it ran with, and the exactness contract is stated
against them: ``quickmatch(X, ids, **result.params.as_kwargs())`` gives the
same labels as the online or distributed run that produced ``result``.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields, replace
from typing import Dict

from .. import validation as V

KERNELS = ("gaussian", "quadratic")
PARENT_MODES = ("any", "other-image")
#: default merge ratio, chosen by the sweep in scripts/sweep_rho.py (docs/quickmatch.md)
DEFAULT_RHO = 0.9
DEFAULT_RATIO_DENSITY = 0.25
#: the batch engine's default kernel (the reference code's)
DEFAULT_KERNEL = "gaussian"
#: the one kernel the online and distributed engines take (finite support)
FINITE_KERNEL = "quadratic"
DEFAULT_PARENT = "any"


@dataclass(frozen=True)
class QuickMatchParams:
    """What a QuickMatch clustering depends on (besides the input), validated by :meth:`validated`.

    ``rho``: merge ratio, an edge merges iff shorter than ``rho * min(scale)``;
    ``kernel``: ``"gaussian"`` or ``"quadratic"``; ``parent``: ``"any"`` or
    ``"other-image"`` (the parent must come from another image);
    ``ratio_density``: Gaussian bandwidth as a fraction of sigma (the quadratic
    kernel ignores it).
    """

    rho: float = field(default=DEFAULT_RHO, metadata={"help": "merge ratio: an edge merges iff shorter than "
                                                              "rho * min(scale)"})
    kernel: str = field(default=DEFAULT_KERNEL, metadata={"help": "density kernel", "choices": KERNELS})
    parent: str = field(default=DEFAULT_PARENT, metadata={"help": "any, or other-image (the parent must come "
                                                                  "from another image)", "choices": PARENT_MODES})
    ratio_density: float = field(default=DEFAULT_RATIO_DENSITY,
                                 metadata={"help": "Gaussian bandwidth as a fraction of sigma"})

    def validated(self, finite: bool = False, engine: str = "") -> "QuickMatchParams":
        """Self, after checking every field (one clear line naming the field); ``finite``: the engine
        (named ``engine``) needs the quadratic kernel."""
        V.check_positive(self.rho, "rho")
        V.check_choice(self.kernel, "kernel", KERNELS)
        V.check_choice(self.parent, "parent", PARENT_MODES)
        V.check_positive(self.ratio_density, "ratio_density")
        if finite and self.kernel != FINITE_KERNEL:
            raise V.InputError(f"{engine or 'this engine'} needs the finite kernel (kernel={FINITE_KERNEL!r}), "
                               f"got {self.kernel!r}: a Gaussian kernel reaches every feature, so no part of the "
                               f"data could finish a density on its own")
        return self

    def but(self, **changes) -> "QuickMatchParams":
        return replace(self, **changes)

    def as_kwargs(self) -> Dict[str, object]:
        """The fields as keyword arguments of :func:`dqm.quickmatch`."""
        return asdict(self)

    @classmethod
    def names(cls) -> tuple:
        return tuple(f.name for f in fields(cls))
