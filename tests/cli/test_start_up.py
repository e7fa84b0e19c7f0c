"""A command's start-up loads what that command needs, not every command's modules (issue 37: scipy.sparse
through dqm.core cost every command about 0.4 s): the parser of one command is built from its own module,
and the package roots load their names on first use."""
import json
import subprocess
import sys

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
