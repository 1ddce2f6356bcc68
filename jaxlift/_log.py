"""Measurement logs of the lift: reading, checking and writing one test run.

Format
------
One test run of one vehicle is one CSV file (see ``DATA.md``):

* UTF-8 text (a leading byte-order mark, as some spreadsheet programs write it, is accepted),
  comma-separated, ``\\n`` or ``\\r\\n`` line ends, standard CSV quoting;
* one header row naming the columns, then one row per sample; blank lines are accepted only
  at the end of the file;
* SI units, the unit is part of the column name:

  ===============  ========  ====================================================================
  column           required  meaning
  ===============  ========  ====================================================================
  ``time_s``       yes       sample time [s]; strictly increasing and uniformly sampled: every
                             step is within 1 % of the median step (the sample period)
  ``pwm``          yes       duty cycle commanded to the voltage unit [-], in [0, 1]
                             (0 = valve closed)
  ``height_m``     yes       fork height from the wire sensor [m], in [-0.01, 4.6]: the mast is
                             4.5 m high; down to -0.01 m is sensor noise at the bottom
  ``load_kg``      yes       mass on the forks [kg], >= 0; may change within a run (a pallet
                             picked up)
  ``speed_mps``    no        fork speed as logged by the vehicle [m/s], any finite value
  ``pressure_pa``  no        line pressure [Pa], absolute, >= 0
  ===============  ========  ====================================================================

* the columns may come in any order; names are case-sensitive, surrounding spaces are ignored;
* every value of a known column is a decimal number (``1``, ``-0.5``, ``.25``, ``1e-3``;
  surrounding spaces are ignored).  Empty fields, text, ``nan`` and ``inf`` are errors;
* any other column is kept in :attr:`Log.extra` but not used (as float64 when every value is a
  number, else as strings), and one :class:`UnusedColumnsWarning` names all of them.

What is not a valid log raises :class:`LogError`, whose message names the file, the line
(1-based, the header is line 1) and the column and says what was expected, e.g.::

    data/run.csv, line 17, column 'pwm': expected a value in [0, 1] (duty cycle), got 1.3

Nothing is dropped, repaired or guessed.  When a file has several problems, the one on the
earliest line is reported.  A :class:`Log` built in code is checked the same way; there the
"line" of sample ``i`` is ``i + 2`` (where it would be in a written file) and the message also
gives the array index.
"""

import codecs
import csv
import dataclasses
import io
import os
import re
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

__all__ = [
    "KNOWN_COLUMNS",
    "OPTIONAL_COLUMNS",
    "REQUIRED_COLUMNS",
    "Log",
    "LogError",
    "UnusedColumnsWarning",
    "read_log",
    "validate_arrays",
    "write_log",
]

REQUIRED_COLUMNS: tuple[str, ...] = ("time_s", "pwm", "height_m", "load_kg")
OPTIONAL_COLUMNS: tuple[str, ...] = ("speed_mps", "pressure_pa")
KNOWN_COLUMNS: tuple[str, ...] = REQUIRED_COLUMNS + OPTIONAL_COLUMNS

MIN_SAMPLES = 2  # fewer gives no sample period
JITTER = 0.01  # tolerated deviation of a time step from the sample period, relative
HEIGHT_MIN_M = -0.01  # sensor noise at the bottom of the mast
HEIGHT_MAX_M = 4.6  # the mast is 4.5 m high; a little margin for the sensor
MAST_HEIGHT_M = 4.5

# A decimal number, as written by any logger; deliberately stricter than float() (which also
# takes "1_000", "nan", "inf", "infinity").
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")
_NON_FINITE = re.compile(r"[+-]?(?:nan|inf|infinity)", re.IGNORECASE)
_NOT_DECIMAL_CHAR = re.compile(r"[^0-9eE+\-. \t]")


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
        0-based array index of the sample, given for logs checked in memory.
    name : str | None
        Name of the log, used in the message when there is no path.
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
    ) -> None:
        self.expected = expected
        self.path = path
        self.row = row
        self.column = column
        self.got = got
        self.index = index
        self.name = name
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
        if self.column is not None:
            where.append(f"column {self.column!r}")
        msg = f"{', '.join(where)}: expected {self.expected}"
        if self.got is not None:
            msg += f", got {self.got}"
        return msg

    def __reduce__(self) -> tuple[Any, ...]:
        args = (self.expected, self.path, self.row, self.column, self.got, self.index, self.name)
        return (type(self), args)


class UnusedColumnsWarning(UserWarning):
    """A log has columns that jaxlift does not use; they are kept in :attr:`Log.extra`."""


def _fmt(x: float) -> str:
    return f"{x:.9g}"


def _first(mask: np.ndarray) -> int | None:
    """Index of the first True in ``mask``, or None."""
    if mask.size == 0:
        return None
    i = int(np.argmax(mask))
    return i if mask[i] else None


def _as_column(value: Any, column: str, *, path: str | None, name: str | None) -> np.ndarray:
    """``value`` as a fresh read-only 1-D float64 array, or LogError."""
    try:
        arr = np.asarray(value)
    except (TypeError, ValueError) as e:  # ragged nested sequences and the like
        raise LogError(
            "a 1-D array of numbers", path=path, column=column, got=str(e), name=name
        ) from None
    if arr.dtype.kind not in "biuf":
        got = "None" if value is None else f"an array of dtype {arr.dtype}"
        raise LogError("a 1-D array of numbers", path=path, column=column, got=got, name=name)
    if arr.ndim != 1:
        raise LogError(
            "a 1-D array of numbers",
            path=path,
            column=column,
            got=f"an array of shape {arr.shape}",
            name=name,
        )
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

    Raises
    ------
    LogError
        For the first problem: shape problems first, then the one on the earliest line (ties
        go to the column that comes first in :data:`KNOWN_COLUMNS`).
    """
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
                raise LogError(
                    f"the required column {c!r}", path=path, column=c, got="none", name=name
                )
            continue
        arrays[c] = _as_column(value, c, path=path, name=name)

    n = arrays["time_s"].shape[0]
    for c, a in arrays.items():
        if a.shape[0] != n:
            raise LogError(
                f"{n} values (as many as time_s)",
                path=path,
                column=c,
                got=f"{a.shape[0]}",
                name=name,
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

    # Candidates (line, column rank, error); the earliest line wins.
    found: list[tuple[int, int, LogError]] = []

    def add(i: int | None, column: str, expected: str, got: str) -> None:
        if i is None:
            return
        err = LogError(
            expected,
            path=path,
            row=int(line_of[i]),
            column=column,
            got=got,
            index=i if in_memory else None,
            name=name,
        )
        found.append((int(line_of[i]), KNOWN_COLUMNS.index(column), err))

    with np.errstate(all="ignore"):
        for c, a in arrays.items():
            i = _first(~np.isfinite(a))
            if i is not None:
                tok = None if raw is None or c not in raw else raw[c][i].strip()
                if tok is None:
                    add(i, c, "a finite number", _fmt(a[i]))
                elif tok == "":
                    add(i, c, "a number", "an empty field")
                elif _NUMBER.fullmatch(tok) or _NON_FINITE.fullmatch(tok):
                    add(i, c, "a finite number", repr(tok))
                else:
                    add(i, c, "a number", repr(tok))

        pwm = arrays["pwm"]
        i = _first((pwm < 0.0) | (pwm > 1.0))
        add(i, "pwm", "a value in [0, 1]", "" if i is None else _fmt(pwm[i]))

        h = arrays["height_m"]
        i = _first(h < HEIGHT_MIN_M)
        add(
            i,
            "height_m",
            f"a height of at least {HEIGHT_MIN_M} m (below 0 only by sensor noise at the bottom)",
            "" if i is None else f"{_fmt(h[i])} m",
        )
        i = _first(h > HEIGHT_MAX_M)
        add(
            i,
            "height_m",
            f"a height of at most {HEIGHT_MAX_M} m (the mast is {MAST_HEIGHT_M} m high)",
            "" if i is None else f"{_fmt(h[i])} m",
        )

        m = arrays["load_kg"]
        i = _first(m < 0.0)
        add(i, "load_kg", "a load of at least 0 kg", "" if i is None else f"{_fmt(m[i])} kg")

        if "pressure_pa" in arrays:
            p = arrays["pressure_pa"]
            i = _first(p < 0.0)
            add(
                i,
                "pressure_pa",
                "an absolute pressure of at least 0 Pa",
                "" if i is None else f"{_fmt(p[i])} Pa",
            )

        t = arrays["time_s"]
        dt = np.diff(t)  # dt[k] is the step that ends at sample k + 1
        k = _first(dt <= 0.0)
        if k is not None:
            prev = f"{_fmt(t[k])} s on line {int(line_of[k])}"
            if dt[k] == 0.0:
                got = f"{_fmt(t[k + 1])} s again (a repeated sample)"
            else:
                got = f"{_fmt(t[k + 1])} s (time goes backwards)"
            add(k + 1, "time_s", f"a time later than {prev}", got)

        ok = np.isfinite(dt) & (dt > 0.0)
        if np.any(ok):
            period = float(np.median(dt[ok]))
            expected = (
                f"a time step of {period:.6g} s, the median sample period "
                f"(uniform sampling, jitter under {JITTER:.0%} tolerated)"
            )
            k = _first(ok & (dt > period * (1.0 + JITTER)))
            if k is not None:
                missing = round(float(dt[k]) / period) - 1
                what = (
                    f"a gap, about {missing} sample{'s' if missing > 1 else ''} missing"
                    if missing >= 1
                    else "a late sample"
                )
                got = f"a step of {dt[k]:.6g} s from line {int(line_of[k])} ({what})"
                add(k + 1, "time_s", expected, got)
            k = _first(ok & (dt < period * (1.0 - JITTER)))
            if k is not None:
                got = f"a step of {dt[k]:.6g} s from line {int(line_of[k])} (irregular sampling)"
                add(k + 1, "time_s", expected, got)

    if found:
        raise min(found, key=lambda f: (f[0], f[1]))[2]
    return arrays


def _check_extra(
    extra: Any, n: int, *, path: str | None, name: str | None
) -> dict[str, np.ndarray]:
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


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Log:
    """One test run: samples of the lift, as read from a CSV log (see the module docstring).

    All arrays are read-only float64 copies of shape ``(n,)``; building a ``Log`` checks them
    like :func:`read_log` checks a file (raising :class:`LogError`).
    """

    time_s: np.ndarray  # sample time [s]
    pwm: np.ndarray  # commanded duty cycle [-], in [0, 1]
    height_m: np.ndarray  # fork height [m]
    load_kg: np.ndarray  # mass on the forks [kg]
    speed_mps: np.ndarray | None = None  # logged fork speed [m/s]
    pressure_pa: np.ndarray | None = None  # absolute line pressure [Pa]
    extra: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)  # unused columns
    name: str = "log"  # stem of the file name, for reports
    path: str | None = None

    def __post_init__(self) -> None:
        path = None if self.path is None else os.fsdecode(self.path)
        object.__setattr__(self, "path", path)
        given = {c: getattr(self, c) for c in KNOWN_COLUMNS}
        arrays = validate_arrays(given, path=path, name=self.name)
        for c in KNOWN_COLUMNS:
            object.__setattr__(self, c, arrays.get(c))
        extra = _check_extra(self.extra, self.n, path=path, name=self.name)
        object.__setattr__(self, "extra", extra)

    @property
    def n(self) -> int:
        """Number of samples."""
        return int(self.time_s.shape[0])

    @property
    def sample_period(self) -> float:
        """Median time step [s]."""
        return float(np.median(np.diff(self.time_s)))

    @property
    def duration(self) -> float:
        """Time from the first to the last sample [s]."""
        return float(self.time_s[-1] - self.time_s[0])

    @property
    def columns(self) -> tuple[str, ...]:
        """Names of the columns present, in the order :func:`write_log` writes them."""
        known = tuple(c for c in KNOWN_COLUMNS if getattr(self, c) is not None)
        return known + tuple(self.extra)

    def column(self, name: str) -> np.ndarray:
        """The array of column ``name`` (known or extra); KeyError if absent."""
        if name in KNOWN_COLUMNS and getattr(self, name) is not None:
            return getattr(self, name)
        if name in self.extra:
            return self.extra[name]
        raise KeyError(name)

    def __repr__(self) -> str:
        return (
            f"Log(name={self.name!r}, n={self.n}, sample_period={self.sample_period:.6g} s, "
            f"duration={self.duration:.6g} s, columns={list(self.columns)})"
        )


def _parse_numbers(tokens: Sequence[str]) -> np.ndarray:
    """Decimal numbers -> float64; anything else (text, empty, nan, inf) -> NaN."""
    if not _NOT_DECIMAL_CHAR.search("".join(tokens)):
        # Fast path: on these characters float() takes exactly the decimal numbers (no "nan",
        # "inf" or "1_0" can be spelt), so it may do the checking.
        try:
            return np.array([float(tok) for tok in tokens], dtype=np.float64)
        except ValueError:  # "", "1e", "1.2.3", ...: find them one by one
            pass
    out = np.empty(len(tokens), dtype=np.float64)
    for i, tok in enumerate(tokens):
        s = tok.strip()
        out[i] = float(s) if _NUMBER.fullmatch(s) else np.nan
    return out


def _parse_extra(tokens: Sequence[str]) -> np.ndarray:
    """An unused column: float64 when every value is a number (nan/inf included), else str."""
    values = []
    for tok in tokens:
        s = tok.strip()
        if not (_NUMBER.fullmatch(s) or _NON_FINITE.fullmatch(s)):
            return np.array(list(tokens), dtype=str)
        values.append(float(s))
    return np.array(values, dtype=np.float64)


def read_log(path: str | os.PathLike[str]) -> Log:
    """Read and check one log file (format: see the module docstring).

    Returns a :class:`Log` named after the file's stem.  Raises :class:`LogError` for anything
    that is not a valid log, and warns once (:class:`UnusedColumnsWarning`) about columns that
    are kept but not used.
    """
    p = os.fsdecode(path)
    name = Path(p).stem

    try:
        with open(p, "rb") as f:
            data = f.read()
    except OSError as e:
        raise LogError(
            "a readable log file", path=p, got=f"{type(e).__name__}: {e.strerror or e}"
        ) from None

    skip = len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0
    try:
        text = data[skip:].decode("utf-8")
    except UnicodeDecodeError as e:
        off = skip + e.start
        raise LogError(
            "UTF-8 text",
            path=p,
            row=data.count(b"\n", 0, off) + 1,
            got=f"the byte 0x{data[off]:02x} at byte offset {off} (save the file as UTF-8)",
        ) from None

    required = ", ".join(REQUIRED_COLUMNS)
    if not text.strip():
        raise LogError(
            f"a header row naming the columns ({required}, ...)", path=p, got="an empty file"
        )

    reader = csv.reader(io.StringIO(text, newline=""), strict=True)
    rows: list[list[str]] = []
    starts: list[int] = []
    start = 1
    try:
        while True:
            start = reader.line_num + 1
            try:
                row = next(reader)
            except StopIteration:
                break
            rows.append(row)
            starts.append(start)
    except csv.Error as e:
        raise LogError("well-formed CSV", path=p, row=start, got=str(e)) from None

    header = rows[0]
    if not header:
        raise LogError(
            f"a header row naming the columns ({required}, ...)", path=p, row=1, got="a blank line"
        )
    names = [h.strip() for h in header]
    for j, c in enumerate(names):
        if not c:
            raise LogError(
                "a name for every column", path=p, row=1, got=f"an empty name for field {j + 1}"
            )
    first_field: dict[str, int] = {}
    for j, c in enumerate(names):
        if c in first_field:
            raise LogError(
                "unique column names",
                path=p,
                row=1,
                column=c,
                got=f"{c!r} in fields {first_field[c] + 1} and {j + 1}",
            )
        first_field[c] = j
    for c in REQUIRED_COLUMNS:
        if c not in first_field:
            raise LogError(
                f"a column named {c!r} (required: {required})",
                path=p,
                row=1,
                column=c,
                got="columns " + ", ".join(repr(x) for x in names),
            )

    body, lines = rows[1:], starts[1:]
    while body and not body[-1]:  # blank lines at the end of the file
        body.pop()
        lines.pop()
    for row, line in zip(body, lines, strict=True):
        if len(row) != len(names):
            raise LogError(
                f"{len(names)} fields, one per column of the header",
                path=p,
                row=line,
                got="a blank line" if not row else f"{len(row)} fields",
            )
    if len(body) < MIN_SAMPLES:
        raise LogError(
            f"at least {MIN_SAMPLES} data rows",
            path=p,
            row=(lines[-1] if lines else starts[0]) + 1,
            got=f"{len(body)}",
        )

    fields = list(zip(*body, strict=True))
    raw = {c: fields[j] for c, j in first_field.items() if c in KNOWN_COLUMNS}
    known = {c: _parse_numbers(tokens) for c, tokens in raw.items()}
    arrays = validate_arrays(known, path=p, name=name, lines=lines, raw=raw)
    extra = {c: _parse_extra(fields[j]) for c, j in first_field.items() if c not in KNOWN_COLUMNS}
    if extra:
        warnings.warn(
            f"{p}: column(s) {', '.join(repr(c) for c in extra)} not used (kept in Log.extra)",
            UnusedColumnsWarning,
            stacklevel=2,
        )
    return Log(**arrays, extra=extra, name=name, path=p)


def write_log(path: str | os.PathLike[str], log: Log, *, float_format: str = "%.9g") -> None:
    """Write ``log`` as a CSV file that :func:`read_log` reads back.

    Columns: the required ones, then ``speed_mps`` and ``pressure_pa`` where present, then the
    extra columns in their order.  Numbers are written with ``float_format`` (``%``-style),
    strings as they are; UTF-8 without byte-order mark, ``\\n`` line ends.  The same log gives
    the same bytes.  If the numbers, rounded to ``float_format``, would no longer make a valid
    log (e.g. time steps collapsing), :class:`LogError` is raised and nothing is written.
    """
    p = os.fsdecode(path)
    try:
        float_format % 1.0
    except (TypeError, ValueError) as e:
        raise ValueError(f"float_format {float_format!r} cannot format a number: {e}") from None

    names = log.columns
    text: list[list[str]] = []
    for c in names:
        arr = log.column(c)
        if arr.dtype.kind in "biuf":
            text.append([float_format % v for v in arr.tolist()])
        else:
            text.append([str(v) for v in arr.tolist()])

    # What read_log will see: check it now, so a written log always reads back.
    try:
        reread = {
            c: _parse_numbers(col) for c, col in zip(names, text, strict=True) if c in KNOWN_COLUMNS
        }
        validate_arrays(
            reread,
            path=p,
            name=log.name,
            raw={c: col for c, col in zip(names, text, strict=True) if c in KNOWN_COLUMNS},
        )
    except LogError as e:
        raise LogError(
            f"{e.expected} after rounding with float_format={float_format!r} (use more digits)",
            path=e.path,
            row=e.row,
            column=e.column,
            got=e.got,
            index=e.index,
            name=e.name,
        ) from None

    with open(p, "w", encoding="utf-8", newline="") as f:
        writer = csv.writer(f, lineterminator="\n")
        writer.writerow(names)
        writer.writerows(zip(*text, strict=True))
