"""Measurement logs of the lift: reading, checking and writing one test run.

Format
------
One test run of one vehicle is one file (see ``docs/data.md``): CSV (below), Parquet
(:mod:`jaxlift.model.log_parquet`) or MDF 4 (:mod:`jaxlift.model.log_mdf`), with the same
columns and checks.  A CSV file is:

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
  ``pressure_pa``  no        line pressure [Pa], **gauge** (above atmosphere, as hydraulic
                             transducers report it; the model's ``p`` is gauge too), at least
                             -101325 Pa (vacuum); slightly negative values are a transducer's
                             noise near atmospheric pressure
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

Two options of :func:`read_log` apply to every format: a channel map, for files whose
columns (channels) are named otherwise (:func:`~jaxlift.model.log_validation.channel_sources`),
and resampling of jittered time stamps onto a uniform clock, only when asked
(:mod:`jaxlift.model.log_resample`).
"""

import codecs
import csv
import dataclasses
import io
import os
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

from .log_mdf import MDF_SUFFIXES, read_mdf_columns
from .log_parquet import PARQUET_SUFFIXES, read_parquet_columns
from .log_resample import resample_columns, resample_period
from .log_validation import (
    JITTER,
    KNOWN_COLUMNS,
    MIN_SAMPLES,
    NON_FINITE,
    NOT_DECIMAL_CHAR,
    NUMBER,
    REQUIRED_COLUMNS,
    RESAMPLE_JITTER,
    LogError,
    UnusedColumnsWarning,
    channel_sources,
    check_extra,
    find_columns,
    read_bytes,
    validate_arrays,
)

# A decimal number, as written by any logger; deliberately stricter than float() (which also
# takes "1_000", "nan", "inf", "infinity").


@dataclasses.dataclass(frozen=True, eq=False, repr=False)
class Log:
    """One test run: samples of the lift, as read from a log file (see the module docstring).

    All arrays are read-only float64 copies of shape ``(n,)``; building a ``Log`` checks them
    like :func:`read_log` checks a file (raising :class:`LogError`).
    """

    time_s: np.ndarray  # sample time [s]
    pwm: np.ndarray  # commanded duty cycle [-], in [0, 1]
    height_m: np.ndarray  # fork height [m]
    load_kg: np.ndarray  # mass on the forks [kg]
    speed_mps: np.ndarray | None = None  # logged fork speed [m/s]
    pressure_pa: np.ndarray | None = None  # gauge line pressure [Pa] (above atmosphere)
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
        extra = check_extra(self.extra, self.n, path=path, name=self.name)
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
    if not NOT_DECIMAL_CHAR.search("".join(tokens)):
        # Fast path: on these characters float() takes exactly the decimal numbers (no "nan",
        # "inf" or "1_0" can be spelt), so it may do the checking.
        try:
            return np.array([float(tok) for tok in tokens], dtype=np.float64)
        except ValueError:  # "", "1e", "1.2.3", ...: find them one by one
            pass
    out = np.empty(len(tokens), dtype=np.float64)
    for i, tok in enumerate(tokens):
        s = tok.strip()
        out[i] = float(s) if NUMBER.fullmatch(s) else np.nan
    return out


def _parse_extra(tokens: Sequence[str]) -> np.ndarray:
    """An unused column: float64 when every value is a number (nan/inf included), else str."""
    values = []
    for tok in tokens:
        s = tok.strip()
        if not (NUMBER.fullmatch(s) or NON_FINITE.fullmatch(s)):
            return np.array(list(tokens), dtype=str)
        values.append(float(s))
    return np.array(values, dtype=np.float64)


def read_log(
    path: str | os.PathLike[str],
    *,
    channel_map: Mapping[str, str] | None = None,
    resample: float | None = None,
) -> Log:
    """Read and check one log file (format: see the module docstring and ``docs/data.md``).

    The format follows the file name's ending: ``.parquet`` or ``.pq`` is Parquet (typed
    columns, :mod:`jaxlift.model.log_parquet`), ``.mf4`` or ``.mdf`` is ASAM MDF (channels,
    :mod:`jaxlift.model.log_mdf`), anything else CSV.  Every format has the same columns,
    units and checks.

    Parameters
    ----------
    path
        The log file.
    channel_map
        Log column -> name of the column or channel in the file, for the columns a logger
        names otherwise, e.g. ``{"height_m": "WireSensor", "pwm": "ValveDuty"}``.  Columns
        not named keep their own name (``time_s``, ``pwm``, ``height_m``, ``load_kg``,
        ``speed_mps``, ``pressure_pa``); in an MDF file without a ``time_s`` channel the
        time is the master channel.  Values must still be in the columns' SI units.  A
        mapped optional column that the file lacks is simply absent.
    resample
        Sample period [s] to resample onto, or ``None`` (default) to take the samples as
        logged, where a time step more than 1 % off the sample period is an error.  With a
        period, time steps may be up to 50 % off (a longer step is still a gap, an error);
        the samples are carried onto ``t0 + k * resample``: height, speed and pressure by
        linear interpolation (continuous physical signals), pwm and load by zero-order
        hold, the last value logged (a command and a mass, piecewise constant: a value
        between two logged ones was never commanded nor on the forks); see
        :mod:`jaxlift.model.log_resample`.

    Returns
    -------
    Log
        Named after the file's stem; its columns under their log names.

    Raises
    ------
    LogError
        For anything that is not a valid log, naming the file, the line or sample, and the
        column (and the channel, where the file names it otherwise).
    ValueError
        For a ``channel_map`` that is not one, or a ``resample`` period that is not > 0.

    Warns
    -----
    UnusedColumnsWarning
        Once, naming the columns (channels) that are kept in :attr:`Log.extra` but not used.
    """
    p = os.fsdecode(path)
    name = Path(p).stem
    sources = channel_sources(channel_map)
    dt = None if resample is None else resample_period(resample)
    jitter = JITTER if dt is None else RESAMPLE_JITTER
    suffix = Path(p).suffix.lower()
    not_kept: list[str] = []
    if suffix in PARQUET_SUFFIXES:
        arrays, extra = read_parquet_columns(p, name, sources, jitter=jitter)
    elif suffix in MDF_SUFFIXES:
        arrays, extra, not_kept = read_mdf_columns(
            p, name, sources, mapped=tuple(channel_map or ()), jitter=jitter
        )
    else:
        arrays, extra = _read_csv_columns(p, name, sources, jitter=jitter)
    if dt is not None:
        arrays, extra = resample_columns(arrays, extra, dt, path=p, name=name)
    _warn_unused(p, extra, not_kept)
    return Log(**arrays, extra=extra, name=name, path=p)


def _read_csv_columns(
    p: str, name: str, sources: Mapping[str, str], *, jitter: float
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
    """The checked known columns and the extra columns of the CSV log at ``p``."""
    data = read_bytes(p)

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
    found = find_columns(names, sources, path=p, row=1)
    column_of = {src: c for c, src in found.items()}  # name in the file -> log column

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
    raw = {column_of[x]: fields[j] for x, j in first_field.items() if x in column_of}
    known = {c: _parse_numbers(tokens) for c, tokens in raw.items()}
    channels = {c: src for c, src in found.items() if src != c}
    arrays = validate_arrays(
        known, path=p, name=name, lines=lines, raw=raw, channels=channels, jitter=jitter
    )
    extra = {x: _parse_extra(fields[j]) for x, j in first_field.items() if x not in column_of}
    return arrays, extra


def _warn_unused(p: str, extra: dict, not_kept: Sequence[str] = ()) -> None:
    """One UnusedColumnsWarning, pointing at the caller of :func:`read_log`."""
    parts = []
    if extra:
        parts.append(f"column(s) {', '.join(repr(c) for c in extra)} not used (kept in Log.extra)")
    if not_kept:
        parts.append(
            f"channel(s) {', '.join(repr(c) for c in not_kept)} not used and not kept (recorded "
            "on another clock, or neither numbers nor text)"
        )
    if parts:
        warnings.warn(f"{p}: {'; '.join(parts)}", UnusedColumnsWarning, stacklevel=3)


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
