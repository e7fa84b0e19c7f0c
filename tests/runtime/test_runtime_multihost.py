"""A job across "hosts": network namespaces joined to a router namespace by veth pairs.

Router in its own namespace, 4 agents spread over 3 host namespaces, the
coordinator on host 1; traffic only between these namespaces' own addresses
(10.213.0.0/16). Skips with the reason where namespaces are not permitted.
"""
import shutil
import subprocess

import numpy as np
import pytest

from dqm import synthetic
from dqm.distributed import DQMConfig, simulate
from dqm.runtime.multihost import (
    Namespaces,
    NamespacesUnavailable,
    make_certs,
    netns_unavailable_reason,
    run_across_namespaces,
)


@pytest.fixture(scope="module")
def netns_ok():
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(f"multi-host test needs network namespaces: {reason}")


def _namespaces():
    return set(subprocess.run(["ip", "netns", "list"], capture_output=True, text=True).stdout.split())


def _run(ds, cfg, workdir, **kw):
    before = _namespaces()
    try:
        res = run_across_namespaces(ds.descriptors, ds.image_ids, cfg, workdir, hosts=3, timeout_s=60,
                                    tag=f"dqmt{np.random.randint(1 << 20)}", **kw)
    except NamespacesUnavailable as exc:
        pytest.skip(f"multi-host test needs network namespaces and veth pairs: {exc}")
    # every namespace we made is gone again
    assert not set(res.namespaces) & (_namespaces() - before)
    return res


def _check(res, ds, cfg, overhead, handshake=0):
    """``overhead``: the kernel's bytes over the metered ones (headers, acknowledgements); ``handshake``:
    bytes on top for each process's session that do not grow with the job (TLS: its certificates)."""
    rep = res.report
    assert rep["agent_exit_codes"] == [0] * cfg.agents  # every process exited cleanly
    assert set(res.placement.values()) == {0, 1, 2}  # agents really are spread over three hosts

    sim = simulate(ds.descriptors, ds.image_ids, cfg)
    assert np.array_equal(np.asarray(rep["ids"]), np.arange(len(ds.descriptors)))
    assert np.array_equal(np.asarray(rep["labels"]), sim.labels)

    # traffic was metered on every directed agent link and agrees with the kernel's veth counters
    links = {(e["src"], e["dst"]): e["bytes"] for e in rep["links"]}
    for a in range(cfg.agents):
        for b in range(cfg.agents):
            if a != b:
                assert links[(f"agent{a}", f"agent{b}")] > 0
    assert rep["kinds"]["features"]["bytes"] > ds.descriptors.shape[0] * ds.descriptors.shape[1] // 4
    assert not rep["rejected"]
    k = res.kernel_totals()
    total = rep["total_bytes"]
    # each message crosses the sender's veth into the router and the receiver's veth out of it
    fixed = handshake * len(res.placement)
    assert total <= k["to_router"] <= overhead * total + fixed, (k, total)
    assert total <= k["from_router"] <= overhead * total + fixed, (k, total)
    for h, m in res.metered_per_host().items():
        c = res.counters[h]
        # per host: the same, plus a few KiB of handshakes / declarations / keep-alives
        fixed = 8192 + handshake * sum(host == h for host in res.placement.values())
        assert m["sent"] <= c["rx_bytes"] <= overhead * m["sent"] + fixed, (h, m, c)
        assert m["received"] <= c["tx_bytes"] <= overhead * m["received"] + fixed, (h, m, c)


def test_job_across_namespaces_matches_simulator_and_kernel_counters(netns_ok, tmp_path):
    ds = synthetic.sift_like(n_images=6, n_points=200, seed=0)
    cfg = DQMConfig(agents=4, seed=1, job="multihost-test")
    res = _run(ds, cfg, tmp_path)
    _check(res, ds, cfg, overhead=1.10)  # the bound: kernel within 10% of the metered bytes


def test_mutual_tls_and_access_control_across_namespaces(netns_ok, tmp_path):
    if shutil.which("openssl") is None:
        pytest.skip("mutual-TLS test needs openssl to make certificates (not installed)")
    ds = synthetic.sift_like(n_images=5, n_points=150, seed=3)
    cfg = DQMConfig(agents=3, seed=2, partition="seeded", job="multihost-tls")
    router_names = [Namespaces().router_addr(h) for h in range(3)]
    certs = make_certs(tmp_path / "certs", router_names, [f"agent{a}" for a in range(3)] + ["coordinator"])
    res = _run(ds, cfg, tmp_path, tls_certs=certs, acl=True)  # the router enforces the job's roster
    # TLS records add a few percent, and each process's session its handshake (certificates both ways): at most
    # 8 KiB a process on top of the plain test's 10% (a fixed cost, a larger share of this small job's bytes
    # as the messages shrink)
    _check(res, ds, cfg, overhead=1.10, handshake=8192)


def test_namespaces_are_deleted_and_processes_killed_on_failure(netns_ok):
    nss = Namespaces(hosts=2, tag=f"dqmf{np.random.randint(1 << 20)}")
    proc = None
    with pytest.raises(RuntimeError, match="boom"):
        with nss:
            addrs = subprocess.run(["ip", "-n", nss.host_ns(0), "-4", "-o", "addr"], capture_output=True,
                                   text=True).stdout
            assert f"{nss.host_addr(0)}/24" in addrs
            proc = subprocess.Popen(nss.prefix(nss.host_ns(1)) + ["sleep", "60"])
            raise RuntimeError("boom")
    assert not {nss.router_ns, nss.host_ns(0), nss.host_ns(1)} & _namespaces()
    assert proc.wait(timeout=5) != 0  # killed, not left behind
