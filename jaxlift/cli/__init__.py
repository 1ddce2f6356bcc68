"""The command line, ``jaxlift COMMAND ...``: argument parsing only.

Each command parses its arguments and calls one workflow function of
:mod:`jaxlift.workflows` (or a library function); nothing is computed here.
"""

from .main import main

__all__ = ["main"]
