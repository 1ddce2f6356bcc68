"""The report page as a browser shows it: headless Chromium decodes every embedded
figure (issue #15: a report mailed to a colleague arrives with its pictures). Skipped
where no Chromium is installed; `.ci/run` installs Debian's where it can."""

from __future__ import annotations

import shutil
import subprocess

import matplotlib
import pytest

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

from jaxlift.report.document import Report  # noqa: E402

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium on this machine")

# after the page has loaded, its title says how many images the browser decoded and
# how many collapsed tables are open
PROBE = """<script>
window.addEventListener("load", () => {
  const imgs = [...document.images];
  const ok = imgs.filter((i) => i.complete && i.naturalWidth > 0).length;
  const open = [...document.querySelectorAll("details")].filter((d) => d.open).length;
  document.title = `decoded ${ok} of ${imgs.length}; open ${open}`;
});
</script></body>"""


def _figure(path, k):
    fig, ax = plt.subplots(figsize=(3, 2))
    ax.plot([0, 1, 2], [0, k, 0])
    fig.savefig(path, dpi=50)
    plt.close(fig)
    return path


def _title_in_browser(html_text, tmp_path):
    probe = tmp_path / "probe.html"
    probe.write_text(html_text.replace("</body>", PROBE), encoding="utf-8")
    out = subprocess.run(
        [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
         "--no-first-run", "--disable-background-networking", "--disable-component-update",
         "--disable-sync", f"--user-data-dir={tmp_path / 'profile'}",
         "--virtual-time-budget=5000", "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=180, check=False,
    )  # fmt: skip
    start = out.stdout.find("<title>")
    assert start >= 0, out.stderr[-2000:]
    return out.stdout[start + 7 : out.stdout.find("</title>", start)]


def test_every_embedded_figure_decodes_in_a_browser(tmp_path):
    rep = Report("browser check")
    rep.figure(_figure(tmp_path / "a.png", 1.0), "first")
    rep.table([{"point": k, "stable": True} for k in range(72)], collapsed="every point")
    rep.figure(_figure(tmp_path / "b.png", 2.0), "second")
    _, html_path = rep.write(tmp_path / "out")
    (tmp_path / "a.png").unlink()  # the page must not need the files beside it
    (tmp_path / "b.png").unlink()
    text = open(html_path, encoding="utf-8").read()
    assert _title_in_browser(text, tmp_path) == "decoded 2 of 2; open 0"
    # the check can fail: a damaged picture is not decoded
    broken = text.replace("data:image/png;base64,iVBOR", "data:image/png;base64,AAAA", 1)
    assert _title_in_browser(broken, tmp_path) == "decoded 1 of 2; open 0"
