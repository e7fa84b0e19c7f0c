"""Check this installation: the tile kernel, the optional and required libraries, the shared data.

Prints one line per check and exits with 0 when everything required works
(1 otherwise). Optional parts (faiss for --approximate; pycolmap and h5py, the
``dqm[colmap]`` extra, for ``dqm export colmap`` / ``dqm import colmap`` and
hloc files; the shared real data for the evaluations) are reported with their
versions but not required.

    dqm doctor
"""
from __future__ import annotations

import importlib
import os
from pathlib import Path

NAME = "doctor"
HELP = "check the installation: native kernel, zenoh, OpenCV, faiss, pycolmap, h5py, shared data"


def add_arguments(p) -> None:
    p.add_argument("--data", default=None, metavar="DIR",
                   help="the shared data folder (default: $DQM_SHARED/data or ../shared/data beside the checkout)")


def _module(name: str):
    try:
        mod = importlib.import_module(name)
    except Exception as exc:  # noqa: BLE001 - any import failure is the finding
        return None, f"not importable ({type(exc).__name__}: {exc})"
    return mod, getattr(mod, "__version__", "installed")


def _checks(data_dir: Path):
    from .. import __version__
    from ..core import native

    yield "dqm", True, True, __version__
    yield "tile kernel", native.native_available(), False, native.kernel_description()
    yield "BLAS (the pass's GEMMs)", True, False, native.blas_description()
    for name, module, required in (("numpy", "numpy", True), ("scipy", "scipy", True),
                                   ("OpenCV", "cv2", True), ("eclipse-zenoh", "zenoh", True),
                                   ("msgpack", "msgpack", True), ("matplotlib", "matplotlib", True),
                                   ("faiss-cpu (--approximate)", "faiss", False),
                                   ("pycolmap (dqm[colmap]: dqm export / import colmap)", "pycolmap", False),
                                   ("h5py (dqm[colmap]: dqm import h5, hloc feature files)", "h5py", False)):
        mod, text = _module(module)
        if module == "cv2" and mod is not None:
            text = f"{mod.__version__}, SIFT {'available' if hasattr(mod, 'SIFT_create') else 'MISSING'}"
        yield name, mod is not None, required, text
    sets = ["oxford/graf", "oxford/wall", "oxford/boat", "oxford/bikes", "cmu_hotel", "sacre_coeur"]
    found = [s for s in sets if (data_dir / s).exists()]
    yield "shared data", len(found) == len(sets), False, (
        f"{data_dir}: {len(found)} of {len(sets)} sets" + (f" (missing: {', '.join(s for s in sets if s not in found)})"
                                                          if len(found) < len(sets) else ""))


def run(args) -> int:
    default = Path(os.environ.get("DQM_SHARED", Path(__file__).resolve().parents[3] / "shared")) / "data"
    data_dir = Path(args.data) if args.data else default
    failed = 0
    for name, ok, required, text in _checks(data_dir):
        mark = "ok" if ok else ("FAIL" if required else "--")
        failed += (not ok) and required
        print(f"{mark:4} {name}: {text}")
    print("everything required works" if not failed else f"{failed} required part(s) missing")
    return 0 if not failed else 1
