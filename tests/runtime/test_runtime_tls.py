"""Mutual TLS on loopback: certificates made by deploy/make-certs.sh (openssl) in a temporary
folder, a `dqm router` on tls/127.0.0.1:PORT, agents and the coordinator with their own
client certificates; a client without a valid certificate is refused, quickly and clearly."""
import shutil
import subprocess
import sys
import time

import numpy as np
import pytest

from dqm import synthetic
from dqm.distributed import DQMConfig, simulate
from dqm.runtime.launcher import START_LIMITS, Processes, free_port, write_agent_files
from dqm.runtime.multihost import finish_job, make_certs, start_job, start_router
from dqm.runtime.multihost import tls_options as tls_args

M = 3


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    if shutil.which("openssl") is None:
        pytest.skip("mutual-TLS test needs openssl to make certificates (not installed)")
    if shutil.which("sh") is None:
        pytest.skip("mutual-TLS test needs a POSIX sh to run deploy/make-certs.sh")
    ours = make_certs(tmp_path_factory.mktemp("certs"), ["127.0.0.1", "localhost"],
                      [f"agent{a}" for a in range(M)] + ["coordinator"])
    other = make_certs(tmp_path_factory.mktemp("other-ca"), ["127.0.0.1"], ["intruder"])
    return ours, other


@pytest.fixture(scope="module")
def tls_router(certs, tmp_path_factory):
    ours, _ = certs
    wd = tmp_path_factory.mktemp("tls-router")
    port = free_port()
    procs = Processes()
    try:
        router = start_router(procs, [f"tls/127.0.0.1:{port}"], wd, ("127.0.0.1", port),
                              tls_args=tls_args(ours, "router"))
        yield {"port": port, "endpoint": f"tls/127.0.0.1:{port}", "proc": router, "workdir": wd}
    finally:
        procs.stop_all()


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    ds = synthetic.sift_like(n_images=6, n_points=200, seed=0)
    wd = tmp_path_factory.mktemp("tls-job")
    return ds, write_agent_files(ds.descriptors, ds.image_ids, M, wd), wd


def _client(args, timeout=30):
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "dqm", *args], capture_output=True, text=True, timeout=timeout)
    return r, time.monotonic() - t0


@pytest.mark.parametrize("who", ["no-certificate", "certificate-of-another-ca", "another-ca-everywhere",
                                 "plain-tcp", "coordinator-of-another-ca"])
def test_client_without_valid_certificate_is_refused(who, certs, tls_router, data):
    ours, other = certs
    _, files, _ = data
    port = tls_router["port"]
    ep = tls_router["endpoint"]
    agent = ["agent", "--id", "0", "--agents", str(M), "--job", "tls", "--connect-timeout", "1"]
    args = {
        "no-certificate": agent + ["--connect", ep, str(files[0])],
        "certificate-of-another-ca": agent + ["--connect", ep, "--tls-ca", str(ours / "ca.pem"),
                                              "--tls-cert", str(other / "intruder.pem"),
                                              "--tls-key", str(other / "intruder.key"), str(files[0])],
        "another-ca-everywhere": agent + ["--connect", ep, *tls_args(other, "intruder"), str(files[0])],
        "plain-tcp": agent + ["--connect", f"tcp/127.0.0.1:{port}", str(files[0])],
        "coordinator-of-another-ca": ["coordinator", "--agents", str(M), "--job", "tls", "--connect", ep,
                                      "--connect-timeout", "1", *tls_args(other, "intruder")],
    }[who]
    r, took = _client(args)
    assert r.returncode == 2, r.stderr
    assert took < 15, f"refusal took {took:.1f} s"
    assert "error: no zenoh router reachable at" in r.stderr
    if who == "plain-tcp":
        assert "did not open a tcp zenoh session" in r.stderr, r.stderr
    else:
        assert "refused the TLS session" in r.stderr, r.stderr
    assert tls_router["proc"].poll() is None, "the router must survive refused clients"


def test_mutual_tls_job_matches_simulator(certs, tls_router, data):
    ours, _ = certs
    ds, files, wd = data
    cfg = DQMConfig(agents=M, seed=2, job="tls-job")
    procs = Processes()
    try:
        job = start_job(procs, cfg, files, wd, connect=lambda a: tls_router["endpoint"],
                        client_args=lambda a: tls_args(ours, "coordinator" if a < 0 else f"agent{a}"),
                        limits=START_LIMITS.but(job_timeout_s=60))
        rep = finish_job(job, 60)
    finally:
        procs.stop_all()
    assert rep["agent_exit_codes"] == [0] * M
    sim = simulate(ds.descriptors, ds.image_ids, cfg)
    assert np.array_equal(np.asarray(rep["labels"]), sim.labels)
    assert rep["total_bytes"] > 0 and not rep["rejected"]
    assert tls_router["proc"].poll() is None
