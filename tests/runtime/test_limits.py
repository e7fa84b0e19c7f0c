"""The runtime limits: one object, options generated from its fields, one encoded value for children."""
import argparse
import subprocess
import sys
from dataclasses import fields

import pytest

from dqm.runtime.launcher import START_LIMITS, coordinator_args
from dqm.runtime.limits import AGENT, COORDINATOR, RUN, RuntimeLimits, add_limits, limits_arg, limits_from
from dqm.validation import InputError


def _parse(command, argv):
    p = argparse.ArgumentParser()
    add_limits(p, command)
    return limits_from(p.parse_args(argv))


def test_every_field_is_an_option_of_the_commands_it_names():
    for command in (COORDINATOR, AGENT, RUN):
        p = argparse.ArgumentParser()
        add_limits(p, command)
        flags = {a.option_strings[0] for a in p._actions if a.option_strings}
        for f in fields(RuntimeLimits):
            assert (f.metadata["flag"] in flags) == (command in f.metadata["commands"]), (command, f.name)


def test_options_override_the_encoded_value_and_both_round_trip():
    base = RuntimeLimits(job_timeout_s=42.0, max_lost=0, recovery="restart", lease_s=2.5)
    assert RuntimeLimits.from_text(base.to_text()) == base
    assert RuntimeLimits.from_text(RuntimeLimits().to_text()) == RuntimeLimits()  # defaults: "{}"
    got = _parse(COORDINATOR, [limits_arg(base), "--max-lost", "2", "--timeout", "7"])
    assert got == base.but(max_lost=2, job_timeout_s=7.0)
    assert got.lease_ms == 2500
    assert _parse(AGENT, []) == RuntimeLimits()


@pytest.mark.parametrize("argv,pattern", [
    (["--max-lost", "-1"], "--max-lost must be an integer >= 0"),
    (["--lease", "0"], "--lease must be a positive number"),
    (["--job-timeout", "nan"], "--job-timeout must be a positive number"),
    (["--limits", "{bad"], "is not JSON"),
    (["--limits", '{"lease": 3}'], "names lease, which are not limits"),
    (["--limits", '{"recovery": "pray"}'], "--recovery must be one of takeover, restart"),
])
def test_bad_limits_are_refused_naming_the_option(argv, pattern):
    with pytest.raises(InputError, match=pattern):
        _parse(COORDINATOR, argv)


def test_a_launcher_hands_its_children_one_value():
    from dqm.distributed import DQMConfig

    limits = START_LIMITS.but(recovery="restart", max_lost=1)
    args = coordinator_args(DQMConfig(agents=3), "tcp/127.0.0.1:7447", "r.json", limits)
    given = [a for a in args if a.startswith("--limits=")]
    assert given == [limits_arg(limits)]
    assert not {"--job-timeout", "--max-lost", "--recovery", "--ready-timeout"} & set(args)


def test_dqm_run_refuses_a_bad_limit_in_one_line():
    r = subprocess.run([sys.executable, "-m", "dqm", "run", "--lease", "-2"], capture_output=True, text=True,
                       timeout=60)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines()[-1].endswith("--lease must be a positive number, got -2.0")
    assert "Traceback" not in r.stderr
