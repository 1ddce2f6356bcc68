"""Logs as MDF files (ASAM MDF 4, also MDF 3, as automotive data loggers write them):
the same columns, units and checks as the CSV format (docs/data.md), channels instead of
columns, read with ``asammdf``.

* The log's columns are channels, found by name through the channel map
  (:func:`~jaxlift.model.log_validation.channel_sources`; by default the column names
  themselves). A name must occur once among the file's channels (master channels aside).
* ``time_s`` is a channel named ``time_s`` (or what the channel map names) if the file
  has one, else the time (master) channel of the channel group that holds the data.
* Every channel of the log must be recorded at the same instants (the same time stamps:
  one channel group, or groups on one clock). A channel on another clock is refused,
  with or without resampling.
* A known channel must be numeric (integer or floating point, physical values after the
  file's conversions) and have no sample marked invalid (MDF 4 invalidation bits).
* Other channels on the log's clock are kept in :attr:`Log.extra` (numbers as float64,
  invalid samples as NaN; text as strings); channels on another clock, or with samples
  that are neither, are not kept. Both are named once in an
  :class:`~jaxlift.model.log_validation.UnusedColumnsWarning`.

Errors name the file, the channel (and the log column it was read as) and the 0-based
sample index, e.g.::

    runs/agv7.mf4, sample index 7, channel 'pwm': expected a value in [0, 1], got 1.3
"""

import io
import re
import traceback
from collections.abc import Collection, Mapping

import numpy as np
from asammdf import MDF

from .log_validation import (
    JITTER,
    KNOWN_COLUMNS,
    REQUIRED_COLUMNS,
    LogError,
    find_columns,
    read_bytes,
    validate_arrays,
)

#: File name endings read as MDF by :func:`jaxlift.read_log`.
MDF_SUFFIXES = (".mf4", ".mdf")

_SYNC_TIME = 1  # MDF 4 cn_sync_type of a time master channel
_BYTESIO = re.compile(r'"?<_io\.BytesIO object at 0x[0-9a-fA-F]+>"? ?')


def _disarm(err: BaseException) -> None:
    """Let asammdf's half-built reader objects of a failed open be collected quietly.

    When ``MDF(...)`` fails on a damaged file, the half-initialised reader's ``__del__``
    raises AttributeError later (printed as "Exception ignored in ..."); marking it closed
    makes its ``close()`` a no-op. Nothing was opened that needs closing: the file was read
    into memory first."""
    for frame, _ in traceback.walk_tb(err.__traceback__):
        obj = frame.f_locals.get("self")
        if obj is not None and type(obj).__module__.startswith("asammdf"):
            try:
                obj._closed = True
            except AttributeError:  # slots or properties: nothing to disarm
                pass


def _describe(exc: Exception) -> str:
    kind = type(exc).__name__
    if kind == "error":  # struct.error and the like: say whose
        kind = f"{type(exc).__module__}.{kind}"
    return f"{kind}: {_BYTESIO.sub('', str(exc))}"


def _open(p: str) -> MDF:
    data = read_bytes(p)
    if not data:
        raise LogError("an MDF file (ASAM MDF 4 or 3)", path=p, got="an empty file")
    try:
        return MDF(io.BytesIO(data))
    # asammdf parses untrusted bytes and fails on damaged files with whatever the parser
    # met (MdfException, struct.error, ValueError, IndexError, ...): all mean "not MDF".
    except Exception as e:
        _disarm(e)
        raise LogError("an MDF file (ASAM MDF 4 or 3)", path=p, got=_describe(e)) from None


def read_mdf_columns(
    p: str,
    name: str,
    sources: Mapping[str, str] | None = None,
    mapped: Collection[str] = (),
    *,
    jitter: float = JITTER,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], list[str]]:
    """The checked known columns, the extra columns and the names of the channels not kept,
    of the MDF log at ``p`` (:func:`jaxlift.read_log` builds the :class:`~jaxlift.Log`).

    Parameters
    ----------
    p, name
        The file and the log's name (for messages).
    sources
        Log column -> channel name (:func:`~jaxlift.model.log_validation.channel_sources`);
        default: the column names.
    mapped
        The log columns the user's channel map names (an explicitly mapped ``time_s`` must
        exist; the default one falls back on the master channel).
    jitter
        Tolerated relative deviation of a time step from the sample period.

    Raises
    ------
    LogError
        For anything that is not a valid log.
    """
    sources = {c: c for c in KNOWN_COLUMNS} if sources is None else dict(sources)
    with _open(p) as mdf:
        try:
            return _read(mdf, p, name, sources, set(mapped), jitter)
        except LogError:
            raise
        except Exception as e:  # a damaged data block, found only when read
            raise LogError("a readable MDF file", path=p, got=_describe(e)) from None


def _channel_list(names: list[str]) -> str:
    shown = ", ".join(repr(n) for n in names[:30])
    return (f"channels {shown}" + (", ..." if len(names) > 30 else "")) if names else "none"


def _read(mdf, p, name, sources, mapped, jitter):
    masters: dict[int, int] = dict(mdf.masters_db)
    where: dict[str, list[tuple[int, int]]] = {}  # channel name -> (group, index), no masters
    for g, group in enumerate(mdf.groups):
        for i, ch in enumerate(group.channels):
            if masters.get(g) != i:
                where.setdefault(ch.name, []).append((g, i))
    names = list(where)

    data_cols = [c for c in KNOWN_COLUMNS if c != "time_s"]
    required = tuple(c for c in REQUIRED_COLUMNS if c != "time_s")
    found = find_columns(
        names, sources, path=p, kind="channel", required=required,
        note="the time is a channel named 'time_s' or the time (master) channel",
    )  # fmt: skip
    for c, src in found.items():
        if len(where[src]) > 1:
            groups = ", ".join(str(g) for g, _ in where[src])
            raise LogError(
                "a channel name that occurs once (master channels aside)", path=p, column=c,
                channel=src, got=f"{src!r} in channel groups {groups}",
            )  # fmt: skip

    signals = {}
    for c in [*data_cols, "time_s"]:
        if c in found:
            g, i = where[found[c]][0]
            signals[c] = (g, i, mdf.get(group=g, index=i, ignore_invalidation_bits=True))

    ref = next(c for c in data_cols if c in signals)  # pwm: a required channel
    g_ref, _, sig_ref = signals[ref]
    t_ref = np.asarray(sig_ref.timestamps)
    channels = dict(found)
    known: dict[str, np.ndarray] = {}
    invalid: list[tuple[int, int, LogError]] = []
    for c, (g, _, sig) in signals.items():
        src = found[c]
        samples = np.asarray(sig.samples)
        if samples.dtype.kind not in "biuf" or samples.ndim != 1:
            raise LogError(
                "a numeric channel (integer or floating point)", path=p, column=c, channel=src,
                got=f"samples of type {samples.dtype} and shape {samples.shape}",
            )  # fmt: skip
        ts = np.asarray(sig.timestamps)
        if c != ref and not (ts.shape == t_ref.shape and np.array_equal(ts, t_ref)):
            raise LogError(
                f"the time stamps of channel {found[ref]!r} (group {g_ref}: every channel of "
                "a log recorded at the same instants)", path=p, column=c, channel=src,
                got=f"{_clock(ts)} in group {g} (another clock)",
            )  # fmt: skip
        bits = sig.invalidation_bits
        if bits is not None and np.any(np.asarray(bits)):
            k = int(np.argmax(np.asarray(bits)))
            err = LogError("a valid sample", path=p, column=c, channel=src, index=k,
                           got="a sample marked invalid (invalidation bit set)")  # fmt: skip
            invalid.append((k, KNOWN_COLUMNS.index(c), err))
        known[c] = samples.astype(np.float64)
    if invalid:
        raise min(invalid, key=lambda e: (e[0], e[1]))[2]

    if "time_s" not in found:
        if "time_s" in mapped and sources["time_s"] != _master_name(mdf, g_ref):
            raise LogError(
                f"a channel named {sources['time_s']!r} (the channel map's time_s)", path=p,
                column="time_s", channel=sources["time_s"], got=_channel_list(names),
            )  # fmt: skip
        master = _time_master(mdf, p, g_ref, found[ref])
        known["time_s"] = t_ref.astype(np.float64)
        channels["time_s"] = master

    arrays = validate_arrays(known, path=p, name=name, rows=False, channels=channels, jitter=jitter)
    extra, not_kept = _extras(mdf, where, set(found.values()), t_ref)
    return arrays, extra, not_kept


def _clock(ts: np.ndarray) -> str:
    if ts.size == 0:
        return "no samples"
    return f"{ts.size} samples from {ts[0]:.6g} s to {ts[-1]:.6g} s"


def _master_name(mdf, g: int) -> str | None:
    i = mdf.masters_db.get(g)
    return None if i is None else mdf.groups[g].channels[i].name


def _time_master(mdf, p: str, g: int, ref_channel: str) -> str:
    """Name of the time master channel of group ``g``; LogError if it has none."""
    i = mdf.masters_db.get(g)
    if i is None:
        raise LogError(
            f"a time (master) channel in the channel group of {ref_channel!r} (group {g}), "
            "or a channel named 'time_s'", path=p, column="time_s", got="none",
        )  # fmt: skip
    ch = mdf.groups[g].channels[i]
    sync = getattr(ch, "sync_type", _SYNC_TIME)  # MDF 3 masters are time
    if sync != _SYNC_TIME:
        raise LogError(
            f"a time master channel in the channel group of {ref_channel!r} (group {g})",
            path=p, column="time_s", channel=ch.name,
            got=f"a master channel of sync type {sync} (not time: angle, distance or index)",
        )  # fmt: skip
    return ch.name


def _extras(mdf, where, used, t_ref):
    """Unused channels on the log's clock (kept) and the names of the others (not kept)."""
    extra: dict[str, np.ndarray] = {}
    not_kept: list[str] = []
    for n, entries in where.items():
        if n in used:
            continue
        for g, i in entries:
            key = n if len(entries) == 1 else f"{n} [group {g}, channel {i}]"
            sig = mdf.get(group=g, index=i, ignore_invalidation_bits=True)
            values = _extra_values(sig, t_ref)
            if values is None:
                not_kept.append(key)
            else:
                extra[key] = values
    return extra, not_kept


def _extra_values(sig, t_ref: np.ndarray) -> np.ndarray | None:
    ts, samples = np.asarray(sig.timestamps), np.asarray(sig.samples)
    if samples.ndim != 1 or ts.shape != t_ref.shape or not np.array_equal(ts, t_ref):
        return None
    bits = sig.invalidation_bits
    bad = np.zeros(samples.shape, bool) if bits is None else np.asarray(bits, dtype=bool)
    if samples.dtype.kind in "biuf":
        out = samples.astype(np.float64)
        out[bad] = np.nan
        return out
    if samples.dtype.kind == "S":
        return np.array([b.decode("utf-8", errors="replace") for b in samples.tolist()])
    if samples.dtype.kind == "U":
        return samples.astype(str)
    return None
