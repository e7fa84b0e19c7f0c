"""Sub-commands of the ``dqm`` CLI, one module each (see dqm/cli.py)."""

import argparse


class HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Keeps each command's docstring layout and shows every option's default value."""

    def _get_help_string(self, action):
        text = action.help or ""
        if (not action.option_strings or any(action.default is v for v in (None, False, argparse.SUPPRESS))
                or "default" in text.lower()):
            return text
        return f"{text} (default: %(default)s)".strip()
