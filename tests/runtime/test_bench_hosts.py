"""Emulated hosts (network namespaces in CPU quotas, links capped with tc tbf): every mode of
scripts/bench_hosts.py gives its documented result through them (a small version: 2 hosts, one rate)."""
import subprocess
from pathlib import Path

import numpy as np
import pytest
from script_modules import load_script

from dqm import evaluation, synthetic
from dqm.distributed import DQMConfig
from dqm.runtime.launcher import Processes, write_agent_files
from dqm.runtime.multihost import (
    ROUTER_PORT,
    EmulatedHosts,
    NamespacesUnavailable,
    _wait_ready_file,
    netns_unavailable_reason,
    run_on_hosts,
    start_router,
)

pytest.importorskip("zenoh")

#: the cores the auto job with probes says agent 0's host gives a gathering match
BIG_GATHER_CORES = 0.1


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(f"emulated hosts need network namespaces: {reason}")
    ds = synthetic.sift_like(n_images=4, n_points=250, seed=5)
    wd = tmp_path_factory.mktemp("hosts")
    files = write_agent_files(ds.descriptors, ds.image_ids, 2, wd)
    cfg = DQMConfig(agents=2, seed=1, job="hosts-test").validated(len(ds.descriptors))
    out = {"n": len(ds.descriptors)}
    try:
        with EmulatedHosts(hosts=2, rate_mbit=100, cpu_cores=1.0, tag=f"dqmh{np.random.randint(1 << 16)}") as nss:
            qdisc = subprocess.run(["ip", "netns", "exec", nss.host_ns(0), "tc", "qdisc", "show", "dev", "eth0"],
                                   capture_output=True, text=True).stdout
            out["settings"] = (qdisc, (nss.cgroup(1) / "cpu.cfs_quota_us").read_text().strip())
            out["cgroups"] = list(nss.cgroups)
            procs = Processes()
            try:
                start_router(procs, [f"tcp/{nss.router_addr(h)}:{ROUTER_PORT}" for h in range(2)], wd,
                             _wait_ready_file, prefix=nss.prefix(nss.router_ns))
                for mode in ("gather", "balanced", "lean", "auto"):
                    out[mode] = run_on_hosts(nss, mode, cfg, files, wd, timeout_s=120)
                # a job whose best mode turns on the link rate (agent 0's host gives a gathering match a tenth
                # of a core: gather on slow links, balanced on fast ones): auto times the links
                big = synthetic.sift_like(n_images=4, n_points=2000, seed=6)
                out["big"] = big
                big_files = write_agent_files(big.descriptors, big.image_ids, 2, wd / "big")
                big_cfg = DQMConfig(agents=2, seed=1, job="hosts-test-big").validated(len(big.descriptors))
                out["auto-big"] = run_on_hosts(nss, "auto", big_cfg, big_files, wd / "big", timeout_s=120,
                                               gather_cores=BIG_GATHER_CORES)
            finally:
                procs.stop_all()
    except NamespacesUnavailable as exc:
        pytest.skip(f"emulated hosts cannot be built here: {exc}")
    return out


def test_hosts_get_their_cpu_quota_and_link_rate_and_leave_nothing(runs):
    qdisc, quota = runs["settings"]
    assert "tbf" in qdisc and "100Mbit" in qdisc
    assert quota == "100000"  # one core per host
    assert not any(cg.exists() for cg in runs["cgroups"])


def test_gather_and_balanced_give_the_same_clusters_and_lean_is_scored(runs):
    g, b, lean = runs["gather"], runs["balanced"], runs["lean"]
    assert len(g.ids) == runs["n"] and np.array_equal(g.ids, b.ids) and np.array_equal(g.ids, lean.ids)
    assert evaluation.comembership_scores(b.labels, g.labels).f1 == 1.0
    assert len(np.unique(b.labels)) == len(np.unique(g.labels))
    assert evaluation.comembership_scores(lean.labels, g.labels).f1 >= 0.99


def test_gather_moves_about_one_copy_and_balanced_more(runs):
    raw = runs["n"] * 128
    # gather ships the features of the one other host: about half of them, once
    assert 0.4 * raw < runs["gather"].bytes < 0.7 * raw
    assert runs["balanced"].bytes > runs["gather"].bytes
    assert all(runs[m].seconds > 0 for m in ("gather", "balanced", "lean"))


def test_auto_picks_without_probes_where_the_size_decides_and_gives_its_clusters(runs):
    a, g = runs["auto"], runs["gather"]
    # 1000 features on 2 hosts: agent 0 gathering the other's half is the fastest at every link rate
    assert a.detail["picked"] == "gather" and a.detail["probe_s"] == 0 and a.detail["rates_mbit"] == {}
    assert np.array_equal(a.ids, g.ids) and evaluation.comembership_scores(a.labels, g.labels).f1 == 1.0


def test_auto_measures_the_links_picks_a_mode_and_gives_its_clusters(runs):
    import dqm
    from dqm.distributed import costmodel

    a, big = runs["auto-big"], runs["big"]
    job = costmodel.JobShape(n=len(big.descriptors), agents=2, dim=128)

    def hosts(rates):
        return costmodel.Hosts.of(rates, 1.0, gather_cores=BIG_GATHER_CORES,
                                  kernel_cpu_s=a.detail["coordinator_kernel_cpu_s"])

    # agent 0's host gives a gathering match a tenth of a core: at this job's size, with the pair rate the
    # coordinator measured (on this machine: the links are timed), no mode is within 10% of the fastest at every rate
    clear = costmodel.rate_free_choice(job, lambda r: hosts([r, r]))
    assert a.detail["picked"] in ("gather", "balanced", "lean")
    ref = dqm.quickmatch(big.descriptors, big.image_ids, kernel="quadratic").labels
    assert np.array_equal(a.ids, np.arange(len(big.descriptors)))
    assert evaluation.comembership_scores(a.labels, ref).f1 >= (0.99 if a.detail["picked"] == "lean" else 1.0)
    if clear is not None:  # a machine whose pair rate puts one mode ahead at every rate: no probes
        assert a.detail["picked"] == clear[0] and a.detail["probe_s"] == 0 and a.detail["rates_mbit"] == {}
        return
    rates = a.detail["rates_mbit"]
    assert 0 < a.detail["probe_s"] < 5 and a.detail["job_s"] >= a.detail["probe_s"]
    settled = costmodel.settled_above(job, lambda r: hosts([r, r]))
    if len(a.detail["rates_at_least"]) == 2:  # every link shown fast enough for the mode settled above some rate
        floor, mode, _ = settled
        assert a.detail["picked"] == mode
        assert all(floor * costmodel.SETTLED_MARGIN <= r * 1e6 / 8 and r < 200 for r in rates.values()), rates
        return
    # the links are capped at 100 Mbit/s: the probes see about that, and the pick is the model's at those rates
    assert all(50 < r < 200 for p, r in rates.items() if p not in a.detail["rates_at_least"]), rates
    assert costmodel.choose(job, hosts([rates["0"] * 1e6 / 8, rates["1"] * 1e6 / 8])).mode == a.detail["picked"]


def _bench_script():
    return load_script("bench_hosts")


def test_the_table_says_what_auto_picked_and_its_time_over_the_best():
    bench = _bench_script()
    base = {"data": "d", "n": 10, "m": 2, "rate_mbit": 100.0, "bytes_over_raw": 1.0}
    rows = [dict(base, mode="gather", seconds=4.0, gather_s=1.0, match_s=2.0),
            dict(base, mode="gather-approx", seconds=1.0, gather_s=0.5, match_s=0.2),
            dict(base, mode="balanced", seconds=2.0, job_s=1.0),
            dict(base, mode="auto", seconds=2.5, job_s=1.2, picked="balanced"),
            dict(base, rate_mbit=10.0, mode="auto", seconds=9.0, error="lost")]
    lines = bench.table(rows).splitlines()
    assert lines[0].endswith("| auto picked | auto / best |")
    auto = next(ln for ln in lines if "| auto | 2.5 |" in ln)
    assert auto.endswith("| balanced | 1.25 |")  # over balanced's 2.0: gather-approx is not among the picks
    assert all(ln.count("|") == lines[0].count("|") for ln in lines)


def test_repeated_runs_take_turns_and_each_row_is_the_run_of_median_time(tmp_path):
    """--repeats: every mode runs that many times at a rate, the rounds starting one mode further on (no mode
    always first); each row is the run of median time (of two, the faster) and lists every run's time."""
    reason = netns_unavailable_reason()
    if reason:
        pytest.skip(f"emulated hosts need network namespaces: {reason}")
    bench = _bench_script()
    ds = synthetic.sift_like(n_images=4, n_points=250, seed=5)
    rows, lines, saved = [], [], []
    try:
        bench.bench("small", ds.descriptors, ds.image_ids, 2, [100.0], ["gather", "auto"], tmp_path, 120.0,
                    lines.append, rows, lambda: saved.append(len(rows)), repeats=2)
    except NamespacesUnavailable as exc:
        pytest.skip(f"emulated hosts cannot be built here: {exc}")
    order = [ln.split(" Mbit/s ")[1].split()[0].rstrip(":") for ln in lines]
    assert order == ["gather", "auto", "auto", "gather"], lines
    # saved after every run, the rows of the runs so far (a long benchmark keeps what it measured)
    assert [r["mode"] for r in rows] == ["gather", "auto"] and saved == [1, 2, 2, 2]
    for r in rows:
        assert len(r["runs_s"]) == 2 and r["seconds"] == min(r["runs_s"]) and "error" not in r
    gather, auto = rows
    assert auto["picked"] == "gather" and auto["identical"]
    assert auto["speedup_over_gather"] == pytest.approx(gather["seconds"] / auto["seconds"])


def test_outputs_are_refused_before_any_work_and_the_rows_file_is_this_runs(tmp_path, capsys):
    """--json and --figure: an existing file is refused in one line (exit 2) before anything runs, unless
    --overwrite; the rows file is taken by its first write and replaced by the later ones (no temporary left)."""
    from dqm import outputs

    bench = _bench_script()
    rows = tmp_path / "rows.json"
    rows.write_text("[]")
    for option in ("--json", "--figure"):
        taken = tmp_path / ("taken.json" if option == "--json" else "taken.png")
        taken.write_text("mine")
        assert bench.main(["--table-from", str(rows), option, str(taken)]) == 2
        err = capsys.readouterr().err.strip()
        assert err == f"bench_hosts: {option} {taken} exists; pass --overwrite to replace it, or name another file"
        assert taken.read_text() == "mine"
    fig = tmp_path / "rows.png"
    measured = str(Path(__file__).resolve().parents[2] / "docs" / "bench_hosts_200k_fast.json")
    assert bench.main(["--table-from", measured, "--figure", str(fig)]) == 0 and fig.stat().st_size > 0
    outputs.reset_claims()
    out = tmp_path / "out.json"
    outputs.check_file(out, "--json", [".json"])
    bench.save_rows([{"a": 1}], str(out))
    bench.save_rows([{"a": 1}, {"b": 2}], str(out))
    assert out.read_text().count("{") == 2 and sorted(p.name for p in tmp_path.iterdir()) == [
        "out.json", "rows.json", "rows.png", "taken.json", "taken.png"]
    outputs.reset_claims()
