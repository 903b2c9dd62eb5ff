"""The operator page in headless Chromium (Debian ``chromium`` + ``chromium-driver``
through Selenium; no browser is downloaded): start a run from the form, see the
progress bar move and the result table fill; bad form input is refused with a
message next to the field and starts nothing."""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from selenium import webdriver
from selenium.webdriver.chrome.service import Service
from selenium.webdriver.common.by import By
from selenium.webdriver.remote.webdriver import WebDriver
from selenium.webdriver.support.ui import WebDriverWait
from test_web_support import KEY, ServerProcess, frame_cache, wait_until, write_config

CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path(shutil.which("chromedriver") or "/usr/bin/chromedriver")


@pytest.fixture(scope="module")
def server(
    tmp_path_factory: pytest.TempPathFactory, pytestconfig: pytest.Config
) -> Iterator[ServerProcess]:
    config = write_config(tmp_path_factory.mktemp("web-page"))
    srv = ServerProcess(config, cache=frame_cache(pytestconfig))
    yield srv
    assert srv.stop() == 0, srv.log()


@pytest.fixture
def browser(tmp_path: Path) -> Iterator[WebDriver]:
    assert CHROMIUM.exists() and CHROMEDRIVER.exists(), (
        "the page test needs Debian's chromium and chromium-driver (make setup installs them)"
    )
    os.environ.setdefault("SE_AVOID_STATS", "true")
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for arg in (
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        "--disable-dev-shm-usage",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
        "--window-size=1200,1600",
    ):
        options.add_argument(arg)
    driver = webdriver.Chrome(options=options, service=Service(str(CHROMEDRIVER)))
    driver.set_page_load_timeout(30)
    try:
        yield driver
    finally:
        driver.quit()


def open_page(browser: WebDriver, server: ServerProcess, key: str | None = KEY) -> None:
    browser.get(server.url + "/")
    wait = WebDriverWait(browser, 30)
    # the form takes its limits and defaults from the API's OpenAPI document
    wait.until(lambda d: d.find_element(By.ID, "start_mm").get_attribute("value") != "")
    wait.until(lambda d: "?" not in d.find_element(By.ID, "devices-status").text)
    field = browser.find_element(By.ID, "api-key")
    field.clear()
    if key:
        field.send_keys(key)


def set_field(browser: WebDriver, name: str, value: str) -> None:
    element = browser.find_element(By.ID, name)
    element.clear()
    element.send_keys(value)


def text(browser: WebDriver, css: str) -> str:
    return str(browser.find_element(By.CSS_SELECTOR, css).text)


def test_a_run_started_from_the_page_shows_progress_and_the_result(
    browser: WebDriver, server: ServerProcess
) -> None:
    open_page(browser, server)
    set_field(browser, "settle_s", "0.3")  # ~0.4 s a frame: the bar has time to move
    set_field(browser, "note", "from the operator page")
    assert text(browser, "#frame-count") == "10 frames"
    browser.find_element(By.ID, "start-button").click()

    seen: list[tuple[int, int]] = []

    def result_shown(d: Any) -> bool:
        bar = d.find_element(By.ID, "progress")
        seen.append((int(float(bar.get_attribute("value"))), int(float(bar.get_attribute("max")))))
        cells = d.find_elements(By.CSS_SELECTOR, "#res-a td.num")
        return bool(cells) and cells[0].text not in ("", "n/a")

    WebDriverWait(browser, 120, poll_frequency=0.05).until(result_shown)
    values = [v for v, _ in seen]
    assert values == sorted(values), "the progress bar went backwards"
    assert len(set(values)) >= 3 and any(0 < v < 10 for v in values), seen
    bar = browser.find_element(By.ID, "progress")
    assert (bar.get_attribute("value"), bar.get_attribute("max")) == ("10", "10")
    assert text(browser, "#job-state") == "succeeded"

    job_id = int(text(browser, "#job-id"))
    result = server.client.get(f"/api/v1/jobs/{job_id}/result").json()
    job = server.client.get(f"/api/v1/jobs/{job_id}").json()
    assert job["request"]["settle_s"] == 0.3 and job["request"]["note"]
    assert text(browser, "#res-a td.num") == f"{result['a_mm']:.5f}"
    assert text(browser, "#res-b td.num") == f"{result['b_mm']:.5f}"
    assert text(browser, "#res-Q td.num") == f"{result['Q']:.6f}"
    assert text(browser, "#res-p td.num") == f"{result['patch_size_px']:.4f}"
    focus = result["focus"]
    assert text(browser, "#res-focus-u td.num") == f"{focus['object_distance_mm']:.3f}"
    assert text(browser, "#res-focus-rail td.num") == f"{focus['rail_mm']:.3f}"
    assert text(browser, "#res-a td:nth-child(3)").startswith("± ")
    # the data-sheet values against the sweep (issue 11)
    assert text(browser, "#res-L td.num") == f"{result['L_mm']:.4f}"
    for key in ("main_focal_mm", "mla_focal_mm", "rail_zero_object_distance_mm"):
        prior = result["priors"][key]
        cells = browser.find_elements(By.CSS_SELECTOR, f"#prior-{key} td")
        assert cells[1].text == f"{prior['datasheet']:.4f}"
        assert cells[3].text == f"{prior['calibrated']:.4f}"
        assert cells[6].text in ("ok", "data sheet used", "CONTRADICTED")

    # the La(u) plot was fed by the event stream
    plotted = browser.find_element(By.ID, "la-plot").get_attribute("data-points")
    assert int(plotted or 0) >= 8

    links = {
        a.text: a.get_attribute("href") for a in browser.find_elements(By.CSS_SELECTOR, "#links a")
    }
    base = f"{server.url}/api/v1/jobs/{job_id}"
    assert links["focus plot La(u)"] == f"{base}/plots/focus.png"
    assert links["rendered, calibrated p"] == f"{base}/render.png?p=calibrated"
    assert links["rendered, designed p"] == f"{base}/render.png?p=designed"
    assert links["sweep archive (zip)"] == f"{base}/archive"
    WebDriverWait(browser, 30).until(
        lambda d: d.execute_script(
            "const imgs = [...document.querySelectorAll('#images img')];"
            "return imgs.length === 4 && imgs.every(i => i.complete && i.naturalWidth > 0);"
        )
    )


def test_bad_form_input_is_refused_and_starts_nothing(
    browser: WebDriver, server: ServerProcess
) -> None:
    before = server.client.get("/api/v1/jobs").json()["jobs"]
    open_page(browser, server)
    set_field(browser, "start_mm", "60")
    set_field(browser, "stop_mm", "40")
    browser.find_element(By.ID, "start-button").click()
    assert "must not be below start" in text(browser, "#err-stop_mm")
    assert "Fix the marked fields" in text(browser, "#form-error")

    set_field(browser, "stop_mm", "140")
    browser.find_element(By.ID, "start-button").click()
    assert "≤ 100" in text(browser, "#err-stop_mm")

    # a form that passes the page's checks but has no API key: the server's answer is shown
    open_page(browser, server, key=None)
    browser.find_element(By.ID, "start-button").click()
    WebDriverWait(browser, 30).until(lambda d: "API key" in text(d, "#form-error"))
    assert server.client.get("/api/v1/jobs").json()["jobs"] == before


def test_opening_the_page_during_a_run_follows_that_run(
    browser: WebDriver, server: ServerProcess
) -> None:
    started = server.client.post(
        "/api/v1/jobs",
        json={"settle_s": 0.5, "calibrate": False, "note": "started over the API"},
        headers={"X-API-Key": KEY},
    )
    assert started.status_code == 202, started.text
    job_id = started.json()["id"]
    try:
        wait_until(
            lambda: server.client.get(f"/api/v1/jobs/{job_id}").json()["state"] == "running",
            60,
            "the job to start",
        )
        open_page(browser, server)
        # no click: the running job's panel opens by itself and its bar moves
        WebDriverWait(browser, 30).until(lambda d: text(d, "#job-id") == str(job_id))
        WebDriverWait(browser, 60, poll_frequency=0.05).until(
            lambda d: int(float(d.find_element(By.ID, "progress").get_attribute("value") or 0)) >= 1
        )
        # the state span holds the state alone (SSE and polling agree); the phase sits beside it
        assert text(browser, "#job-state") == "running"
        WebDriverWait(browser, 30).until(lambda d: text(d, "#job-phase") == "(sweeping)")
    finally:
        server.client.post(f"/api/v1/jobs/{job_id}/cancel", headers={"X-API-Key": KEY})
        wait_until(
            lambda: server.client.get(f"/api/v1/jobs/{job_id}").json()["state"] == "cancelled",
            60,
            "the job to be cancelled",
        )
    WebDriverWait(browser, 30).until(lambda d: text(d, "#job-state") == "cancelled")
    assert text(browser, "#job-phase") == ""


SCREENSHOTS = Path(__file__).resolve().parents[1] / "out" / "screenshots"


def _data(browser: WebDriver, element_id: str, name: str) -> int:
    return int(browser.find_element(By.ID, element_id).get_attribute(f"data-{name}") or 0)


def test_live_frame_with_corners_edge_spread_plot_devices_and_a_url_per_job(
    browser: WebDriver, server: ServerProcess
) -> None:
    """The operator sees the latest frame with the corners the analysis found, the edge
    spread per frame (the quantity that decides the focus plane) with the fitted defocus
    model once the result exists, the devices panel; the job's URL survives a reload."""
    open_page(browser, server)
    set_field(browser, "settle_s", "0.2")
    browser.find_element(By.ID, "start-button").click()
    WebDriverWait(browser, 120, poll_frequency=0.1).until(
        lambda d: _data(d, "frame-view", "corners") > 0
    )
    job_id = int(text(browser, "#job-id"))
    assert browser.current_url == f"{server.url}/?job={job_id}"
    assert text(browser, "#job-link").endswith(f"/?job={job_id}")
    # the overlay shows exactly the corners the API reports for that frame (frame number,
    # corner count and caption read in one script: the view moves on as new frames are
    # analysed, so separate reads may see two different frames)
    frame, shown, caption = browser.execute_script(
        "const c = document.getElementById('frame-view');"
        "return [Number(c.dataset.frame), Number(c.dataset.corners),"
        " document.getElementById('frame-caption').textContent];"
    )
    corners = server.client.get(f"/api/v1/jobs/{job_id}/frames/{frame}/corners").json()
    assert corners["analysed"] and corners["width"] == 2000 and corners["height"] == 500
    n = len(corners["standard"]) + len(corners["reference"])
    assert n > 0 and shown == n
    assert caption.startswith(f"frame {frame}, ")
    assert f"{len(corners['standard'])} standard (green)" in caption
    # the view is a downscaled frame (2000x500 -> 640x160)
    width, height = browser.execute_script(
        "const c = document.getElementById('frame-view'); return [c.width, c.height];"
    )
    assert (width, height) == (640, 160)

    WebDriverWait(browser, 120, poll_frequency=0.1).until(
        lambda d: _data(d, "width-plot", "model-points") > 0
    )
    result = server.client.get(f"/api/v1/jobs/{job_id}/result").json()
    assert _data(browser, "width-plot", "points") == sum(
        f["edge_spread_px"] is not None for f in result["frames"]
    )
    assert _data(browser, "width-plot", "model-points") == sum(
        v is not None for v in result["curves"]["edge_spread_model_px"]
    )
    assert f"{result['focus']['object_distance_mm']:.2f} mm" in text(browser, "#width-note")
    assert _data(browser, "la-plot", "points") >= 8
    # the last frame is the one on view once the sweep is over
    WebDriverWait(browser, 30).until(lambda d: _data(d, "frame-view", "frame") == 9)

    # the devices panel (the simulated bench: homed stages, the sensor's temperature)
    WebDriverWait(browser, 30).until(lambda d: "homed" in text(d, "#dev-rail"))
    assert "mm" in text(browser, "#dev-rail") and "homed" in text(browser, "#dev-xy")
    devices = server.client.get("/api/v1/devices").json()
    assert f"{devices['camera']['temperature_c']:.1f} °C" in text(browser, "#dev-camera")

    links = {
        a.text: a.get_attribute("href") for a in browser.find_elements(By.CSS_SELECTOR, "#links a")
    }
    assert links["calibration report (HTML)"] == f"{server.url}/api/v1/jobs/{job_id}/report.html"

    browser.set_window_size(1200, 2400)
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    shot = SCREENSHOTS / "operator.png"
    assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 10_000

    # reload (or open the shared URL): the same job, its result and plots come back
    browser.get(f"{server.url}/?job={job_id}")
    WebDriverWait(browser, 60).until(lambda d: text(d, "#job-state") == "succeeded")
    assert text(browser, "#job-id") == str(job_id)
    WebDriverWait(browser, 60, poll_frequency=0.1).until(
        lambda d: (
            _data(d, "width-plot", "model-points") > 0
            and _data(d, "width-plot", "points") == 10
            and _data(d, "frame-view", "corners") > 0
        )
    )
    assert text(browser, "#res-b td.num") == f"{result['b_mm']:.5f}"
