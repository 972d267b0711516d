"""The page in a real browser (issue 41, Must have 5): headless Chromium (Debian's `chromium` and
`chromium-driver`; .ci/run installs them) uploads a mask, the numbers on the page are `infer`'s,
the 3D view drew, a photo gets infer's one-line error, and no request left the machine."""
from __future__ import annotations

import json
import shutil
from pathlib import Path
from urllib.parse import urlparse

import cv2
import numpy as np
import pytest
from typer.testing import CliRunner

from cuboidtrain.cli import app
from tests.test_not_a_mask import photo

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")

pytestmark = pytest.mark.skipif(CHROMIUM is None or DRIVER is None,
                                reason="no headless browser here: apt-get install chromium chromium-driver "
                                       "(.ci/run does) to run the page in one")


@pytest.fixture(scope="module")
def browser():
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (the test extra)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--window-size=1500,1300",
                     "--enable-unsafe-swiftshader", "--use-angle=swiftshader"):  # WebGL in software, for the 3D view
        options.add_argument(argument)
    options.set_capability("goog:loggingPrefs", {"performance": "ALL", "browser": "ALL"})
    driver = webdriver.Chrome(service=Service(DRIVER), options=options)
    yield driver
    driver.quit()


def wait_for(driver, state: str, seconds: float = 240) -> None:  # a loaded 2-core VM took over 60 s once
    from selenium.webdriver.support.ui import WebDriverWait

    WebDriverWait(driver, seconds).until(lambda d: d.execute_script("return document.body.dataset.state") in (
        state, "error" if state != "error" else state))
    assert driver.execute_script("return document.body.dataset.state") == state, driver.find_element("id", "error").text


def shown(driver, key: str) -> float:
    """The full-precision number behind a row of the page's record table."""
    return float(driver.find_element("css selector", f"#numbers tr[data-key='{key}'] td[data-value]")
                 .get_attribute("data-value"))


def requested(driver) -> list[str]:
    """Every URL the browser asked for since the last call (the DevTools performance log)."""
    urls = []
    for entry in driver.get_log("performance"):
        message = json.loads(entry["message"])["message"]
        if message["method"] == "Network.requestWillBeSent":
            urls.append(message["params"]["request"]["url"])
    return urls


def test_the_page_fits_an_upload_as_infer_does_in_a_browser(page_server, browser, tmp_path):
    address, _ = page_server
    browser.get(address)
    browser.find_element("id", "file").send_keys(str(ROOT / "examples/building.png"))
    wait_for(browser, "answered")
    result = CliRunner().invoke(app, ["infer", "examples/building.png", "--device", "cpu", "--json", "-"])
    [record] = json.loads(result.stdout)
    cuboid = record["cuboid"]
    assert shown(browser, "confidence") == record["confidence"]
    assert shown(browser, "ratios.depth_height") == record["ratios"]["depth_height"]
    assert shown(browser, "ratios.width_height") == record["ratios"]["width_height"]
    assert shown(browser, "yaw_deg") == cuboid["yaw_deg"] and shown(browser, "focal_px") == cuboid["focal_px"]
    called = browser.find_element("css selector", "#numbers tr[data-key='shape_call'] td:last-child").text
    assert called.startswith(record["shape_call"]["by"])  # who called the class: the silhouettes or the classifier
    sd = browser.find_element("css selector", "#numbers tr[data-key='yaw_deg'] td[data-sd]").get_attribute("data-sd")
    assert float(sd) == cuboid["yaw_sd_deg"]
    scores = [float(td.get_attribute("data-value")) for td in
              browser.find_elements("css selector", "#corners tbody tr td:last-child")]
    assert scores == [c["score"] for c in cuboid["corners"]]

    # the 3D view drew: plotly's WebGL canvas holds a picture, not a blank
    view = browser.find_element("id", "view3d")
    assert view.find_elements("css selector", "canvas") and "WebGL" not in view.text  # plotly's message when it cannot draw
    picture = cv2.imdecode(np.frombuffer(view.screenshot_as_png, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert picture.std() > 10 and len(np.unique(picture)) > 50
    wait_for(browser, "explained")
    assert browser.find_element("id", "panel").get_attribute("src").startswith("data:image/png;base64,")

    # a photo: infer's one-line error on the page, and the page goes on
    assert cv2.imwrite(str(tmp_path / "photo.jpg"), photo())
    browser.find_element("id", "file").send_keys(str(tmp_path / "photo.jpg"))
    wait_for(browser, "error")
    error = browser.find_element("id", "error").text
    assert error.startswith("photo.jpg: not a binary mask: ") and "\n" not in error

    # every request the browser made went to this server
    hosts = {(urlparse(u).scheme, urlparse(u).netloc) for u in requested(browser) if not u.startswith(("data:", "blob:"))}
    assert hosts == {("http", urlparse(address).netloc)}
