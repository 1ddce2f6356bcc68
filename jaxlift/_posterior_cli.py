"""Command line: ``jaxlift posterior`` (being written; see the open issue)."""

from __future__ import annotations

import argparse


def add_parsers(sub: argparse._SubParsersAction) -> None:
    """Add this module's sub-commands to ``jaxlift``'s parser."""
