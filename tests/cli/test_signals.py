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
    rng = np.random.default_rng(0)
    n = 400_000  # about 8e10 pairs: minutes of work on two cores, the pass is surely running at the signal
    X = rng.integers(0, 64, size=(n, 128), dtype=np.uint8)
    feats = tmp_path / "f.npz"
    dqm_io.save_features(feats, dqm_io.FeatureSet(X, np.arange(n) % 200))
    out = tmp_path / "c.npz"
    p = subprocess.Popen([sys.executable, "-m", "dqm", "match", str(feats), "--out", str(out), "--quiet"],
                         stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        time.sleep(6)
        assert p.poll() is None, p.communicate()[0]
        t = time.monotonic()
        p.send_signal(signal.SIGTERM)
        text, _ = p.communicate(timeout=60)
        waited = time.monotonic() - t
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    assert p.returncode == 143, text
    assert "terminated" in text and "Traceback" not in text
    assert waited < 15, f"the process took {waited:.1f} s to end after SIGTERM"
    assert not out.exists()
