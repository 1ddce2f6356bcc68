"""Fuzzing the log readers (hypothesis, derandomized: the same examples every run):
whatever the bytes of a CSV file, the columns of a Parquet file or the channels of an
MDF 4 file (read as they are, and resampled), ``read_log`` returns a valid ``Log`` or
raises ``LogError`` naming the file, never another exception, a NaN or a silent drop."""

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from asammdf import MDF, Signal
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import jaxlift as jl

COLUMNS = ["time_s", "pwm", "height_m", "load_kg", "speed_mps", "pressure_pa"]
SETTINGS = settings(
    max_examples=150, deadline=None, derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)  # fmt: skip
TOKENS = ["", " ", "nan", "inf", "-inf", "1e400", "abc", "1,5", '"', "0x10", "1_000", "--1",
          "１", "\x00", "-0.0", "2.5", "1e-3", ".5", "7"]  # fmt: skip


def _valid_rows(n, cols):
    t = np.round(np.arange(n) * 0.01, 9)
    vals = {"time_s": t, "pwm": np.linspace(0, 0.6, n), "height_m": np.linspace(0, 1, n),
            "load_kg": np.full(n, 500.0), "speed_mps": np.full(n, 0.02),
            "pressure_pa": np.full(n, 1e6)}  # fmt: skip
    return [[f"{vals[c][i]:.9g}" for c in cols] for i in range(n)]


@st.composite
def csv_bytes(draw):
    cols = draw(st.permutations(COLUMNS).map(lambda p: p[: 4 + (len(p) - 4) // 2]))
    cols = list(cols) + draw(st.lists(st.sampled_from(["note", "x", "time_s"]), max_size=1))
    n = draw(st.integers(0, 12))
    rows = _valid_rows(n, [c if c in COLUMNS else "time_s" for c in cols])
    header = list(cols)
    for _ in range(draw(st.integers(0, 3))):
        op = draw(st.sampled_from(["cell", "drop_field", "add_field", "blank", "header",
                                   "swap_rows", "quote"]))  # fmt: skip
        full = [r for r in rows if r]
        if op == "cell" and full:
            row = full[draw(st.integers(0, len(full) - 1))]
            j = draw(st.integers(0, len(row) - 1))
            row[j] = draw(st.one_of(st.sampled_from(TOKENS), st.text(max_size=5)))
        elif op == "drop_field" and full:
            full[draw(st.integers(0, len(full) - 1))].pop()
        elif op == "add_field" and rows:
            rows[draw(st.integers(0, len(rows) - 1))].append("1")
        elif op == "blank" and rows:
            rows.insert(draw(st.integers(0, len(rows))), [])
        elif op == "header":
            header[draw(st.integers(0, len(header) - 1))] = draw(st.sampled_from(TOKENS))
        elif op == "swap_rows" and len(rows) > 1:
            rows[0], rows[-1] = rows[-1], rows[0]
        elif op == "quote" and full:
            full[0][0] = '"' + full[0][0]
    eol = draw(st.sampled_from(["\n", "\r\n"]))
    text = eol.join(",".join(r) for r in [header, *rows]) + draw(st.sampled_from(["", eol]))
    data = text.encode("utf-8", errors="surrogatepass")
    if draw(st.booleans()):
        data = b"\xef\xbb\xbf" + data
    if draw(st.integers(0, 9)) == 0:
        k = draw(st.integers(0, max(len(data) - 1, 0)))
        data = data[:k] + b"\xff" + data[k:]
    return data


def _check(path, **options):
    try:
        with np.errstate(all="raise"):
            log = jl.read_log(path, **options)
    except jl.LogError as err:
        assert str(err).startswith(str(path)), err
        return None
    for c in log.columns:
        col = log.column(c)
        if col.dtype.kind == "f":
            assert np.all(np.isfinite(col))
    assert log.n >= 2 and np.all(np.diff(log.time_s) > 0)
    return log


@SETTINGS
@given(data=csv_bytes())
def test_any_csv_bytes_give_a_log_or_a_named_error(tmp_path, data):
    path = tmp_path / "fuzz.csv"
    path.write_bytes(data)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jl.UnusedColumnsWarning)
        _check(path)


@st.composite
def parquet_tables(draw):
    n = draw(st.integers(0, 10))
    cols = draw(st.lists(st.sampled_from(COLUMNS + ["note"]), min_size=1, max_size=7,
                         unique=True))  # fmt: skip
    rows = _valid_rows(n, [c if c in COLUMNS else "time_s" for c in cols])
    arrays = {}
    for j, c in enumerate(cols):
        vals = [float(r[j]) for r in rows]
        kind = draw(st.sampled_from(["float", "float", "int", "string", "null", "weird"]))
        if kind == "int":
            arrays[c] = pa.array([int(v) for v in vals], pa.int64())
        elif kind == "string":
            arrays[c] = pa.array([str(v) for v in vals], pa.string())
        elif kind == "null" and n:
            vals[draw(st.integers(0, n - 1))] = None
            arrays[c] = pa.array(vals, pa.float64())
        elif kind == "weird" and n:
            vals[draw(st.integers(0, n - 1))] = draw(
                st.sampled_from([float("nan"), float("inf"), -1.0, 5.0, 1e300])
            )
            arrays[c] = pa.array(vals, pa.float64())
        else:
            arrays[c] = pa.array(vals, pa.float64())
    return pa.table(arrays)


@SETTINGS
@given(table=parquet_tables())
def test_any_parquet_table_gives_a_log_or_a_named_error(tmp_path, table):
    path = tmp_path / "fuzz.parquet"
    pq.write_table(table, path)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jl.UnusedColumnsWarning)
        _check(path)


@st.composite
def mdf_groups(draw):
    """Channel groups ``[(time stamps, {name: Signal keyword arguments})]`` of an MDF 4
    file, and how many bytes of the written file to keep (None: all)."""
    n = draw(st.integers(0, 10))
    t = np.round(np.arange(n) * 0.01, 9)
    if n > 1 and draw(st.booleans()):
        k = draw(st.integers(1, n - 1))
        t[k:] += draw(st.sampled_from([-0.02, -0.01, 0.002, 0.03, 1.0]))  # back, repeat, ...
    cols = [c for c in ("pwm", "height_m", "load_kg") if draw(st.integers(0, 19))]  # mostly
    cols += draw(st.lists(st.sampled_from(["time_s", "speed_mps", "pressure_pa", "note"]),
                          max_size=3, unique=True))  # fmt: skip
    rows = _valid_rows(n, [c if c in COLUMNS else "time_s" for c in cols])
    main, other = {}, {}
    for j, c in enumerate(cols):
        vals = np.array([float(r[j]) for r in rows])
        kind = draw(st.sampled_from(["float"] * 12 + ["int", "text", "weird", "weird",
                                                      "invalid", "other_clock"]))  # fmt: skip
        kw: dict = {"samples": vals}
        if kind == "int":
            kw = {"samples": vals.astype(np.int64)}
        elif kind == "text" and n:
            kw = {"samples": np.array([f"{v:g}".encode() for v in vals]), "encoding": "utf-8"}
        elif kind == "weird" and n:
            vals[draw(st.integers(0, n - 1))] = draw(
                st.sampled_from([np.nan, np.inf, -1.0, 5.0, -2e5, 1e300])
            )
        elif kind == "invalid" and n:
            bits = np.zeros(n, bool)
            bits[draw(st.integers(0, n - 1))] = True
            kw = {"samples": vals, "invalidation_bits": bits}
        if kind == "other_clock" and n > 1:
            other[c] = {"samples": vals[:-1]}
        else:
            main[c] = kw
    groups = [(t, main)] + ([(t[:-1] + 0.001, other)] if other else [])
    keep = (
        draw(st.one_of(st.none(), st.integers(0, 4000))) if draw(st.integers(0, 4)) == 0 else None
    )
    return groups, keep


def _write_mdf(path, spec):
    groups, keep = spec
    with MDF(version="4.10") as mdf:
        for t, chans in groups:
            if chans:
                mdf.append([Signal(timestamps=t, name=c, **kw) for c, kw in chans.items()])
        mdf.save(path, overwrite=True)
    if keep is not None:
        path.write_bytes(path.read_bytes()[:keep])  # a damaged (cut) file


@SETTINGS
@given(spec=mdf_groups())
def test_any_mdf_channels_give_a_log_or_a_named_error(tmp_path, spec):
    path = tmp_path / "fuzz.mf4"
    _write_mdf(path, spec)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", jl.UnusedColumnsWarning)
        _check(path)
        _check(path, resample=0.01)  # resampling gives a valid log or a named error too


def test_fuzzer_reaches_both_outcomes(tmp_path):
    """The generators are not vacuous: among their first examples some files are valid
    logs and some are refused (checked on the fixed examples of ``derandomize``)."""
    outcomes = set()

    @SETTINGS
    @given(data=csv_bytes())
    def collect(data):
        path = tmp_path / "c.csv"
        path.write_bytes(data)
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", jl.UnusedColumnsWarning)
            outcomes.add(_check(path) is not None)

    collect()
    assert outcomes == {True, False}

    mdf_outcomes = set()

    @SETTINGS
    @given(spec=mdf_groups())
    def collect_mdf(spec):
        path = tmp_path / "c.mf4"
        _write_mdf(path, spec)
        mdf_outcomes.add(_check(path) is not None)

    collect_mdf()
    assert mdf_outcomes == {True, False}


pytestmark = pytest.mark.filterwarnings("ignore::jaxlift.UnusedColumnsWarning")
