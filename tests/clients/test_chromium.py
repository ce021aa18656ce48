"""Chromium (headless) renders report.html, and its embedded preview images show up."""

from __future__ import annotations

import matplotlib.image as mpimg
import numpy as np
import pytest
from clientlib import foreground_fraction, require, run

WIDTH, HEIGHT = 1300, 4000


@pytest.fixture(scope="module")
def screenshot(outputs: dict, tmp_path_factory):
    out = outputs["dir"]
    png = out / "report_screenshot.png"
    profile = tmp_path_factory.mktemp("chromium-profile")
    run([require("chromium"), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         f"--user-data-dir={profile}", f"--window-size={WIDTH},{HEIGHT}", "--hide-scrollbars",
         f"--screenshot={png}", (out / "report.html").as_uri()], out)
    return png


def test_report_renders_with_images(screenshot) -> None:
    img = mpimg.imread(screenshot)[..., :3]
    assert img.shape[:2] == (HEIGHT, WIDTH)
    assert foreground_fraction(screenshot) > 0.2
    # Text and tables are black/grey on white and the warning box is pale yellow; saturated
    # blue and orange only come from the embedded previews (surface rendering, component slices).
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    orange = (r > 0.8) & (g > 0.3) & (g < 0.6) & (b < 0.2)
    blue = (b > 0.55) & (r < 0.3)
    assert orange.mean() > 0.005 and blue.mean() > 0.005
    rows = np.flatnonzero(orange.any(axis=1))
    assert rows.min() < HEIGHT // 2  # the first preview (surface rendering) is near the top


def test_report_title_and_warning_in_page_text(outputs: dict) -> None:
    proc = run([require("chromium"), "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking", "--disable-component-update",
                "--disable-sync", f"--user-data-dir={outputs['dir'] / 'chromium-dom'}", "--dump-dom",
                (outputs["dir"] / "report.html").as_uri()], outputs["dir"])
    dom = proc.stdout
    assert "frepvdb run: spheres" in dom
    assert "12 voxels near the medial axis clamped" in dom
    assert dom.count("data:image/png;base64,") == len(outputs["previews"])
