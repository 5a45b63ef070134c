"""``python -m reconstruct``: the ``reconstruct`` command."""

from reconstruct.cli.console import console

console()
