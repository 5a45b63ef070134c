"""``python -m reconstruct``: the ``reconstruct`` command."""

from reconstruct.cli.main import console

console()
