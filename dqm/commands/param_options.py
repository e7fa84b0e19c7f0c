"""The QuickMatch parameters as command-line options, generated from :class:`dqm.core.params.QuickMatchParams`.

Every command that takes ``--rho``, ``--kernel``, ``--parent`` or ``--ratio-density``
(dqm match / sfm, dqm stream, dqm demo) adds them here, so that each parameter's
flag, help, choices and default are defined once (in the field's metadata and
default). The distributed commands' options come from :class:`dqm.distributed.DQMConfig`
(:mod:`dqm.commands.runtime_options`), whose rho and kernel share that vocabulary.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Dict, Iterable, Optional, Sequence, get_type_hints

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
        add_field_option(p, f, types[name], flag(name), default=kernel_default if name == "kernel" else f.default,
                         help_text=f.metadata["help"] + (notes or {}).get(name, ""), number_type=number_type)


def add_field_option(p, f: dataclasses.Field, type_hint, option: str, *, default, help_text: str,
                     aliases: Sequence[str] = (), metavar: Optional[str] = None,
                     number_type: Optional[Callable[[str], float]] = None) -> None:
    """The option ``option`` (and ``aliases``) of the dataclass field ``f`` (annotated ``type_hint``): its
    ``choices`` metadata, else its numeric type (``number_type`` instead, where given) and ``metavar``;
    the value lands in ``args.<field name>``. The one place where parameter objects become options
    (:func:`add_quickmatch_params`, :func:`dqm.commands.runtime_options.add_algorithm`)."""
    kw = {"dest": f.name, "default": default, "help": help_text}
    if f.metadata.get("choices"):
        kw["choices"] = f.metadata["choices"]
    else:
        if metavar is not None:
            kw["metavar"] = metavar
        if type_hint in (int, float):
            kw["type"] = number_type or type_hint
    p.add_argument(option, *aliases, **kw)
