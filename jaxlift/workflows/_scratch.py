"""Where a workflow writes when the caller names no folder (a notebook that wants
objects, not files): a temporary folder, removed when the object that holds it is
garbage-collected (the workflow's result, or the workflow's own frame)."""

from __future__ import annotations

import os
import pathlib
import tempfile


def output_folder(
    out_dir: str | os.PathLike | None, what: str
) -> tuple[pathlib.Path, tempfile.TemporaryDirectory | None]:
    """``(folder, keeper)``: ``out_dir`` itself, or a new temporary folder and the
    :class:`tempfile.TemporaryDirectory` that removes it when it is dropped."""
    if out_dir is not None:
        return pathlib.Path(out_dir), None
    keeper = tempfile.TemporaryDirectory(prefix=f"jaxlift-{what}-")
    return pathlib.Path(keeper.name), keeper
