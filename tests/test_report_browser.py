"""report.html renders in headless Chromium (Debian's `chromium`) with every figure loaded.

Two looks: `--dump-dom` of a copy of the report with a small inline script that writes, once
the page has loaded, how many <img> have a decoded bitmap (naturalWidth > 0) into the title;
and a full-page screenshot that must not be blank (it is kept as report-screenshot.png in the
test's folder, and copied to $REPORT_SCREENSHOT when that is set, for CI artefacts)."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from matplotlib.image import imread
from test_report import small_run, write_run

from reports.build import build_report

CHROMIUM = shutil.which("chromium") or (
    "/usr/bin/chromium" if Path("/usr/bin/chromium").exists() else None
)
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="install Debian's chromium (apt-get install chromium)"
)

# Runs after load: count images whose bitmap decoded; the title carries the verdict.
PROBE = """<script>
window.addEventListener("load", () => {
  const imgs = Array.from(document.images);
  const ok = imgs.filter((i) => i.complete && i.naturalWidth > 0).length;
  document.title = "IMAGES " + ok + "/" + imgs.length;
});
</script>"""


def chromium(args: list[str], home: Path) -> subprocess.CompletedProcess[str]:
    assert CHROMIUM is not None
    cmd = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",  # runs as root in CI containers
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={home}",
        "--window-size=1280,4000",
        *args,
    ]
    # A private HOME and no D-Bus session keep it from touching the user's profile.
    env = {**os.environ, "HOME": str(home)}
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120, env=env, check=False)


def test_report_html_renders_every_figure(tmp_path: Path) -> None:
    folder = write_run(tmp_path, small_run())
    build_report(folder)
    html = (folder / "report.html").read_text()
    n_img = html.count("<img ")
    assert n_img >= 8

    probe = folder / "probe.html"
    probe.write_text(html.replace("</body>", PROBE + "</body>"))
    dom = chromium(
        ["--virtual-time-budget=10000", "--dump-dom", probe.as_uri()], tmp_path / "chrome1"
    )
    assert dom.returncode == 0, dom.stderr[-2000:]
    title = re.search(r"<title>(.*?)</title>", dom.stdout)
    assert title is not None, dom.stdout[:500]
    assert title.group(1) == f"IMAGES {n_img}/{n_img}"

    shot = folder / "report-screenshot.png"
    run = chromium([f"--screenshot={shot}", (folder / "report.html").as_uri()], tmp_path / "c2")
    assert run.returncode == 0 and shot.is_file(), run.stderr[-2000:]
    img = imread(shot)
    assert img.shape[0] == 4000 and img.shape[1] == 1280
    gray = img[..., :3].mean(axis=2)
    # Not blank: a good share of rows carry ink (text, tables, figures), and colour varies.
    rows_with_ink = float(np.mean((gray < 0.9).any(axis=1)))
    assert rows_with_ink > 0.3, rows_with_ink
    assert float(gray.std()) > 0.05
    if os.environ.get("REPORT_SCREENSHOT"):
        shutil.copyfile(shot, os.environ["REPORT_SCREENSHOT"])
