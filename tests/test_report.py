"""Tests of the report builder jaxlift.report.document."""

from __future__ import annotations

import base64
import math
import os

import numpy as np
import pytest

from jaxlift.report.document import Report, format_value, markdown_inline_to_html

ROWS = [
    {"group": "all", "n": 12901, "rms_speed_mmps": 3.14159, "bias_speed_mmps": -0.0123},
    {"group": "slow", "n": np.int64(7596), "rms_speed_mmps": np.float64(10.5), "extra": "a|b"},
    {"group": "fast", "n": 1814, "rms_speed_mmps": math.nan},
]


def _png(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 16)
    return path


def _report(fig):
    rep = Report("Calibration <of> lift_500kg")
    rep.heading("Where the model fails")
    rep.text(
        "The **baseline** misses the oscillation in `stage 3` & below <2 Hz>.\n\n"
        "- first point\n- second **point**"
    )
    rep.table(ROWS, caption="RMS errors per group")
    rep.table(ROWS, columns=["group", "rms_speed_mmps"], floatfmt=".2f")
    rep.figure(fig, "Residuals of the fit")
    return rep


def test_report_writes_markdown_and_html(tmp_path):
    out = tmp_path / "out"
    fig = _png(out / "figures" / "residuals.png")
    md_path, html_path = _report(fig).write(out)
    assert md_path == os.fspath(out / "report.md")
    assert html_path == os.fspath(out / "report.html")
    md = open(md_path, encoding="utf-8").read()
    ht = open(html_path, encoding="utf-8").read()

    # markdown: title, heading, pipe tables with formatted values, relative image link
    assert md.startswith("# Calibration <of> lift_500kg\n")
    assert "## Where the model fails" in md
    assert "| group | n | rms_speed_mmps | bias_speed_mmps | extra |" in md
    assert "|---|---:|---:|---:|---|" in md
    assert "| all | 12901 | 3.14 | -0.0123 |  |" in md
    assert "| slow | 7596 | 10.5 |  | a\\|b |" in md
    assert "| fast | 1814 | – |  |  |" in md
    assert "| all | 3.14 |" in md and "| slow | 10.50 |" in md
    assert "*RMS errors per group*" in md
    assert "![Residuals of the fit](figures/residuals.png)" in md
    assert "The **baseline** misses" in md

    # html: standalone, escaped, tables, figures embedded
    assert ht.startswith("<!DOCTYPE html>")
    assert "<style>" in ht and "</html>" in ht
    assert "<title>Calibration &lt;of&gt; lift_500kg</title>" in ht
    assert "<h2>Where the model fails</h2>" in ht
    assert (
        "<p>The <strong>baseline</strong> misses the oscillation in <code>stage 3</code> "
        "&amp; below &lt;2 Hz&gt;.</p>"
    ) in ht
    assert "<ul><li>first point</li><li>second <strong>point</strong></li></ul>" in ht
    assert '<td class="num">3.14</td>' in ht
    assert '<td class="num">10.50</td>' in ht
    assert "<td>a|b</td>" in ht
    assert "<caption>RMS errors per group</caption>" in ht
    png = base64.b64encode((out / "figures" / "residuals.png").read_bytes()).decode("ascii")
    assert f'<img src="data:image/png;base64,{png}" alt="Residuals of the fit">' in ht
    assert "figures/residuals.png" not in ht  # a mailed report needs no folder beside it
    assert "<figcaption>Residuals of the fit</figcaption>" in ht
    assert "<2 Hz>" not in ht and "<of>" not in ht


def test_report_is_deterministic_and_links_relative(tmp_path, monkeypatch):
    out = tmp_path / "out"
    fig = _png(out / "fig one.png")
    a = _report(fig).write(out, stem="a")
    b = _report(fig).write(out, stem="b")
    for pa, pb in zip(a, b, strict=True):
        with open(pa, "rb") as fa, open(pb, "rb") as fb:
            assert fa.read() == fb.read()
    md = open(a[0], encoding="utf-8").read()
    assert "](fig%20one.png)" in md
    # a relative path from the current directory, and one given relative to the out dir
    monkeypatch.chdir(tmp_path)
    rep = Report("t").figure("out/fig one.png", "x").figure("figures/later.png", "y")
    md = open(rep.write("out")[0], encoding="utf-8").read()
    assert "![x](fig%20one.png)" in md
    assert "![y](figures/later.png)" in md
    html_text = open(rep.write("out")[1], encoding="utf-8").read()
    assert 'src="figures/later.png"' in html_text  # not written yet: linked
    assert html_text.count("data:image/png;base64,") == 1  # the one that exists: embedded


def test_a_long_table_can_be_collapsed_in_html_and_survives_read_and_include(tmp_path):
    rep = Report("t")
    rep.table(ROWS, collapsed="every point: **3** rows")
    rep.table(ROWS[:1])
    ht = rep.to_html(tmp_path)
    opened = ht.index("<details><summary>every point: <strong>3</strong> rows</summary>")
    closed = ht.index("</details>")
    assert opened < ht.index("<td>slow</td>") < closed  # the collapsed table's rows inside
    assert ht.count("<details>") == 1  # the other table stays open
    assert ht.rindex("<table>") > closed
    assert "| slow | 7596 |" in rep.to_markdown(tmp_path)  # Markdown shows it whole
    rep.write(tmp_path / "a")
    outer = Report("outer").include(Report.read(tmp_path / "a"))
    assert outer.to_html(tmp_path).count("<details><summary>every point") == 1


def test_format_value_and_inline_markdown():
    assert format_value(math.nan) == "–"
    assert format_value(None) == ""
    assert format_value(True) == "True"
    assert format_value(3) == "3"
    assert format_value(np.float32(0.5)) == "0.5"
    assert format_value(1234567.0) == "1.23e+06"
    assert format_value(math.inf) == "inf"
    assert format_value("x") == "x"
    assert markdown_inline_to_html("a <b> **c** `d**e**`") == (
        "a &lt;b&gt; <strong>c</strong> <code>d**e**</code>"
    )
    with pytest.raises(ValueError):
        Report("t").heading("x", level=7)


def test_air_histogram_zooms_on_the_posterior_and_points_to_a_far_threshold():
    """A posterior 0.01 % wide beside the 1 % bleeding threshold was drawn as a sliver:
    the axis now spans the posterior, and the threshold only where it is near."""
    from jaxlift.report.posterior import air_axis

    rng = np.random.default_rng(0)
    narrow = rng.normal(0.12, 0.004, 4000)  # percent
    x0, x1, shown = air_axis(narrow, 1.0)
    assert not shown and x0 < 0.11 and 0.13 < x1 < 0.2  # the posterior fills the axis
    wide = rng.normal(0.8, 0.2, 4000)
    x0, x1, shown = air_axis(wide, 1.0)
    assert shown and x0 < 0.3 and x1 > 1.0


def test_summary_points_to_the_tuning_section_by_its_title():
    """The one-line robust verdict sends the reader to the per-case figures: by the title
    the combined report gives the tuning section, not by a number written twice."""
    from jaxlift.workflows.report import SECTION_TITLES, STAGES, write_summary

    summary = {
        "quick": False, "verdict": "none", "screen": None, "missing_effects": [],
        "evidence": [], "reasons": [], "chi2_nominal": 9.0, "chi2_baseline": 1.1,
        "chi2_final": None, "air": None, "beta": None, "posterior_mode": "mcmc",
        "posterior_converged": True, "gains": {"Kp": 1.0, "Ki": 0.5, "Kd": 0.0},
        "gains_name": "robust", "cost_current": 2.0, "cost_recommended": 1.0,
        "robust_verdict": {"short": "robust gains: better on 9 of 10 draws", "text": "-"},
    }  # fmt: skip
    rep = Report("summary")
    write_summary(rep, summary, held_out=[])
    text = rep.to_markdown()
    assert "Robust gains: better on 9 of 10 draws" in text
    assert f"section “{SECTION_TITLES['tune']}”" in text
    # the sections are numbered in the order the report includes them
    assert [SECTION_TITLES[s].split(".")[0] for s in STAGES] == ["1", "2", "3", "4"]
