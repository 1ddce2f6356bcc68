"""Tests of the log reader/writer (jaxlift.model.log); numpy only, no JAX."""

import pickle
import re
import warnings

import numpy as np
import pytest

from jaxlift.model.log import Log, read_log, write_log
from jaxlift.model.log_validation import LogError, UnusedColumnsWarning, validate_arrays

HEADER = "time_s,pwm,height_m,load_kg,speed_mps,pressure_pa"
N_ROWS = 10  # data rows of the template: lines 2..11


def template_lines(n: int = N_ROWS) -> list[str]:
    """A valid log as text lines (line k of the file is element k - 1)."""
    lines = [HEADER]
    for i in range(n):
        lines.append(f"{0.01 * i:.2f},0.5,{0.1 * i:.1f},250,0.1,{1e5 + i:.0f}")
    return lines


def set_field(lines: list[str], line: int, column: str, value: str) -> list[str]:
    """Replace one field (file line number ``line``, column name ``column``)."""
    out = list(lines)
    header = out[0].split(",")
    fields = out[line - 1].split(",")
    fields[header.index(column)] = value
    out[line - 1] = ",".join(fields)
    return out


def make_log(n: int = 50, **kw) -> Log:
    rng = np.random.default_rng(0)
    cols = dict(
        time_s=0.02 * np.arange(n),
        pwm=rng.uniform(0, 1, n),
        height_m=np.linspace(0.0, 4.5, n),
        load_kg=np.full(n, 300.0),
        speed_mps=rng.normal(0.0, 0.3, n),
        pressure_pa=rng.uniform(1e5, 2e7, n),
    )
    cols.update(kw)
    return Log(**cols)


def write_text(tmp_path, text: str | bytes, name: str = "run.csv"):
    path = tmp_path / name
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8", newline="")
    return path


def join(lines: list[str]) -> str:
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- valid files


def test_read_template(tmp_path):
    path = write_text(tmp_path, join(template_lines()))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = read_log(path)
    assert log.n == N_ROWS
    assert log.name == "run"
    assert log.path == str(path)
    assert log.sample_period == pytest.approx(0.01)
    assert log.duration == pytest.approx(0.09)
    assert log.time_s.dtype == np.float64
    np.testing.assert_allclose(log.height_m, 0.1 * np.arange(N_ROWS))
    assert log.columns == ("time_s", "pwm", "height_m", "load_kg", "speed_mps", "pressure_pa")
    assert log.extra == {}
    assert "n=10" in repr(log)


def test_round_trip_and_deterministic_bytes(tmp_path):
    log = make_log(extra={"temp_c": np.linspace(20, 30, 50), "note": np.array(["a,b", "x"] * 25)})
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    write_log(a, log)
    write_log(b, log)
    assert a.read_bytes() == b.read_bytes()
    with pytest.warns(UnusedColumnsWarning):
        back = read_log(a)
    for c in ("time_s", "pwm", "height_m", "load_kg", "speed_mps", "pressure_pa"):
        np.testing.assert_allclose(getattr(back, c), getattr(log, c), rtol=1e-8, atol=1e-15)
    np.testing.assert_allclose(back.extra["temp_c"], log.extra["temp_c"], rtol=1e-8)
    np.testing.assert_array_equal(back.extra["note"], log.extra["note"])
    assert list(back.extra) == ["temp_c", "note"]
    assert back.name == "a"
    # writing what was read gives the same bytes again
    with pytest.warns(UnusedColumnsWarning):
        write_log(b, read_log(a))
    assert a.read_bytes() == b.read_bytes()
    assert a.read_bytes().startswith(b"time_s,pwm,height_m,load_kg,speed_mps,pressure_pa,")


def test_round_trip_required_only(tmp_path):
    log = make_log(speed_mps=None, pressure_pa=None)
    path = tmp_path / "req.csv"
    write_log(path, log, float_format="%.17g")
    back = read_log(path)
    assert back.speed_mps is None and back.pressure_pa is None
    for c in ("time_s", "pwm", "height_m", "load_kg"):
        np.testing.assert_array_equal(getattr(back, c), getattr(log, c))
    assert path.read_text(encoding="utf-8").splitlines()[0] == "time_s,pwm,height_m,load_kg"


def test_write_refuses_too_few_digits(tmp_path):
    log = make_log(time_s=1000.0 + 0.001 * np.arange(50))
    path = tmp_path / "coarse.csv"
    with pytest.raises(LogError, match="float_format") as e:
        write_log(path, log, float_format="%.4g")
    assert e.value.column == "time_s"
    assert not path.exists()


def test_tolerated_variants(tmp_path):
    """BOM, CRLF, spaces, column order, jitter under 1 %, blank lines at the end."""
    t = 0.01 * np.arange(8) + np.array([0, 4e-5, -3e-5, 2e-5, 0, 4e-5, 0, -4e-5])
    rows = [" pwm , time_s,load_kg,height_m"]
    rows += [f" 0.25 ,{ti:.6f},0,-0.01" for ti in t]
    data = b"\xef\xbb\xbf" + ("\r\n".join(rows) + "\r\n\r\n\n").encode()
    path = write_text(tmp_path, data)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        log = read_log(path)
    np.testing.assert_allclose(log.time_s, t, atol=1e-9)
    np.testing.assert_array_equal(log.pwm, 0.25)
    np.testing.assert_array_equal(log.height_m, -0.01)


def test_unused_columns_warn_once_and_are_kept(tmp_path):
    lines = [HEADER + ",oil_temp_c,operator"]
    lines += [line + f",{40 + i},bob" for i, line in enumerate(template_lines()[1:])]
    path = write_text(tmp_path, join(lines))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        log = read_log(path)
    unused = [w for w in caught if issubclass(w.category, UnusedColumnsWarning)]
    assert len(unused) == 1
    assert len(caught) == 1
    message = str(unused[0].message)
    assert "oil_temp_c" in message and "operator" in message and "run.csv" in message
    assert unused[0].filename == __file__  # points at the caller
    np.testing.assert_array_equal(log.extra["oil_temp_c"], 40.0 + np.arange(N_ROWS))
    assert log.extra["oil_temp_c"].dtype == np.float64
    assert list(log.extra["operator"]) == ["bob"] * N_ROWS


def test_log_arrays_are_read_only_copies():
    t = 0.1 * np.arange(5)
    log = make_log(n=5, time_s=t)
    assert log.time_s is not t
    with pytest.raises(ValueError):
        log.pwm[0] = 0.3
    with pytest.raises(AttributeError):
        log.pwm = np.zeros(5)


# --------------------------------------------------------------------------- bad files

T = template_lines()
BAD_FILES = {
    # id: (content, line, column, text the message must contain)
    "empty-file": (b"", None, None, "empty file"),
    "blank-file": ("\n\n", None, None, "empty file"),
    "not-utf8": (join(T[:4]).encode() + b"0.03,0.5,0.3,250,\xff,1\n", 5, None, "UTF-8"),
    "latin1-header": (("time_s,pwm,höhe_m\n").encode("latin-1"), 1, None, "UTF-8"),
    "header-only": (HEADER + "\n", 2, None, "at least 2 data rows"),
    "one-data-row": (join(T[:2]), 3, None, "at least 2 data rows"),
    "blank-header": (join([""] + T[1:]), 1, None, "header"),
    "missing-column": (
        join([",".join(f.split(",")[:3]) for f in T]),
        1,
        "load_kg",
        "a column named 'load_kg'",
    ),
    "duplicate-column": (join([HEADER + ",pwm"] + [r + ",0.5" for r in T[1:]]), 1, "pwm", "unique"),
    "empty-column-name": (join([HEADER + ","] + [r + "," for r in T[1:]]), 1, None, "name"),
    "too-few-fields": (join(T[:6] + ["0.05,0.5,0.5,250,0.1"] + T[7:]), 7, None, "6 fields"),
    "too-many-fields": (join(T[:6] + [T[6] + ",1"] + T[7:]), 7, None, "got 7 fields"),
    "blank-line-inside": (join(T[:6] + [""] + T[6:]), 7, None, "blank line"),
    "unclosed-quote": (join(T[:6] + ['0.05,"0.5,0.5,250,0.1,1'] + T[7:]), 7, None, "CSV"),
    "text": (join(set_field(T, 7, "pwm", "abc")), 7, "pwm", "expected a number, got 'abc'"),
    "empty-value": (join(set_field(T, 7, "load_kg", "")), 7, "load_kg", "empty field"),
    "spaces-value": (join(set_field(T, 7, "load_kg", "  ")), 7, "load_kg", "empty field"),
    "underscore": (join(set_field(T, 7, "load_kg", "2_50")), 7, "load_kg", "'2_50'"),
    "decimal-comma": (join(set_field(T, 7, "height_m", '"0,6"')), 7, "height_m", "'0,6'"),
    "nan": (join(set_field(T, 7, "height_m", "nan")), 7, "height_m", "finite"),
    "NaN-time": (join(set_field(T, 7, "time_s", "NaN")), 7, "time_s", "finite"),
    "inf": (join(set_field(T, 7, "pwm", "inf")), 7, "pwm", "finite"),
    "-inf": (join(set_field(T, 7, "load_kg", "-inf")), 7, "load_kg", "finite"),
    "overflow": (join(set_field(T, 7, "height_m", "1e999")), 7, "height_m", "finite"),
    "speed-text": (join(set_field(T, 7, "speed_mps", "fast")), 7, "speed_mps", "'fast'"),
    "speed-nan": (join(set_field(T, 7, "speed_mps", "nan")), 7, "speed_mps", "finite"),
    "pressure-inf": (join(set_field(T, 7, "pressure_pa", "inf")), 7, "pressure_pa", "finite"),
    "pressure-below-vacuum": (
        join(set_field(T, 7, "pressure_pa", "-2e5")),
        7,
        "pressure_pa",
        "gauge pressure of at least -101325 Pa",
    ),
    "time-backwards": (join(set_field(T, 7, "time_s", "0.03")), 7, "time_s", "backwards"),
    "time-repeats": (join(set_field(T, 7, "time_s", "0.04")), 7, "time_s", "repeated"),
    "time-gap": (
        join(T[:6] + T[8:]),  # the rows of 0.05 and 0.06 s are missing
        7,
        "time_s",
        "a time step of 0.01 s",
    ),
    "time-jitter-2pct": (join(set_field(T, 7, "time_s", "0.0502")), 7, "time_s", "0.0102 s"),
    "time-short-step": (join(set_field(T, 7, "time_s", "0.045")), 7, "time_s", "irregular"),
    "pwm-above-1": (join(set_field(T, 7, "pwm", "1.3")), 7, "pwm", "[0, 1], got 1.3"),
    "pwm-negative": (join(set_field(T, 7, "pwm", "-0.1")), 7, "pwm", "[0, 1], got -0.1"),
    "load-negative": (join(set_field(T, 7, "load_kg", "-5")), 7, "load_kg", "at least 0 kg"),
    "height-too-low": (join(set_field(T, 7, "height_m", "-0.02")), 7, "height_m", "-0.01 m"),
    "height-too-high": (join(set_field(T, 7, "height_m", "4.7")), 7, "height_m", "4.5 m high"),
    "earliest-line-wins": (
        join(set_field(set_field(T, 9, "pwm", "2"), 5, "load_kg", "x")),
        5,
        "load_kg",
        "'x'",
    ),
}


@pytest.mark.parametrize("case", list(BAD_FILES))
def test_bad_file(tmp_path, case):
    content, line, column, text = BAD_FILES[case]
    path = write_text(tmp_path, content, name="bad_run.csv")
    with pytest.raises(LogError) as e:
        read_log(path)
    err = e.value
    message = str(err)
    assert isinstance(err, ValueError)
    assert message.startswith(str(path))
    assert "bad_run.csv" in message
    assert err.path == str(path)
    assert err.row == line
    if line is not None:
        assert re.search(rf"\bline {line}\b", message), message
    assert err.column == column
    if column is not None:
        assert f"column '{column}'" in message, message
    assert text in message, message
    assert "expected" in message
    assert err.__cause__ is None and (err.__context__ is None or err.__suppress_context__)


def test_missing_file(tmp_path):
    path = tmp_path / "nowhere.csv"
    with pytest.raises(LogError, match=r"nowhere\.csv.*readable.*FileNotFoundError") as e:
        read_log(path)
    assert e.value.row is None


def test_directory_is_not_a_log(tmp_path):
    with pytest.raises(LogError, match="readable") as e:
        read_log(tmp_path)
    assert e.value.path == str(tmp_path)


def test_gap_message_names_period_and_missing_samples(tmp_path):
    content, *_ = BAD_FILES["time-gap"]
    with pytest.raises(LogError) as e:
        read_log(write_text(tmp_path, content))
    assert "about 2 samples missing" in str(e.value)
    assert "from line 6" in str(e.value)


def test_log_error_pickles():
    err = LogError("a value in [0, 1]", path="x.csv", row=17, column="pwm", got="1.3")
    assert str(err) == "x.csv, line 17, column 'pwm': expected a value in [0, 1], got 1.3"
    back = pickle.loads(pickle.dumps(err))
    assert str(back) == str(err) and back.row == 17 and back.column == "pwm"


# --------------------------------------------------------------------------- bad arrays

n = 20
REQUIRED = ("time_s", "pwm", "height_m", "load_kg")
BAD_ARRAYS = {
    # id: (overrides, row, column, text)
    "pwm-above-1": ({"pwm": np.r_[np.zeros(3), 1.5, np.zeros(n - 4)]}, 5, "pwm", "index 3"),
    "nan-height": ({"height_m": np.r_[np.zeros(7), np.nan, np.zeros(n - 8)]}, 9, "height_m", "nan"),
    "inf-speed": ({"speed_mps": np.r_[np.inf, np.zeros(n - 1)]}, 2, "speed_mps", "inf"),
    "negative-load": ({"load_kg": np.r_[np.zeros(n - 1), -1.0]}, n + 1, "load_kg", "0 kg"),
    "time-repeats": ({"time_s": np.r_[0.0, 0.0, 0.1 * np.arange(1, n - 1)]}, 3, "time_s", "again"),
    "time-gap": (
        {"time_s": np.r_[0.1 * np.arange(10), 2.0 + 0.1 * np.arange(n - 10)]},
        12,
        "time_s",
        "gap",
    ),
    "below-vacuum": ({"pressure_pa": np.full(n, -1.1e5)}, 2, "pressure_pa", "-101325 Pa"),
    "length-mismatch": ({"pwm": np.zeros(n - 1)}, None, "pwm", f"expected {n} values"),
    "two-dimensional": ({"height_m": np.zeros((n, 2))}, None, "height_m", "shape (20, 2)"),
    "strings": ({"load_kg": np.array(["1"] * n)}, None, "load_kg", "dtype <U1"),
    "none-required": ({"pwm": None}, None, "pwm", "required column 'pwm'"),
    "too-short": (
        {**{c: np.zeros(1) for c in REQUIRED}, "speed_mps": None, "pressure_pa": None},
        None,
        None,
        "at least 2 samples",
    ),
    "extra-known-name": ({"extra": {"pwm": np.zeros(n)}}, None, "pwm", "Log.extra"),
    "extra-wrong-length": ({"extra": {"x": np.zeros(3)}}, None, "x", "shape (3,)"),
    "extra-empty-name": ({"extra": {"": np.zeros(n)}}, None, None, "column name"),
}


@pytest.mark.parametrize("case", list(BAD_ARRAYS))
def test_bad_arrays(case):
    overrides, row, column, text = BAD_ARRAYS[case]
    cols = dict(
        time_s=0.1 * np.arange(n),
        pwm=np.zeros(n),
        height_m=np.zeros(n),
        load_kg=np.zeros(n),
        speed_mps=np.zeros(n),
        pressure_pa=np.full(n, 1e5),
    )
    cols.update(overrides)
    with pytest.raises(LogError) as e:
        Log(**cols, name="built")
    err = e.value
    assert err.row == row
    assert err.column == column
    message = str(err)
    assert message.startswith("log 'built'")
    assert text in message, message
    if row is not None:
        assert re.search(rf"\bline {row} \(array index {row - 2}\)", message), message


def test_bad_arrays_with_path_name_the_file():
    with pytest.raises(LogError, match=r"^data/x\.csv, line 4 \(array index 2\), column 'pwm'"):
        make_log(n=5, pwm=np.array([0, 0, 2.0, 0, 0]), path="data/x.csv")


def test_validate_arrays_uses_given_lines():
    cols = {
        "time_s": [0.0, 1.0, 2.0],
        "pwm": [0, 0, 0],
        "height_m": [0, 0, 0],
        "load_kg": [0, -1, 0],
    }
    with pytest.raises(LogError) as e:
        validate_arrays(cols, path="f.csv", lines=[2, 5, 6])
    assert e.value.row == 5 and e.value.index is None
    out = validate_arrays({**cols, "load_kg": [0, 1, 0]})
    assert set(out) == {"time_s", "pwm", "height_m", "load_kg"}
    assert all(a.dtype == np.float64 and not a.flags.writeable for a in out.values())
    with pytest.raises(LogError, match="unknown column 'foo'"):
        validate_arrays({**cols, "foo": [1, 2, 3]})
