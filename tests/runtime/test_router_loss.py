"""An agent notices that its router is gone (issue 36: with the router stopped under it, an agent waiting for
its coordinator waited the whole --phase-timeout, 120 s, and then blamed the coordinator)."""
import signal
import subprocess
import sys
import time

from runtime_helpers import kill_all, wait_for_text

from dqm import io, synthetic
from dqm.runtime.launcher import free_port


def test_an_agent_waiting_for_its_coordinator_notices_the_router_is_gone(tmp_path):
    ds = synthetic.sized(200, seed=0)
    io.save_features(tmp_path / "f.npz", io.FeatureSet(ds.descriptors, ds.image_ids))
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    router_log, agent_log = tmp_path / "router.log", tmp_path / "agent.log"
    router = subprocess.Popen([sys.executable, "-m", "dqm", "router", "--listen", endpoint],
                              stdout=open(router_log, "w"), stderr=subprocess.STDOUT)
    agent = None
    try:
        wait_for_text(router_log, "listening", router)
        agent = subprocess.Popen([sys.executable, "-m", "dqm", "-v", "agent", "--id", "0", "--agents", "1",
                                  "--connect", endpoint, "--phase-timeout", "120", str(tmp_path / "f.npz")],
                                 stdout=subprocess.DEVNULL, stderr=open(agent_log, "w"))
        wait_for_text(agent_log, "waiting for the coordinator", agent)
        router.send_signal(signal.SIGTERM)
        router.wait(timeout=30)
        t = time.monotonic()
        agent.wait(timeout=60)
        took = time.monotonic() - t
    finally:
        kill_all((router, agent))
    text = agent_log.read_text()
    assert agent.returncode == 5, text
    assert "the zenoh router is gone" in text and endpoint in text and "Traceback" not in text
    assert took < 10, f"the agent took {took:.1f} s to notice"
