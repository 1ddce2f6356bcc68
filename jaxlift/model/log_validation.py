"""What a valid log is: the columns, their units and ranges, and the named errors
(file, row, column, what was expected) for everything else (see ``docs/data.md``).
"""

import re
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from .constants import MAST_HEIGHT_M, P_ATM

REQUIRED_COLUMNS: tuple[str, ...] = ("time_s", "pwm", "height_m", "load_kg")
OPTIONAL_COLUMNS: tuple[str, ...] = ("speed_mps", "pressure_pa")
KNOWN_COLUMNS: tuple[str, ...] = REQUIRED_COLUMNS + OPTIONAL_COLUMNS

MIN_SAMPLES = 2  # fewer gives no sample period
JITTER = 0.01  # tolerated deviation of a time step from the sample period, relative
#: Tolerated deviation before resampling (``read_log(..., resample=dt)``): a step more
#: than 1.5 periods long is a missing sample (a gap), still an error.
RESAMPLE_JITTER = 0.5
HEIGHT_MIN_M = -0.01  # sensor noise at the bottom of the mast
HEIGHT_MAX_M = 4.6  # the mast is 4.5 m high; a little margin for the sensor
#: Lowest gauge pressure [Pa] a log may hold: vacuum, 1 atm below atmosphere. A gauge
#: transducer reads a little below 0 at rest (noise); below -1 atm is impossible.
PRESSURE_MIN_PA = -P_ATM


NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
NOT_DECIMAL_CHAR = re.compile(r"[^0-9eE+\-. \t]")


class LogError(ValueError):
    """A file (or arrays) that is not a valid log.

    Attributes
    ----------
    expected : str
        What was expected, in words.
    path : str | None
        The file, if there is one.
    row : int | None
        1-based line number in the file (the header is line 1); for a :class:`Log` built in
        code, array index + 2.  ``None`` when the problem is not on one line.
    column : str | None
        The column concerned, if any.
    got : str | None
        What was found instead, in words.
    index : int | None
        0-based array index of the sample, given for logs checked in memory and for files
        whose samples have no lines (MDF: then ``row`` is ``None``).
    name : str | None
        Name of the log, used in the message when there is no path.
    channel : str | None
        The name of the channel (or column) in the file that holds ``column``, where it
        differs from ``column`` (a channel map) or the file has channels (MDF).  The
        message then names the channel.
    """

    def __init__(
        self,
        expected: str,
        path: str | None = None,
        row: int | None = None,
        column: str | None = None,
        got: str | None = None,
        index: int | None = None,
        name: str | None = None,
        channel: str | None = None,
    ) -> None:
        self.expected = expected
        self.path = path
        self.row = row
        self.column = column
        self.got = got
        self.index = index
        self.name = name
        self.channel = channel
        super().__init__(self._message())

    def _message(self) -> str:
        if self.path is not None:
            where = [self.path]
        else:
            where = [f"log {self.name!r}" if self.name is not None else "log"]
        if self.row is not None:
            line = f"line {self.row}"
            if self.index is not None:
                line += f" (array index {self.index})"
            where.append(line)
        elif self.index is not None:  # samples without lines (MDF channels)
            where.append(f"sample index {self.index}")
        if self.channel is not None:
            mapped = self.column is not None and self.column != self.channel
            where.append(
                f"channel {self.channel!r}" + (f" (log column {self.column!r})" if mapped else "")
            )
        elif self.column is not None:
            where.append(f"column {self.column!r}")
        msg = f"{', '.join(where)}: expected {self.expected}"
        if self.got is not None:
            msg += f", got {self.got}"
        return msg

    def __reduce__(self) -> tuple[Any, ...]:
        args = (self.expected, self.path, self.row, self.column, self.got, self.index, self.name,
                self.channel)  # fmt: skip
        return (type(self), args)


class UnusedColumnsWarning(UserWarning):
    """A log has columns that jaxlift does not use; they are kept in :attr:`Log.extra`."""


def read_bytes(p: str) -> bytes:
    """The bytes of the log file at ``p``; a :class:`LogError` naming it if it cannot
    be read (CSV and MDF logs alike)."""
    try:
        with open(p, "rb") as f:
            return f.read()
    except OSError as e:
        raise LogError(
            "a readable log file", path=p, got=f"{type(e).__name__}: {e.strerror or e}"
        ) from None


def fmt_value(x: float) -> str:
    return f"{x:.9g}"


def first_index(mask: np.ndarray) -> int | None:
    """Index of the first True in ``mask``, or None."""
    if mask.size == 0:
        return None
    i = int(np.argmax(mask))
    return i if mask[i] else None


def _as_column(
    value: Any, column: str, *, path: str | None, name: str | None, channel: str | None = None
) -> np.ndarray:
    """``value`` as a fresh read-only 1-D float64 array, or LogError."""
    where = dict(path=path, column=column, name=name, channel=channel)
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as e:  # ragged nested sequences and the like
        raise LogError("a 1-D array of numbers", got=str(e), **where) from None
    if arr.dtype.kind not in "biuf":
        got = "None" if value is None else f"an array of dtype {arr.dtype}"
        raise LogError("a 1-D array of numbers", got=got, **where)
    if arr.ndim != 1:
        raise LogError("a 1-D array of numbers", got=f"an array of shape {arr.shape}", **where)
    out = np.array(arr, dtype=np.float64)  # always a copy
    out.setflags(write=False)
    return out


def validate_arrays(
    columns: Mapping[str, ArrayLike | None],
    *,
    path: str | None = None,
    name: str | None = "log",
    lines: Sequence[int] | np.ndarray | None = None,
    raw: Mapping[str, Sequence[str]] | None = None,
    rows: bool = True,
    channels: Mapping[str, str] | None = None,
    jitter: float = JITTER,
) -> dict[str, np.ndarray]:
    """Check the known columns of a log; return them as read-only float64 arrays.

    Shared by :func:`read_log` and :meth:`Log.__post_init__`.

    Parameters
    ----------
    columns
        Column name -> values.  Must hold every required column; optional columns may be
        missing or ``None``.  Unknown names are an error (unused columns go to ``Log.extra``).
    path, name
        Used in error messages.
    lines
        File line of each sample (from :func:`read_log`).  Default: array index + 2, and the
        messages give the array index as well.
    raw
        Original text of each value (from :func:`read_log`), only to word the message about a
        value that is not a number (it was parsed to NaN).
    rows
        ``False`` for samples that have no lines (MDF channels): errors then give the 0-based
        sample index only (``LogError.row`` is ``None``).
    channels
        Column -> name of its channel in the file, for the messages (``LogError.channel``);
        columns not in it are named as columns.
    jitter
        Tolerated deviation of a time step from the median step, relative: :data:`JITTER`,
        or :data:`RESAMPLE_JITTER` for samples that are resampled afterwards.

    Raises
    ------
    LogError
        For the first problem: shape problems first, then the one on the earliest line (ties
        go to the column that comes first in :data:`KNOWN_COLUMNS`).
    """
    channels = {} if channels is None else channels
    for c in columns:
        if c not in KNOWN_COLUMNS:
            raise LogError(
                f"one of the columns {', '.join(KNOWN_COLUMNS)}",
                path=path,
                column=c,
                got=f"unknown column {c!r} (unused columns belong in Log.extra)",
                name=name,
            )
    arrays: dict[str, np.ndarray] = {}
    for c in KNOWN_COLUMNS:
        value = columns.get(c)
        if value is None:
            if c in REQUIRED_COLUMNS:
                raise LogError(f"the required column {c!r}", path=path, column=c, got="none",
                               name=name, channel=channels.get(c))  # fmt: skip
            continue
        arrays[c] = _as_column(value, c, path=path, name=name, channel=channels.get(c))

    n = arrays["time_s"].shape[0]
    for c, a in arrays.items():
        if a.shape[0] != n:
            raise LogError(
                f"{n} values (as many as time_s)",
                path=path,
                column=c,
                got=f"{a.shape[0]}",
                name=name,
                channel=channels.get(c),
            )
    if n < MIN_SAMPLES:
        row = None
        if lines is not None and len(lines) > 0:
            row = int(lines[-1]) + 1
        raise LogError(
            f"at least {MIN_SAMPLES} samples (data rows)", path=path, row=row, got=str(n), name=name
        )

    in_memory = lines is None
    line_of = np.arange(n) + 2 if lines is None else np.asarray(lines, dtype=np.int64)
    if line_of.shape != (n,):
        raise ValueError(f"lines has shape {line_of.shape}, expected ({n},)")

    def at(i: int) -> str:
        return f"line {int(line_of[i])}" if rows else f"sample index {i}"

    # Candidates (line, column rank, error); the earliest line wins.
    found: list[tuple[int, int, LogError]] = []

    def add(i: int | None, column: str, expected: str, got: str) -> None:
        if i is None:
            return
        err = LogError(
            expected,
            path=path,
            row=int(line_of[i]) if rows else None,
            column=column,
            got=got,
            index=i if in_memory or not rows else None,
            name=name,
            channel=channels.get(column),
        )
        found.append((int(line_of[i]), KNOWN_COLUMNS.index(column), err))

    with np.errstate(all="ignore"):
        for c, a in arrays.items():
            i = first_index(~np.isfinite(a))
            if i is not None:
                tok = None if raw is None or c not in raw else raw[c][i].strip()
                if tok is None:
                    add(i, c, "a finite number", fmt_value(a[i]))
                elif tok == "":
                    add(i, c, "a number", "an empty field")
                elif NUMBER.fullmatch(tok) or NON_FINITE.fullmatch(tok):
                    add(i, c, "a finite number", repr(tok))
                else:
                    add(i, c, "a number", repr(tok))

        pwm = arrays["pwm"]
        i = first_index((pwm < 0.0) | (pwm > 1.0))
        add(i, "pwm", "a value in [0, 1]", "" if i is None else fmt_value(pwm[i]))

        h = arrays["height_m"]
        i = first_index(h < HEIGHT_MIN_M)
        add(
            i,
            "height_m",
            f"a height of at least {HEIGHT_MIN_M} m (below 0 only by sensor noise at the bottom)",
            "" if i is None else f"{fmt_value(h[i])} m",
        )
        i = first_index(h > HEIGHT_MAX_M)
        add(
            i,
            "height_m",
            f"a height of at most {HEIGHT_MAX_M} m (the mast is {MAST_HEIGHT_M} m high)",
            "" if i is None else f"{fmt_value(h[i])} m",
        )

        m = arrays["load_kg"]
        i = first_index(m < 0.0)
        add(i, "load_kg", "a load of at least 0 kg", "" if i is None else f"{fmt_value(m[i])} kg")

        if "pressure_pa" in arrays:
            p = arrays["pressure_pa"]
            i = first_index(p < PRESSURE_MIN_PA)
            add(
                i,
                "pressure_pa",
                f"a gauge pressure of at least {PRESSURE_MIN_PA:.0f} Pa (1 atm below "
                "atmosphere is vacuum)",
                "" if i is None else f"{fmt_value(p[i])} Pa",
            )

        t = arrays["time_s"]
        dt = np.diff(t)  # dt[k] is the step that ends at sample k + 1
        k = first_index(dt <= 0.0)
        if k is not None:
            prev = f"{fmt_value(t[k])} s at {at(k)}"
            if dt[k] == 0.0:
                got = f"{fmt_value(t[k + 1])} s again (a repeated sample)"
            else:
                got = f"{fmt_value(t[k + 1])} s (time goes backwards)"
            add(k + 1, "time_s", f"a time later than {prev}", got)

        ok = np.isfinite(dt) & (dt > 0.0)
        if np.any(ok):
            period = float(np.median(dt[ok]))
            expected = (
                f"a time step of {period:.6g} s, the median sample period "
                f"(uniform sampling, jitter under {jitter:.0%} tolerated)"
            )
            k = first_index(ok & (dt > period * (1.0 + jitter)))
            if k is not None:
                missing = round(float(dt[k]) / period) - 1
                what = (
                    f"a gap, about {missing} sample{'s' if missing > 1 else ''} missing"
                    if missing >= 1
                    else "a late sample"
                )
                got = f"a step of {dt[k]:.6g} s from {at(k)} ({what})"
                add(k + 1, "time_s", expected, got)
            k = first_index(ok & (dt < period * (1.0 - jitter)))
            if k is not None:
                got = f"a step of {dt[k]:.6g} s from {at(k)} (irregular sampling)"
                add(k + 1, "time_s", expected, got)

    if found:
        raise min(found, key=lambda f: (f[0], f[1]))[2]
    return arrays


def check_extra(extra: Any, n: int, *, path: str | None, name: str | None) -> dict[str, np.ndarray]:
    if not isinstance(extra, Mapping):
        raise LogError(
            "a mapping column name -> array for Log.extra",
            path=path,
            got=type(extra).__name__,
            name=name,
        )
    out: dict[str, np.ndarray] = {}
    for c, value in extra.items():
        if not isinstance(c, str) or not c or c != c.strip():
            raise LogError(
                "a non-empty column name without surrounding spaces in Log.extra",
                path=path,
                got=repr(c),
                name=name,
            )
        if c in KNOWN_COLUMNS:
            raise LogError(
                "extra columns other than the known ones",
                path=path,
                column=c,
                got=f"{c!r} in Log.extra (give it as Log.{c})",
                name=name,
            )
        arr = np.asarray(value)
        if arr.dtype.kind not in "biufU" or arr.ndim != 1 or arr.shape[0] != n:
            raise LogError(
                f"a 1-D array of {n} numbers or strings (one per sample)",
                path=path,
                column=c,
                got=f"an array of dtype {arr.dtype} and shape {arr.shape}",
                name=name,
            )
        arr = arr.copy()
        arr.setflags(write=False)
        out[c] = arr
    return out


def channel_sources(channel_map: Mapping[str, str] | None) -> dict[str, str]:
    """Log column -> name of the column (CSV, Parquet) or channel (MDF) that holds it in a
    file: the column's own name, unless ``channel_map`` names another.

    Parameters
    ----------
    channel_map
        Log column (``time_s``, ``pwm``, ``height_m``, ``load_kg``, ``speed_mps``,
        ``pressure_pa``) -> name in the file, for the columns a logger names otherwise;
        ``None`` or ``{}``: every column under its own name.

    Raises
    ------
    ValueError
        For a key that is not a log column, a name that is not a non-empty string, or one
        name given to two columns.
    """
    if channel_map is None:
        channel_map = {}
    if not isinstance(channel_map, Mapping):
        raise ValueError(
            f"channel_map: expected a mapping log column -> channel name, got "
            f"{type(channel_map).__name__}"
        )
    for c, src in channel_map.items():
        if c not in KNOWN_COLUMNS:
            raise ValueError(
                f"channel_map: {c!r} is not a log column (expected one of "
                f"{', '.join(KNOWN_COLUMNS)})"
            )
        if not isinstance(src, str) or not src.strip():
            raise ValueError(f"channel_map: expected a channel name for {c}, got {src!r}")
    sources = {c: channel_map.get(c, c).strip() for c in KNOWN_COLUMNS}
    seen: dict[str, str] = {}
    for c, src in sources.items():
        if src in seen:
            raise ValueError(
                f"channel_map: the channel {src!r} would be read as both {seen[src]} and {c} "
                "(map one of them to another channel)"
            )
        seen[src] = c
    return sources


def find_columns(
    names: Sequence[str],
    sources: Mapping[str, str],
    *,
    path: str | None,
    row: int | None = None,
    kind: str = "column",
    required: Sequence[str] = REQUIRED_COLUMNS,
    note: str | None = None,
) -> dict[str, str]:
    """Log column -> its name in the file, for the known columns whose name (``sources``,
    :func:`channel_sources`) is among the file's column or channel ``names``.

    Raises :class:`LogError` (at line ``row``, naming the ``kind``: ``"column"`` or
    ``"channel"``) for a missing required column, and for a column named like a known one
    that the channel map reads from another name (it would be neither used nor kept).
    """
    present = set(names)
    found: dict[str, str] = {}
    for c in KNOWN_COLUMNS:
        src = sources[c]
        if src in present:
            found[c] = src
        elif c in required:
            expected = f"a {kind} named {src!r}"
            if src != c:
                expected += f" (the channel map's {c})"
            expected += f" (required: {', '.join(required)}"
            expected += f"; {note})" if note else ")"
            shown = ", ".join(repr(x) for x in names[:30]) + (", ..." if len(names) > 30 else "")
            raise LogError(
                expected, path=path, row=row, column=c, got=f"{kind}s {shown}" if shown else "none",
                channel=src if src != c or kind == "channel" else None,
            )  # fmt: skip
    used = set(found.values())
    for x in names:
        if x in KNOWN_COLUMNS and x not in used:
            raise LogError(
                f"no {kind} named {x!r}: the channel map reads {x} from {sources[x]!r}, and "
                f"{x!r} would be neither used nor kept", path=path, row=row, column=x,
                got=f"a {kind} {x!r} as well",
            )  # fmt: skip
    return found
