"""A long `dqm match` ends promptly on SIGTERM: the all-pairs pass drops the tiles not yet started
(ThreadPoolExecutor.map queues every tile at once; waiting for them kept a terminated process
computing the whole pass)."""
import signal
import subprocess
import sys
import time

import numpy as np

from dqm import io as dqm_io


def test_sigterm_during_the_pass_ends_dqm_match_within_seconds(tmp_path):
    from runtime_helpers import wait_for_text

    rng = np.random.default_rng(0)
    n = 150_000  # about 1.1e10 pairs: a minute of work on two cores, the pass is surely running at the signal
    X = rng.integers(0, 64, size=(n, 128), dtype=np.uint8)
    feats = tmp_path / "f.npz"
    dqm_io.save_features(feats, dqm_io.FeatureSet(X, np.arange(n) % 200))
    out, log = tmp_path / "c.npz", tmp_path / "log.txt"
    with open(log, "w") as fh:
        p = subprocess.Popen([sys.executable, "-m", "dqm", "-v", "match", str(feats), "--out", str(out), "--quiet"],
                             stdout=fh, stderr=subprocess.STDOUT, text=True)
    try:
        wait_for_text(log, "sigma (nearest other feature", p)  # -v: the pass starts next
        time.sleep(0.5)
        assert p.poll() is None, log.read_text()
        t = time.monotonic()
        p.send_signal(signal.SIGTERM)
        p.wait(timeout=60)
        waited = time.monotonic() - t
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    text = log.read_text()
    assert p.returncode == 143, text
    assert "terminated" in text and "Traceback" not in text and "kernel pass (densities" not in text
    assert waited < 15, f"the process took {waited:.1f} s to end after SIGTERM"
    assert not out.exists()
