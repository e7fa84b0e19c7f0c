import compileall
import os
from pathlib import Path

import numpy as np
import pytest


def pytest_configure(config):
    """Byte-compile the package once: the suite starts hundreds of dqm processes, and where
    PYTHONDONTWRITEBYTECODE is set (as in this project's sandboxes and CI) each of them would
    otherwise compile every module it imports from source again (about 0.2 s of every start-up;
    cached .pyc files are read whatever that variable says). Under pytest-xdist the controller
    compiles before its workers start; they find it done.

    Tests that call pycolmap themselves, before any dqm command set COLMAP's log up in their process
    (:func:`dqm.vision.colmap.require_pycolmap`), would have glog write a log file into the temporary
    folder at each run: glog reads GLOG_logtostderr when pycolmap loads, so it is set here first."""
    os.environ.setdefault("GLOG_logtostderr", "1")
    if hasattr(config, "workerinput"):
        return
    compileall.compile_dir(Path(__file__).resolve().parents[1] / "dqm", quiet=1)

#: the shared real data (Oxford sequences, CMU hotel), next to the project checkout
SHARED = Path(os.environ.get("DQM_SHARED", Path(__file__).resolve().parents[1].parent / "shared"))
DATA = SHARED / "data"


def require_data(*parts: str) -> Path:
    """Path under ../shared/data, or skip the test with the reason."""
    p = DATA.joinpath(*parts)
    if not p.exists():
        pytest.skip(f"real data not available: {p} is absent (set DQM_SHARED to the shared folder)")
    return p


def assert_consistent(labels, image_ids):
    """C1: every feature has exactly one cluster; C2: at most one feature per image per cluster."""
    labels = np.asarray(labels)
    image_ids = np.asarray(image_ids)
    assert labels.shape == image_ids.shape
    assert labels.dtype.kind == "i"
    assert (labels >= 0).all()
    if len(labels):
        # canonical numbering 0..k-1, every id used
        assert set(np.unique(labels).tolist()) == set(range(labels.max() + 1))
        pairs = np.unique(np.stack([labels, image_ids]), axis=1)
        assert pairs.shape[1] == len(labels), "a cluster holds two features of one image (C2)"


@pytest.fixture(scope="session")
def graf_sift():
    """SIFT descriptors (OpenCV defaults) of all six graf images: (descriptors, image_ids)."""
    root = require_data("oxford", "graf")
    import cv2

    sift = cv2.SIFT_create()
    descs, ids = [], []
    for k in range(1, 7):
        img = cv2.imread(str(root / f"img{k}.png"), cv2.IMREAD_GRAYSCALE)
        _, d = sift.detectAndCompute(img, None)
        descs.append(d)
        ids.append(np.full(len(d), k))
    return np.vstack(descs), np.concatenate(ids)


@pytest.fixture(scope="module")
def router():
    """A zenoh router process on a free loopback port (one per test module): its endpoint."""
    pytest.importorskip("zenoh")
    from runtime_helpers import start_dqm

    from dqm.runtime.launcher import free_port, wait_listening

    port = free_port()
    p = start_dqm(["router", "--listen", f"tcp/127.0.0.1:{port}"])
    try:
        wait_listening("127.0.0.1", port, 15.0, p)
        yield f"tcp/127.0.0.1:{port}"
    finally:
        p.terminate()
        p.wait(timeout=10)
