"""Parquet logs: read like CSV logs (same arrays, same checks), errors naming the file,
column and row."""

import warnings

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import jaxlift as jl


@pytest.fixture
def csv_log(tmp_path):
    t = np.round(np.arange(50) * 0.01, 9)
    log = jl.Log(time_s=t, pwm=np.where(t > 0.1, 0.4, 0.0), height_m=0.2 + 0.01 * t,
                 load_kg=np.full(50, 500.0), speed_mps=np.full(50, 0.01), name="run")  # fmt: skip
    jl.write_log(tmp_path / "run.csv", log)
    return jl.read_log(tmp_path / "run.csv")


def _table(log, **changes):
    cols = {c: log.column(c) for c in log.columns}
    cols.update(changes)
    return pa.table(cols)


def test_parquet_reads_like_csv(tmp_path, csv_log):
    pq.write_table(_table(csv_log, note=pa.array(["a"] * 50)), tmp_path / "run.parquet")
    with pytest.warns(jl.UnusedColumnsWarning, match="'note'"):
        log = jl.read_log(tmp_path / "run.parquet")
    for c in csv_log.columns:
        np.testing.assert_array_equal(log.column(c), csv_log.column(c))
    assert log.name == "run" and log.extra["note"][0] == "a"
    # integer columns are numbers too
    pq.write_table(_table(csv_log, load_kg=pa.array([500] * 50, pa.int32())), tmp_path / "i.pq")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert jl.read_log(tmp_path / "i.pq").load_kg.dtype == np.float64


@pytest.mark.parametrize(
    "change, message",
    [
        ({"pwm": pa.array(["0.1"] * 50)}, "column 'pwm': expected a numeric column"),
        ({"pwm": pa.array([0.0] * 7 + [None] + [0.0] * 42, pa.float64())},
         "line 9 (array index 7), column 'pwm': expected a number, got a missing value"),
        ({"pwm": pa.array([0.0] * 10 + [1.3] + [0.0] * 39)},
         "line 12 (array index 10), column 'pwm': expected a value in [0, 1]"),
        ({"height_m": pa.array([0.0] * 20 + [float("nan")] + [0.0] * 29)}, "column 'height_m'"),
    ],
)  # fmt: skip
def test_bad_parquet_values_are_named(tmp_path, csv_log, change, message):
    path = tmp_path / "bad.parquet"
    pq.write_table(_table(csv_log, **change), path)
    with pytest.raises(jl.LogError) as err:
        jl.read_log(path)
    assert str(path) in str(err.value) and message in str(err.value)


def test_bad_parquet_files_are_named(tmp_path, csv_log):
    missing = tmp_path / "nope.parquet"
    with pytest.raises(jl.LogError, match="nope.parquet: expected a readable log file"):
        jl.read_log(missing)
    garbage = tmp_path / "garbage.parquet"
    garbage.write_bytes(b"time_s,pwm\n0,0\n")
    with pytest.raises(jl.LogError, match="garbage.parquet: expected a Parquet file"):
        jl.read_log(garbage)
    cols = {c: csv_log.column(c) for c in csv_log.columns if c != "load_kg"}
    pq.write_table(pa.table(cols), tmp_path / "noload.parquet")
    with pytest.raises(jl.LogError, match="column 'load_kg': expected a column named 'load_kg'"):
        jl.read_log(tmp_path / "noload.parquet")
    pq.write_table(_table(csv_log).slice(0, 1), tmp_path / "short.parquet")
    with pytest.raises(jl.LogError, match="at least 2 rows"):
        jl.read_log(tmp_path / "short.parquet")
