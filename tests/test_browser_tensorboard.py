"""TensorBoard in a real browser: a tiny oracle run, ``tensorboard`` serving it, headless Chromium
(the Debian package, driven by playwright; no browser is ever downloaded) opening the Time Series
(scalars) and HParams dashboards and finding the run's data in them.

Needs ``/usr/bin/chromium`` (``apt-get install -y chromium``) and the ``playwright`` Python package
(``pip install -e '.[browser]'``); skipped with that reason otherwise. Screenshots go to
``$DVSLAND_SCREENSHOT_DIR`` (default ``logs/screenshots/``): ``tensorboard_scalars.png`` and
``tensorboard_hparams.png``.
"""

from __future__ import annotations

import os
import shutil
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
CHROMIUM = next((p for p in ("/usr/bin/chromium", shutil.which("chromium") or "", shutil.which("chromium-browser") or "")
                 if p and os.path.exists(p)), None)
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]

try:
    import playwright.sync_api  # noqa: F401

    HAVE_PLAYWRIGHT = True
except ImportError:
    HAVE_PLAYWRIGHT = False

pytestmark = [
    pytest.mark.browser,
    pytest.mark.skipif(CHROMIUM is None, reason="no Chromium at /usr/bin/chromium: apt-get install -y chromium"),
    pytest.mark.skipif(not HAVE_PLAYWRIGHT, reason="the playwright package is missing: pip install -e '.[browser]'"),
]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def tensorboard_url(tmp_path_factory):
    """A finished 8 s oracle flight on site D (two descents), served by tensorboard on localhost."""
    from dvsland.sim import simulate

    run = simulate(None, estimator="oracle", sites="D", out=tmp_path_factory.mktemp("browser") / "run", quiet=True,
                   overrides=["simulation.t_max_s=8", "logging.figures=false"])
    assert run.status == "complete"
    port = _free_port()
    log = open(run.run_dir / "tensorboard.log", "w")
    proc = subprocess.Popen([sys.executable, "-m", "tensorboard.main", "--logdir", str(run.run_dir / "tb"),
                             "--host", "127.0.0.1", "--port", str(port), "--reload_interval", "0"],
                            stdout=log, stderr=subprocess.STDOUT)
    url = f"http://127.0.0.1:{port}"
    try:
        deadline = time.time() + 60
        while True:
            try:
                with urllib.request.urlopen(url + "/data/runs", timeout=2) as r:
                    if b"D_Kp5e6-n5" in r.read():
                        break
            except OSError:
                pass
            if proc.poll() is not None or time.time() > deadline:
                pytest.fail("tensorboard did not start: " + (run.run_dir / "tensorboard.log").read_text()[-2000:])
            time.sleep(0.5)
        yield url
    finally:
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


@pytest.fixture(scope="module")
def page():
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS)
        pg = browser.new_page(viewport={"width": 1600, "height": 1000})
        pg.set_default_timeout(45_000)
        yield pg
        browser.close()


def _shots() -> Path:
    d = Path(os.environ.get("DVSLAND_SCREENSHOT_DIR", REPO / "logs" / "screenshots"))
    d.mkdir(parents=True, exist_ok=True)
    return d


def test_scalars_dashboard_shows_the_run(tensorboard_url, page):
    page.goto(tensorboard_url + "/#timeseries")
    # the run selector lists both descents, and the altitude card plots them against flight time (ms)
    page.get_by_text("D_Kp5e6-n5").first.wait_for()
    page.get_by_text("D_Kp4e6-n10").first.wait_for()
    card = page.locator("card-view", has_text="altitude_m").first
    card.wait_for()
    card.locator("canvas, svg").first.wait_for()
    page.wait_for_timeout(1500)  # let the charts draw before the screenshot
    text = page.inner_text("body")
    assert "altitude_m" in text and "divergence" in text and "outcome" in text
    # the data table of the card: last point at flight time 8 s -> step 8,000 (ms), relative 8 s
    assert "8,000" in text or "7,900" in text or "7,500" in text, text[:3000]
    page.screenshot(path=str(_shots() / "tensorboard_scalars.png"))


def _visible(page, text: str):
    """The first visible element showing ``text`` (open shadow DOMs included; the other
    dashboards stay in the page, hidden)."""
    loc = page.get_by_text(text).filter(visible=True).first
    loc.wait_for()
    return loc


def test_hparams_dashboard_lists_each_descent(tensorboard_url, page):
    page.goto(tensorboard_url + "/#hparams")
    # one row per descent (the trial ID is the run folder), its settings, and the outcome metrics
    for want in ("D_Kp5e6-n5", "D_Kp4e6-n10", "Kp5e6-n5", "kp_n_per_s", "5.0000e+6", "4.0000e+6", "oracle",
                 "outcome/success", "outcome/lowest_altitude_m", "outcome/t_end_s"):
        _visible(page, want)
    page.wait_for_timeout(500)
    page.screenshot(path=str(_shots() / "tensorboard_hparams.png"))
