"""The QuickMatch parameters as command-line options, generated from :class:`dqm.core.params.QuickMatchParams`.

Every command that takes ``--rho``, ``--kernel``, ``--parent`` or ``--ratio-density``
(dqm match / sfm, dqm stream, dqm demo) adds them here, so that each parameter's
flag, help, choices and default are defined once (in the field's metadata and
default). The distributed commands' options come from :class:`dqm.distributed.DQMConfig`
(:mod:`dqm.commands.runtime_options`), whose rho and kernel share that vocabulary.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Dict, Iterable, Optional, get_type_hints

from ..core.params import DEFAULT_KERNEL, QuickMatchParams


def flag(name: str) -> str:
    """The command-line option of a QuickMatch parameter: ``ratio_density`` -> ``--ratio-density``."""
    return "--" + name.replace("_", "-")


def add_quickmatch_params(p, names: Optional[Iterable[str]] = None, kernel_default: str = DEFAULT_KERNEL,
                          notes: Optional[Dict[str, str]] = None,
                          number_type: Optional[Callable[[str], float]] = None) -> None:
    """Add the options of the QuickMatch parameters ``names`` (default: all four, in
    :class:`QuickMatchParams` order) to the parser or argument group ``p``.

    Help, choices and default come from the field (``kernel_default`` replaces the kernel's: the online
    and distributed commands use the finite one); ``notes``: text added to a parameter's help, for what
    is particular to the command; ``number_type``: the argparse type of the numeric parameters (default:
    the field's type, float). The parsed values land in ``args.<name>``."""
    types = get_type_hints(QuickMatchParams)
    by_name = {f.name: f for f in dataclasses.fields(QuickMatchParams)}
    for name in (QuickMatchParams.names() if names is None else names):
        f = by_name[name]
        help_text = f.metadata["help"] + (notes or {}).get(name, "")
        kw = {"dest": name, "default": kernel_default if name == "kernel" else f.default, "help": help_text}
        if f.metadata.get("choices"):
            kw["choices"] = f.metadata["choices"]
        elif types[name] in (int, float):
            kw["type"] = number_type or types[name]
        p.add_argument(flag(name), **kw)
