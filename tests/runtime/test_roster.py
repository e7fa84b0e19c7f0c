"""The roster (dqm router --acl): parsed with one clear line per mistake, turned into default-deny rules
that give every identity exactly its own keys."""
import subprocess
import sys

import pytest

from dqm.distributed import keys
from dqm.runtime.roster import RosterError, access_control, job_roster, load_roster, parse_roster

GOOD = """# a team of two robots
coordinator  base-station
agent        robot-a   0   # agent process 0
agent        robot-b   1
stream       stream
camera       cam-a     0
viewer       dashboard
job          survey-7
"""


def test_a_roster_is_read_with_roles_indices_and_jobs():
    r = parse_roster(GOOD, "team.txt")
    assert [(i.role, i.name, i.index) for i in r.identities] == [
        ("coordinator", "base-station", None), ("agent", "robot-a", 0), ("agent", "robot-b", 1),
        ("stream", "stream", None), ("camera", "cam-a", 0), ("viewer", "dashboard", None)]
    assert r.jobs == ("survey-7",)
    assert parse_roster(r.text()) == parse_roster(GOOD)  # text() writes what parse reads (source aside)


@pytest.mark.parametrize("text,said", [
    ("agent robot-a 0\nrobot robot-b\n", "line 2: unknown role 'robot'"),
    ("agent robot-a 0\nagent robot-a 1\n", "line 2: identity 'robot-a' is listed twice (first on line 1)"),
    ("agent robot-a 0\nagent robot-b 0\n", "line 2: agent 0 is given to two identities"),
    ("agent robot-a\n", "line 1: write 'agent IDENTITY INDEX'"),
    ("agent robot-a -1\n", "line 1: agent index '-1' must be a non-negative integer"),
    ("coordinator a b\n", "line 1: write 'coordinator IDENTITY'"),
    ("agent robot/a 0\n", "line 1: identity 'robot/a' must be"),
    ("job bad/job\ncoordinator c\n", "line 1: job id must be"),
    ("# nothing\n\n", "no identities"),
])
def test_roster_mistakes_are_named_with_their_line(text, said):
    with pytest.raises(RosterError) as e:
        parse_roster(text, "team.txt")
    assert said in str(e.value) and str(e.value).startswith("team.txt")


def test_unreadable_rosters_are_refused(tmp_path):
    with pytest.raises(RosterError, match="cannot read the roster"):
        load_roster(str(tmp_path / "missing.txt"))
    (tmp_path / "bin.txt").write_bytes(b"\xff\xfe\x00agent")
    with pytest.raises(RosterError, match="is not UTF-8 text"):
        load_roster(str(tmp_path / "bin.txt"))


def test_rules_give_each_identity_only_its_own_keys():
    acl = access_control(parse_roster(GOOD), subjects=("cert", "user"))
    assert acl["enabled"] and acl["default_permission"] == "deny"
    rules = {r["id"]: r for r in acl["rules"]}
    subjects = {s["id"]: s for s in acl["subjects"]}

    def allowed(name):
        out = set()
        for pol in acl["policies"]:
            names = {next(v[0] for k, v in subjects[s].items() if k != "id") for s in pol["subjects"]}
            if name in names:
                for rid in pol["rules"]:
                    r = rules[rid]
                    out |= {(r["flows"][0], m, k) for m in r["messages"] for k in r["key_exprs"]}
        return out

    a = allowed("robot-a")
    assert ("ingress", "put", "dqm/survey-7/proc/*/from/0/**") in a  # only keys that name itself
    assert ("ingress", "declare_subscriber", "dqm/survey-7/proc/0/**") in a  # only its own inbox
    assert ("ingress", "liveliness_token", keys.alive_agent("survey-7", 0)) in a
    puts = {k for f, m, k in a if f == "ingress" and m == "put"}
    assert puts == {"dqm/survey-7/proc/*/from/0/**"}
    assert not any("proc/1" in k or "from/1" in k or "coordinator" in k for _, _, k in a)
    cam = allowed("cam-a")
    assert {k for f, m, k in cam if f == "ingress" and m == "put"} == {keys.camera_images("survey-7", 0),
                                                                     keys.camera_probe("survey-7", 0)}
    # its own probe key only (the start-up check): a camera never subscribes to images
    assert {k for f, m, k in cam if m == "declare_subscriber"} == {keys.camera_images("survey-7", 0),
                                                                   keys.camera_probe("survey-7", 0)}
    assert {k for f, m, k in cam if f == "ingress" and m == "declare_subscriber"} == {keys.camera_probe("survey-7", 0)}
    assert {k for f, m, k in allowed("dashboard") if m == "declare_subscriber"} == {keys.stream_changes("survey-7")}
    # both authentications name the same identity: a subject each
    assert {tuple(sorted(s)) for s in acl["subjects"]} == {("cert_common_names", "id"), ("id", "usernames")}


def test_the_example_roster_in_deploy_parses():
    from pathlib import Path

    r = load_roster(str(Path(__file__).resolve().parents[2] / "deploy" / "roster.example"))
    assert [i.describe() for i in r.identities] == ["coordinator"] + [f"agent {p}" for p in range(4)]


def test_a_job_roster_names_what_dqm_run_secure_certifies():
    r = job_roster(3, ["j"])
    assert [i.as_line() for i in r.identities] == ["coordinator coordinator", "agent agent0 0", "agent agent1 1",
                                                   "agent agent2 2"]


@pytest.mark.parametrize("content,said", [
    ("boss base\n", "unknown role 'boss'"),
    ("agent a 0\nagent a 1\n", "identity 'a' is listed twice"),
    (None, "cannot read the roster"),
])
def test_dqm_router_refuses_a_bad_roster_in_one_line(tmp_path, content, said):
    roster = tmp_path / "roster.txt"
    if content is not None:
        roster.write_text(content)
    for name in ("ca", "router"):
        (tmp_path / f"{name}.pem").write_text("-----BEGIN CERTIFICATE-----\n")
    tls = ["--tls-ca", str(tmp_path / "ca.pem"), "--tls-cert", str(tmp_path / "router.pem"),
           "--tls-key", str(tmp_path / "router.pem")]
    r = subprocess.run([sys.executable, "-m", "dqm", "router", "--listen", "tls/127.0.0.1:1", "--acl", str(roster),
                        *tls], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2
    assert said in r.stderr and len(r.stderr.strip().splitlines()) == 1 and "Traceback" not in r.stderr


def test_acl_without_identities_is_refused(tmp_path):
    roster = tmp_path / "roster.txt"
    roster.write_text("coordinator c\n")
    r = subprocess.run([sys.executable, "-m", "dqm", "router", "--listen", "tcp/127.0.0.1:1", "--acl", str(roster)],
                       capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "--acl needs identities" in r.stderr and "Traceback" not in r.stderr
