"""The report of ``motion register`` in a real browser: headless Chromium renders the page
(offline, from the file) to a screenshot that is not blank, with the title's dark text at the
top and the embedded figures drawn, and its DOM has every picture the template produces.

Skipped where Chromium is not installed (``.ci/run`` installs it on Debian)."""

from __future__ import annotations

import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import cv2
import pytest

from motion.registration.report import KEY_FRAMES

CHROMIUM = shutil.which("chromium")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="needs chromium on PATH (Debian: apt-get install chromium)"
)

WIDTH, HEIGHT = 1100, 3000
#: the report's figures outside the key frames: time correspondence, heat map, fit per frame
FIGURES = 3


def _chromium(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    """Headless Chromium with nothing that reaches the network (as root: no sandbox)."""
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        f"--window-size={WIDTH},{HEIGHT}",
        *args,
    ]
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)


class _Page(HTMLParser):
    """The h1's text and the <img> sources of a page."""

    def __init__(self):
        super().__init__()
        self.h1 = ""
        self.images: list[str] = []
        self._in_h1 = False

    def handle_starttag(self, tag, attrs):
        if tag == "h1":
            self._in_h1 = True
        if tag == "img":
            self.images.append(dict(attrs).get("src") or "")

    def handle_endtag(self, tag):
        if tag == "h1":
            self._in_h1 = False

    def handle_data(self, data):
        if self._in_h1:
            self.h1 += data


def _parse(text: str) -> _Page:
    page = _Page()
    page.feed(text)
    return page


@pytest.fixture(scope="module")
def report(register_run) -> Path:
    assert register_run.rc == 0, register_run.stderr
    return register_run.out / "report.html"


def test_screenshot_is_not_blank(report, tmp_path):
    png = tmp_path / "report.png"
    done = _chromium(tmp_path, f"--screenshot={png}", report.as_uri())
    assert done.returncode == 0, done.stderr[-2000:]
    assert png.is_file(), done.stderr[-2000:]
    image = cv2.imread(str(png), cv2.IMREAD_COLOR)  # BGR
    assert image is not None
    assert image.shape[1] == WIDTH
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    assert float(grey.std()) > 20, "the page looks blank"
    # the title and the line under it: dark text on the light page, at the top
    top = grey[:120]
    assert int((top < 80).sum()) > 300, "no dark text at the top of the page"
    # the embedded figures are drawn: the heat map's reds and blues (diverging colour map),
    # which no text or frame of the page has
    b, g, r = (image[..., i].astype(int) for i in range(3))
    red = (r > 150) & (g < 90) & (b < 90)
    blue = (b > 120) & (r < 90) & (g < 140)
    assert int(red.sum()) > 200 and int(blue.sum()) > 200, "the figures were not drawn"


def test_dom_has_the_title_and_every_picture(report, tmp_path):
    done = _chromium(tmp_path, "--dump-dom", report.as_uri())
    assert done.returncode == 0, done.stderr[-2000:]
    dom = _parse(done.stdout)
    source = _parse(report.read_text(encoding="utf-8"))
    assert re.sub(r"\s+", " ", dom.h1).strip() == re.sub(r"\s+", " ", source.h1).strip()
    assert dom.h1.startswith("Registration of cam1.avi")
    # the three figures and one picture per key frame, each an embedded PNG
    assert len(dom.images) == len(source.images) == FIGURES + KEY_FRAMES
    assert all(src.startswith("data:image/png;base64,") for src in dom.images)
