"""A command's start-up loads what that command needs, not every command's modules (issue 37: scipy.sparse
through dqm.core cost every command about 0.4 s): the parser of one command is built from its own module,
and the package roots load their names on first use."""
import json
import subprocess
import sys

import numpy as np
import pytest

from dqm.cli import COMMANDS, build_parser, command_named


def _loaded_after(argv):
    """The dqm and scipy modules loaded once ``dqm <argv>`` has parsed its arguments (in a fresh interpreter)."""
    code = ("import json, sys\nfrom dqm import cli\n"
            f"try:\n    cli.main({argv!r})\nexcept SystemExit:\n    pass\n"
            "print(json.dumps(sorted(m for m in sys.modules if m.startswith(('dqm.', 'scipy')))))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr
    return set(json.loads(r.stdout.strip().splitlines()[-1]))


def test_every_command_is_registered_under_its_own_name():
    sub = next(a for a in build_parser()._actions if a.__class__.__name__ == "_SubParsersAction")
    assert sorted(sub.choices) == sorted(COMMANDS)
    for name in COMMANDS:
        assert command_named(["-v", name, "--out", "run"]) == name
    assert command_named(["--help"]) is None and command_named(["nonsense", "match"]) is None
    assert command_named(["--help", "match"]) is None and command_named(["match", "--help"]) == "match"


@pytest.mark.parametrize("argv,own", [(["agent", "--help"], "dqm.commands.agent"),
                                      (["match", "--help"], "dqm.commands.match"),
                                      (["router", "--help"], "dqm.commands.router")])
def test_a_command_loads_its_own_module_and_no_scipy(argv, own):
    loaded = _loaded_after(argv)
    assert own in loaded
    others = {m for m in COMMANDS.values() if m in loaded} - {own}
    # a command module may build on another's options (match on extract's), never on all of them
    assert len(others) <= 2, sorted(others)
    assert not any(m.startswith("scipy") for m in loaded), sorted(m for m in loaded if m.startswith("scipy"))
    assert "dqm.distributed.simulator" not in loaded and "dqm.core.online" not in loaded


def test_help_of_all_commands_still_lists_them(capsys):
    from dqm.cli import main

    with pytest.raises(SystemExit):
        main(["--help"])
    out = capsys.readouterr().out
    assert all(name in out for name in COMMANDS)


def test_the_coordinator_pick_and_the_gathered_match_load_neither_numpy_ma_nor_numpy_random():
    """np.median's and np.unique's first calls import numpy.ma, and numpy.random is an import of its own:
    about 20 ms of CPU each, 80 ms on a host's quarter core, in the coordinator before ``--mode auto``
    decides and in the gathering agent. The pair-rate probe, the cost model's pick (a median of the rates)
    and the gathered match (a check for repeated ids) use neither, and still refuse repeated ids."""
    code = """
import json, sys
import numpy as np
from dqm.core.pairs import pair_cpu_s_here
from dqm.distributed import costmodel
from dqm.distributed.gathering import match_gathered
rate = pair_cpu_s_here(128, np.uint8, rows=256, repeats=1)
job = costmodel.JobShape(n=20000, agents=4, dim=128)
pick = costmodel.choose(job, costmodel.Hosts.of([1.25e6, 12.5e6, 125e6, 12.5e6], 0.25, kernel_cpu_s=rate))
k = np.arange(300 * 16, dtype=np.int64)
X = ((k * 2654435761) % 251).astype(np.uint8).reshape(300, 16)
ids, labels = match_gathered(np.arange(300), np.arange(300) % 3, X)
try:
    match_gathered(np.r_[np.arange(299), 7], np.arange(300) % 3, X)
    refused = ""
except ValueError as exc:
    refused = str(exc)
loaded = sorted(m for m in ("numpy.ma", "numpy.random") if m in sys.modules)
print(json.dumps([pick.mode, len(labels), refused, loaded]))
"""
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    mode, n, refused, loaded = json.loads(r.stdout.strip().splitlines()[-1])
    assert mode in ("gather", "lean", "balanced") and n == 300
    assert "same feature id" in refused
    assert loaded == []


def test_has_repeats_agrees_with_unique():
    from dqm.validation import has_repeats

    rng = np.random.default_rng(4)
    for n in (0, 1, 2, 3, 50, 1000):
        for hi in (2, 60, 10**9):
            v = rng.integers(0, hi, n)
            assert has_repeats(v) == (len(np.unique(v)) != len(v)), (n, hi)
    assert has_repeats(np.array([[1, 2], [3, 1]])) and not has_repeats([5.0, -5.0])


def test_the_cost_models_median_is_numpys():
    from dqm.distributed.costmodel import _median

    rng = np.random.default_rng(5)
    for n in range(1, 30):
        v = rng.random(n) * 10.0 ** rng.integers(-3, 10)
        assert _median(v) == float(np.median(v))



def test_the_runtime_processes_leave_without_the_interpreters_teardown():
    """``dqm agent`` and ``dqm coordinator`` leave with os._exit once their command returned (their sessions are
    closed and their outputs written by then; the teardown cost a host with a quarter core 0.06-0.15 s before
    the coordinator was gone): an atexit handler no longer runs there, and still runs after any other command.
    The command's last line still arrives, and the exit code is the command's."""
    hook = ("import atexit, sys\natexit.register(lambda: print('teardown ran', flush=True))\n"
            "sys.argv = ['dqm'] + sys.argv[1:]\nfrom dqm.cli import program\nprogram()\n")

    def run(*argv):
        return subprocess.run([sys.executable, "-c", hook, *argv], capture_output=True, text=True, timeout=60)

    for argv in (["coordinator", "--agents", "2", "--connect", "tcp/127.0.0.1:9", "--connect-timeout", "0.2",
                  "--job", "exit-at-once", "--no-clusters"],
                 ["agent", "--id", "0", "--agents", "2", "--connect", "tcp/127.0.0.1:9", "--connect-timeout", "0.2",
                  "--job", "exit-at-once", "nothing.npz"]):
        r = run(*argv)
        assert r.returncode == 2 and "teardown ran" not in r.stdout, (argv[0], r.stdout, r.stderr)
        assert r.stderr.strip().startswith(f"dqm {argv[0]}: error:") and len(r.stderr.strip().splitlines()) == 1
    r = run("match", "nothing.npz")
    assert r.returncode == 2 and "teardown ran" in r.stdout and r.stderr.startswith("dqm match: error:")
