"""Package roots that load their public names, and their submodules, on first use (PEP 562).

``dqm``, ``dqm.core`` and ``dqm.distributed`` use it so that a command's start-up imports what
the command runs and nothing else (tests/cli/test_start_up.py)."""
from __future__ import annotations

import importlib
from typing import Callable, Dict, List, Tuple


def lazy_exports(package: str, public: Dict[str, str]) -> Tuple[Callable[[str], object], Callable[[], List[str]]]:
    """``__getattr__`` and ``__dir__`` for ``package``: a name of ``public`` (name -> the relative module that
    defines it) is imported when first read, and any other name as a submodule of ``package``."""
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        if name in public:
            value = getattr(importlib.import_module(public[name], package), name)
        else:
            try:
                value = importlib.import_module(f".{name}", package)
            except ModuleNotFoundError as exc:
                if exc.name != f"{package}.{name}":
                    raise  # the submodule exists; something it imports is missing
                raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        namespace[name] = value
        return value

    def __dir__() -> List[str]:
        return sorted(set(namespace) | set(public))

    return __getattr__, __dir__
