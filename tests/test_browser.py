"""In a real browser (headless Chromium driven by Selenium): upload a tile on the
landing page, follow the job page through its live progress to the end, see the
quicklooks drawn, download an output, and check a screenshot is not blank.

Skips, saying why, only where no Chromium or chromedriver can be found (`.ci/run`
installs Debian's `chromium` and `chromium-driver` when missing).
"""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import rasterio

from terrasift.service.settings import Settings
from terrasift.synthetic.terrain import make_scene, write_las

webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed")

from live_server import live_server  # noqa: E402

SHOTS = (
    Path(os.environ.get("TERRASIFT_SCREENSHOTS", ""))
    if os.environ.get("TERRASIFT_SCREENSHOTS")
    else None
)


def _binary(*names: str) -> str | None:
    for name in names:
        found = shutil.which(name)
        if found:
            return found
    return None


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    chrome = _binary("chromium", "chromium-browser", "google-chrome")
    driver_bin = _binary("chromedriver")
    if chrome is None or driver_bin is None:
        pytest.skip(
            "no headless browser: install Debian's `chromium` and `chromium-driver` "
            "(.ci/run does when it can)"
        )
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chrome
    for arg in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--window-size=1280,1600",
    ):
        options.add_argument(arg)
    driver = webdriver.Chrome(service=Service(driver_bin), options=options)
    driver.set_page_load_timeout(60)
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    data = tmp_path_factory.mktemp("browser") / "data"
    with live_server(Settings(_env_file=None, data_dir=data, workers=2)) as url:
        yield url


def not_blank(png: Path) -> tuple[float, int]:
    """Standard deviation of the grey values and the number of distinct colours of a screenshot."""
    with rasterio.open(png) as ds:
        rgb = ds.read()[:3].astype(np.int64)
    colours = np.unique((rgb[0] << 16) | (rgb[1] << 8) | rgb[2]).size
    return float(rgb.mean(axis=0).std()), int(colours)


def test_upload_watch_look_download(browser, server: str, tmp_path: Path) -> None:
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    tile = write_las(make_scene(size=80, density=4, seed=7), tmp_path / "tile.laz", crs=None)
    driver = browser
    driver.get(server + "/")
    assert "terrasift" in driver.title
    driver.find_element(By.ID, "file").send_keys(str(tile))
    driver.find_element(By.ID, "params").send_keys(
        '{"block_size": 40, "buffer": 5, "resolution": 1.0}'
    )
    driver.find_element(By.ID, "submit").click()
    WebDriverWait(driver, 30).until(lambda d: "/jobs/" in d.current_url)
    job_url = driver.current_url
    assert driver.find_element(By.TAG_NAME, "h1").text.startswith("Job")

    # live progress: the page updates itself (events or polling), never backwards
    seen: list[int] = []
    end = time.monotonic() + 240
    status = ""
    pushed = False  # the page listens to server-sent events
    running_shot = (SHOTS or tmp_path) / "job-running.png"
    running_shot.parent.mkdir(parents=True, exist_ok=True)
    while time.monotonic() < end:
        try:
            status = driver.find_element(By.ID, "status").text
            seen.append(int(driver.find_element(By.ID, "progress").text.split()[0]))
            if status == "running" and 0 < seen[-1] < 100 and not running_shot.exists():
                driver.save_screenshot(str(running_shot))
            if status == "running":
                live = driver.execute_script("return document.body.dataset.live")
                pushed = pushed or live == "events"
        except Exception:  # noqa: BLE001 - the page reloads itself at the end
            pass
        if status in ("successful", "failed", "dismissed") and driver.find_elements(
            By.CSS_SELECTOR, ".looks img"
        ):
            break
        time.sleep(0.3)
    assert status == "successful", (status, seen)
    assert pushed, "the job page got no server-sent event from /jobs/{id}/events"
    seen.append(int(driver.find_element(By.ID, "progress").text.split()[0]))  # the final page
    assert seen == sorted(seen) and seen[-1] == 100 and len(set(seen)) >= 2, seen
    warnings = driver.find_element(By.ID, "warnings").text
    assert "no CRS" in warnings  # the tile has none: the warning reaches the page

    # every quicklook is a decoded image with pixels
    images = driver.find_elements(By.CSS_SELECTOR, ".looks img")
    ids = {img.get_attribute("id") for img in images}
    assert {"look-hillshade", "look-chm", "look-coverage", "look-categories"} <= ids, ids
    WebDriverWait(driver, 20).until(
        lambda d: all(
            d.execute_script("return arguments[0].complete && arguments[0].naturalWidth", i)
            for i in images
        )
    )
    coverage = driver.find_element(By.ID, "look-coverage").find_element(By.XPATH, "../..")
    assert "open" in coverage.find_element(By.CSS_SELECTOR, ".legend").text  # with its legend

    # a download link serves the file the table says
    link = driver.find_element(By.LINK_TEXT, "dtm.tif")
    size_text = link.find_element(By.XPATH, "../../td[2]").text
    body = driver.execute_async_script(
        "const done = arguments[1];"
        "fetch(arguments[0]).then(r => r.arrayBuffer()).then(b => done(b.byteLength));",
        link.get_attribute("href"),
    )
    assert body > 0 and size_text.split()[1] in ("B", "kB", "MB")

    shot = (SHOTS or tmp_path) / "job-page.png"
    shot.parent.mkdir(parents=True, exist_ok=True)
    driver.execute_script("document.querySelector('.looks').scrollIntoView()")
    driver.get(job_url)  # top of the page again
    assert driver.save_screenshot(str(shot))
    spread, colours = not_blank(shot)
    assert spread > 10 and colours > 50, (spread, colours)
