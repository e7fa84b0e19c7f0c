"""Sub-commands of the ``dqm`` CLI, one module each (see dqm/cli.py)."""
