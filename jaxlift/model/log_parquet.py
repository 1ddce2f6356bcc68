"""Logs as Parquet files: the same columns, units and checks as the CSV format
(docs/data.md), typed columns instead of text.

A known column must have a numeric type (integers or floating point) and no missing
values; any other column is kept in :attr:`Log.extra` (float64 when numeric, else as
strings) and named once in an :class:`UnusedColumnsWarning`. Errors name the file, the
column and the row: a row is reported as the line it would be on in the CSV file (row
index + 2, the header being line 1), with its 0-based index.
"""

from collections.abc import Mapping

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq

from .log_validation import (
    JITTER,
    KNOWN_COLUMNS,
    MIN_SAMPLES,
    LogError,
    find_columns,
    validate_arrays,
)

#: File name endings read as Parquet by :func:`jaxlift.read_log`.
PARQUET_SUFFIXES = (".parquet", ".pq")


def _numeric(t: pa.DataType) -> bool:
    return pa.types.is_integer(t) or pa.types.is_floating(t)


def read_parquet_columns(
    p: str, name: str, sources: Mapping[str, str] | None = None, *, jitter: float = JITTER
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The checked known columns and the extra columns of the Parquet log at ``p``
    (:func:`jaxlift.read_log` builds the :class:`~jaxlift.Log` from them): the known
    columns found under their names in ``sources`` (log column -> column name in the file,
    :func:`~jaxlift.model.log_validation.channel_sources`; default: their own names),
    their time steps checked with the relative tolerance ``jitter``. Raises
    :class:`~jaxlift.LogError` for anything that is not a valid log."""
    sources = {c: c for c in KNOWN_COLUMNS} if sources is None else sources
    try:
        table = pq.read_table(p)
    except FileNotFoundError as e:
        raise LogError("a readable log file", path=p, got=f"FileNotFoundError: {e}") from None
    except (pa.ArrowException, OSError) as e:
        raise LogError("a Parquet file", path=p, got=f"{type(e).__name__}: {e}") from None
    names = table.column_names
    if len(set(names)) != len(names):
        dup = sorted({c for c in names if names.count(c) > 1})
        raise LogError("unique column names", path=p, column=dup[0], got=f"{dup} repeated")
    found = find_columns(names, sources, path=p)
    channels = {c: src for c, src in found.items() if src != c}
    if table.num_rows < MIN_SAMPLES:
        raise LogError(f"at least {MIN_SAMPLES} rows", path=p, got=f"{table.num_rows}")
    known = {}
    for c, src in found.items():
        col = table.column(src)
        where = dict(path=p, column=c, channel=channels.get(c))
        if not _numeric(col.type):
            raise LogError("a numeric column (integer or floating point)",
                           got=f"type {col.type}", **where)  # fmt: skip
        if col.null_count:
            i = int(np.flatnonzero(np.asarray(col.is_null()))[0])
            raise LogError("a number", row=i + 2, index=i, got="a missing value (null)", **where)
        known[c] = col.to_numpy().astype(np.float64)
    arrays = validate_arrays(known, path=p, name=name, channels=channels, jitter=jitter)
    used = set(found.values())
    extra = {}
    for c in names:
        if c in used:
            continue
        col = table.column(c)
        if _numeric(col.type) and not col.null_count:
            extra[c] = col.to_numpy().astype(np.float64)
        else:
            extra[c] = np.array(["" if v is None else str(v) for v in col.to_pylist()])
    return arrays, extra
