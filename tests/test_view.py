"""``voxelwatch view``: the live page, in a real browser, over the real demo system.

Default run (one demo system for the module): ``voxelwatch demo --view``
plays 'fall_forward' (the person falls at frame 101 and lies still) as five
camera workers, the fusion server and the view, all processes on loopback.
Headless Chromium (selenium, ``/usr/bin/chromedriver``) logs in with the
token and a name, and checks against the scenario's truth: the fall banner
comes up, the person's marker lies on the plan where the fall was, the event
list holds the fall; a click on the banner's button acknowledges it, the
``alarm_ack`` (by the name typed at login) is in the fusion server's history
and the banner clears on every open page. The installer's page shows a
camera's mask under the floor outline. Over plain HTTP: a wrong token is
refused (401 form, 403 link, 401 API), a form from another site too, the
fusion server's refusals (an unknown alarm, a bad history filter) reach the
page with their reason, pages that go away free their places, and the
command refuses to start without a token. A view started after a fall (a
fusion server whose store holds it) shows the alarm still waiting, not the
one acknowledged before, and acknowledges it.

slow: a page left open while a test session publishes 54,000 track frames
(an hour of the house at 15 frames/s) with events and status as fast as it
can; the JS heap after a garbage collection grows by less than
:data:`HEAP_GROWTH_BOUND` bytes (measured: 0.86 MB before, 0.91 MB after, 19,120
frames drawn of the 54,000), and the view process's resident memory by less
than :data:`RSS_GROWTH_BOUND_KB`.

``VOXELWATCH_VIEW_SHOTS=1`` also writes the screenshots ``docs/view-plan.png``
(during the fall) and ``docs/view-install.png``.
"""

from __future__ import annotations

import http.cookiejar
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.parse
import urllib.request
from pathlib import Path

import pytest

from procs import ROOT, Proc, free_port, loopback_config, stop_all, wait_for

import synth
from common import keys, messages

CHROMEDRIVER = Path("/usr/bin/chromedriver")
SCENARIO = "fall_forward"
CAMERAS = ("cam1", "cam3", "cam5")
"""Three of the house's five cameras: the demo (its workers render their cameras too) with the view and
a browser then needs about half of a 2-core machine, so a slower moment of a shared machine does not
starve it; with five it needs nearly all of it and the workers drop frames."""
FRAMES = 540            # 36 s: the truth fall is at frame 101 (6.7 s), its long lie (frame 551) just after the end
NEAR_M = 0.5
NAME = "Night nurse"
SHOTS = os.environ.get("VOXELWATCH_VIEW_SHOTS") == "1"
HEAP_GROWTH_BOUND = 1024 * 1024
RSS_GROWTH_BOUND_KB = 20 * 1024
PREFIX = "voxelwatch/synthetic-house"
PYTHON_CLI = [sys.executable, "-c", "import sys; from voxelwatch.cli import main; sys.exit(main())"]


def _chrome_or_skip():
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        pytest.skip("selenium is not installed (pip install -e '.[test]')")
    browser = shutil.which("chromium") or shutil.which("chromium-browser") or shutil.which("google-chrome")
    if not CHROMEDRIVER.is_file() or browser is None:
        pytest.skip("headless Chromium is not installed (Debian: apt-get install chromium chromium-driver)")
    opts = webdriver.ChromeOptions()
    for arg in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                "--window-size=1280,1000", "--autoplay-policy=no-user-gesture-required",
                "--js-flags=--expose-gc"):
        opts.add_argument(arg)
    opts.binary_location = browser
    return webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)


# --------------------------------------------------------------------------- the demo system with the view


class DemoView:
    def __init__(self, proc: Proc, out: Path, url: str, token: str, endpoint: str) -> None:
        self.proc, self.out, self.url, self.token, self.endpoint = proc, out, url, token, endpoint

    def log(self) -> str:
        return self.proc.output()


class Alerts:
    """``voxelwatch notify`` beside the demo system, with its real receivers: a mosquitto broker, an
    HTTP hook server and an MQTT subscriber."""

    def __init__(self, folder: Path) -> None:
        from notifyparts import HookServer, Mosquitto, MqttWatcher

        from common.site import MqttSettings, NotifySettings, WebhookSettings, write_site

        self.folder = folder
        self.broker = Mosquitto(folder / "broker").start()
        self.hooks = HookServer()
        self.watcher = MqttWatcher(self.broker.port, (f"{PREFIX}/#",))
        site = synth.default_site(folder / "site")  # the demo's house: same name, same prefix
        notify = NotifySettings(retry_max_s=2.0, outbox=str(folder / "outbox.sqlite"),
                                mqtt=MqttSettings(host="127.0.0.1", port=self.broker.port),
                                webhooks=[WebhookSettings(url=self.hooks.url("/hook"))])
        self.site_file = write_site(site.model_copy(update={"notify": notify}), site.base_dir / "site.toml")
        self.port = free_port()
        self.notifier: Proc | None = None

    def start_notifier(self, endpoint: str) -> None:
        self.notifier = Proc("notify", [sys.executable, "-m", "voxelwatch", "notify", "--site", str(self.site_file),
                                        "--mode", "client", "--connect", endpoint, "--status-every", "2"],
                             self.folder / "notify.log", env={"PYTHONPATH": str(ROOT)})

    def close(self) -> None:
        if self.notifier is not None:
            self.notifier.stop()
        self.watcher.close()
        self.hooks.close()
        self.broker.stop()


@pytest.fixture(scope="module")
def alerts(tmp_path_factory):
    """The notifier's receivers, or None where mosquitto is not installed (the view's tests go on)."""
    from notifyparts import MOSQUITTO

    if MOSQUITTO is None:
        yield None
        return
    made = Alerts(tmp_path_factory.mktemp("alerts"))
    try:
        yield made
    finally:
        made.close()


@pytest.fixture(scope="module")
def demo(tmp_path_factory, alerts, lut_cache, machine_to_itself):
    """The demo system with its view; with ``alerts``, the notifier joins the demo's router and
    connects to the broker, and the broker is stopped before the workers' first frame: the fall
    happens while it is down."""
    if not CHROMEDRIVER.is_file():
        pytest.skip("chromedriver is not installed (Debian: apt-get install chromium chromium-driver)")
    out = tmp_path_factory.mktemp("demo-view")
    port = free_port()
    router = alerts.port if alerts is not None else free_port()
    proc = Proc("demo", [*PYTHON_CLI, "demo", "--view", f"127.0.0.1:{port}", "--scenario", SCENARIO,
                         "--frames", str(FRAMES), "--out", str(out / "demo"), "--port", str(router),
                         "--cache-dir", str(lut_cache), "--cameras", ",".join(CAMERAS)],
                out / "demo.log", env={"PYTHONPATH": str(ROOT)})
    try:
        if alerts is not None:
            wait_for(lambda: "zenoh router" in proc.output(), 60, "the demo's router", procs=[proc])
            alerts.start_notifier(f"tcp/127.0.0.1:{router}")
            wait_for(lambda: any(p == "online" for p, _ in alerts.watcher.on(f"{PREFIX}/availability")), 60,
                     "the notifier online on the broker", procs=[proc, alerts.notifier])
            alerts.broker.stop()
        text = wait_for(lambda: re.search(r"live view: (http://127\.0\.0\.1:\d+/)\?token=(\S+)", proc.output())
                        and "voxelwatch view: http" in (out / "demo" / "logs" / "view.log").read_text(errors="replace")
                        and proc.output(), 120, "the demo's view", procs=[proc])
        url = re.search(r"live view: (http://127\.0\.0\.1:\d+/)", text).group(1)
        endpoint = re.search(r"zenoh router (tcp/127\.0\.0\.1:\d+)", text).group(1)
        token = (out / "demo" / "view.token").read_text().strip()
        yield DemoView(proc, out / "demo", url, token, endpoint)
    finally:
        proc.stop(timeout_s=30, sig=signal.SIGINT)  # Ctrl-C: the demo stops every process it started


@pytest.fixture(scope="module")
def truth_fall(tmp_path_factory):
    folder = tmp_path_factory.mktemp("truth")
    synth.write_truth(synth.get_scenario(SCENARIO, 0), folder, n_frames=FRAMES)
    events = [json.loads(line) for line in (folder / "events.jsonl").read_text().splitlines()]
    (fall,) = [e for e in events if e["kind"] == "fall"]
    return fall


@pytest.fixture(scope="module")
def browser():
    driver = _chrome_or_skip()
    yield driver
    driver.quit()


# --------------------------------------------------------------------------- access over HTTP


def _opener():
    jar = http.cookiejar.CookieJar()
    return urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar)), jar


def _status(opener, url: str, data: bytes | None = None, headers: dict | None = None) -> tuple[int, str]:
    req = urllib.request.Request(url, data=data, headers=headers or {})
    try:
        with opener.open(req, timeout=10) as r:
            return r.status, r.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, exc.read().decode()


def test_a_wrong_token_is_refused_and_the_right_one_opens_the_page(demo):
    opener, jar = _opener()
    code, body = _status(opener, demo.url)
    assert code == 401 and 'name="token"' in body  # the login form
    code, body = _status(opener, demo.url + "?token=not-the-token-at-all")
    assert code == 403 and "Wrong token" in body
    code, _ = _status(opener, demo.url + "api/plan")
    assert code == 401
    form = urllib.parse.urlencode({"token": "not-the-token-at-all", "name": "x", "next": "/"}).encode()
    code, body = _status(opener, demo.url + "login", form)
    assert code == 401 and "Wrong token" in body and not list(jar)
    # a form posted from another site is refused even with the right token
    form = urllib.parse.urlencode({"token": demo.token, "next": "/"}).encode()
    code, _ = _status(opener, demo.url + "login", form, {"Origin": "http://evil.example"})
    assert code == 403 and not list(jar)
    code, body = _status(opener, demo.url + "login", form)
    assert code == 200 and "/static/app.js" in body  # redirected to the page
    (cookie,) = list(jar)
    assert cookie.has_nonstandard_attr("HttpOnly") and cookie.get_nonstandard_attr("SameSite") == "Strict"
    code, body = _status(opener, demo.url + "api/plan")
    plan = json.loads(body)
    assert code == 200 and plan["plan"]["site"] == "synthetic-house" and plan["alarms"] == ["fall", "long_lie"]
    assert [c["id"] for c in plan["plan"]["cameras"]] == list(CAMERAS)
    # pages that go away free their places: twice as many streams as may be open at once, one after the other
    from view.server import MAX_CLIENTS

    for _ in range(2 * MAX_CLIENTS):
        _fusion_up(opener, demo.url)
    # the fusion server's refusals come through with its reason
    wait_for(lambda: _fusion_up(opener, demo.url), 60, "the fusion server", procs=[demo.proc], period_s=1.0)
    code, body = _status(opener, demo.url + "api/ack", json.dumps({"event": "1-fall-99"}).encode(),
                         {"Content-Type": "application/json"})
    assert code == 502 and "no stored event" in json.loads(body)["error"], body
    code, body = _status(opener, demo.url + "api/events?kind=tumble")
    assert code == 400 and "unknown kind" in json.loads(body)["error"], body
    code, body = _status(opener, demo.url + "api/events?kind=fall%3Bformat%3Dmsgpack")
    assert code == 400, body  # nothing but the page's own parameters reaches the selector


def _fusion_up(opener, url: str) -> bool:
    """Whether the view has seen the fusion server's liveliness token (its stream's first message says)."""
    req = urllib.request.Request(url + "api/stream")
    with opener.open(req, timeout=10) as r:
        first = b""
        while not first.endswith(b"\n\n"):
            first += r.read(1)
    return json.loads(first.decode().split("data: ", 1)[1])["fusion_alive"] is True


def test_the_command_refuses_to_start_without_a_token(tmp_path):
    site = synth.default_site(tmp_path / "site")
    result = subprocess.run([*PYTHON_CLI, "view", "--site", str(site.base_dir / "site.toml")], cwd=ROOT,
                            capture_output=True, text=True, timeout=60, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "no access token" in lines[0] and "[view] token" in lines[0], result.stderr


# --------------------------------------------------------------------------- the fall in the browser


def _login(driver, url: str, token: str, name: str) -> None:
    from selenium.webdriver.common.by import By

    driver.get(url + "login")  # the form, whether or not the browser has been here before
    driver.find_element(By.ID, "token").send_keys(token)
    driver.find_element(By.ID, "name").send_keys(name)
    driver.find_element(By.ID, "login-button").click()
    wait_for(lambda: driver.execute_script("return !!document.getElementById('plan') && "
                                           "document.querySelectorAll('#plan .camera').length"), 20, "the plan")


def _shot(driver, name: str, height: int) -> None:
    """A screenshot of the whole page into docs/ (the window made ``height`` pixels tall for it)."""
    (ROOT / "docs").mkdir(exist_ok=True)
    size = driver.get_window_size()
    driver.set_window_size(1280, height)
    time.sleep(1.5)  # a redraw, the timeline and a fresh mask
    assert driver.save_screenshot(str(ROOT / "docs" / name))
    driver.set_window_size(size["width"], size["height"])


def _get(driver, url: str, *, text: bool = True):
    """GET ``url`` with the browser's session cookie."""
    cookie = driver.get_cookie("voxelwatch_view")
    req = urllib.request.Request(url, headers={"Cookie": f"voxelwatch_view={cookie['value']}"})
    with urllib.request.urlopen(req, timeout=10) as r:
        body = r.read()
    return body.decode() if text else body


def _history(endpoint: str, prefix: str, params: str) -> list[messages.Event]:
    import zenoh

    with zenoh.open(loopback_config(mode="client", connect=[endpoint])) as session:
        replies = session.get(f"{keys.history_key(prefix)}/**?{params}", timeout=10)
        return [messages.decode_event(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]


def test_the_installer_page_shows_the_mask_under_the_floor_outline(demo, browser):
    browser.get(demo.url + "install/cam1?token=" + urllib.parse.quote(demo.token))  # the printed link's way in
    assert browser.current_url == demo.url + "install/cam1"  # the token left the address bar
    wait_for(lambda: browser.execute_script(
        "const i = document.querySelector('#image image'); return i && i.getAttribute('href')"), 120,
        "the mask image", procs=[demo.proc])
    counts = browser.execute_script(
        "return [document.querySelectorAll('#image .floor').length, document.querySelectorAll('#image .hotspot-line').length]")
    assert counts[0] >= 1 and counts[1] >= 4, counts  # the floor (cut where it leaves the image) and four hot spots
    wait_for(lambda: browser.execute_script(
        "const s = document.querySelector('#health [data-field=state]'); return s && s.textContent === 'ok'"), 30,
        "cam1 reported ok on its page", procs=[demo.proc])
    # the PNG the page shows is the camera's mask: the mask's size, with foreground (the person lying)
    png = _get(browser, demo.url + "api/mask/cam1.png", text=False)
    import cv2
    import numpy as np

    mask = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_GRAYSCALE)
    assert mask.shape == (240, 320) and set(np.unique(mask)) <= {0, 255} and (mask == 255).sum() > 50
    if SHOTS:
        _shot(browser, "view-install.png", 860)


def test_the_fall_raises_the_banner_the_marker_lies_where_it_fell_and_a_click_acknowledges_it(demo, browser,
                                                                                              truth_fall):
    from selenium.webdriver.common.by import By

    _login(browser, demo.url, demo.token, NAME)
    first = browser.current_window_handle
    assert browser.execute_script("return voxelwatchView.name") == NAME
    # the plan: every hot spot, door, piece of furniture and camera of the site, each camera's view on the floor
    from common.site import load_site

    site = load_site(demo.out / "site" / "site.toml")
    drawn = browser.execute_script(
        "return ['.hotspot', '.door', '.occluder', '.camera', '#fov polygon'].map("
        "q => document.querySelectorAll('#plan ' + q).length)")
    assert drawn == [len(site.hotspots), len(site.doors), len(site.occluders), len(CAMERAS), len(CAMERAS)], drawn
    wait_for(lambda: browser.execute_script("return !document.getElementById('alarm').hidden"), 90,
             "the fall banner", procs=[demo.proc])
    banner = browser.find_element(By.ID, "alarm")
    assert browser.find_element(By.ID, "alarm-title").text == "FALL"
    fall_id = banner.get_attribute("data-event")
    prefix = "voxelwatch/synthetic-house"
    (fall,) = [e for e in _history(demo.endpoint, prefix, "kind=fall")]
    assert fall.id == fall_id
    # the fall the system raised is the scenario's fall: near the truth in time and place
    assert -30 <= fall.frame - truth_fall["frame"] <= 45, (fall, truth_fall)
    assert ((fall.x - truth_fall["x"]) ** 2 + (fall.y - truth_fall["y"]) ** 2) ** 0.5 < NEAR_M

    # the person's marker: lying, on the plan where the fall happened (plan units: cm from the
    # volume's corner less a 0.3 m margin, y flipped; read from the marker's own transform)
    def marker():
        return browser.execute_script(
            "const g = document.querySelector('#markers .person:not([visibility])');"
            "return g && [g.getAttribute('transform'), g.dataset.posture, g.querySelector('text').textContent];")
    transform, posture, label = wait_for(lambda: (m := marker()) and m[1] == "lying" and m, 20, "a lying marker")
    cx, cy = map(float, re.match(r"translate\(([-\d.]+),([-\d.]+)\)", transform).groups())
    x, y = cx / 100 - 0.3, 6.0 - (cy / 100 - 0.3)
    assert ((x - fall.x) ** 2 + (y - fall.y) ** 2) ** 0.5 < NEAR_M, (x, y, fall)
    assert label.startswith(f"#{fall.track}") and "lying" in label
    # the event list holds the fall
    wait_for(lambda: browser.execute_script(
        f"return !!document.querySelector('#events tr[data-id=\"{fall_id}\"][data-kind=\"fall\"]')"), 20,
        "the fall in the event list")
    # the banner beeps (WebAudio) while it waits
    assert browser.execute_script("return voxelwatchView.beepTimer !== null && !!voxelwatchView.audio")
    # the day's timeline of the person: standing, then lying from about the fall, with the fall marked
    timeline = json.loads(_get(browser, demo.url + "api/timeline?since=0"))
    (person,) = [p for p in timeline["people"] if p["key"] == str(fall.track)]
    lying = [r for r in person["runs"] if r[2] == "lying"]
    assert lying and abs(lying[0][0] - fall.stamp_ns) < 3e9 and person["runs"][0][2] != "lying", person["runs"]
    assert [fall.stamp_ns, "fall"] in person["marks"]
    if SHOTS:
        _shot(browser, "view-plan.png", 1500)

    # a second page open on the same view: it too shows the banner, and clears it when the first acknowledges
    browser.switch_to.new_window("window")
    second = browser.current_window_handle
    browser.get(demo.url)
    wait_for(lambda: browser.execute_script("return !document.getElementById('alarm').hidden"), 20,
             "the banner on the second page")
    browser.switch_to.window(first)
    browser.find_element(By.ID, "ack").click()
    wait_for(lambda: browser.execute_script("return document.getElementById('alarm').hidden"), 20,
             "the banner to clear")
    acks = wait_for(lambda: _history(demo.endpoint, prefix, "kind=alarm_ack"), 20, "the stored alarm_ack")
    assert [(a.details["event"], a.details["alarm"], a.details["by"]) for a in acks] == [(fall_id, "fall", NAME)]
    assert browser.execute_script("return voxelwatchView.beepTimer") is None  # and the beeping stopped
    wait_for(lambda: browser.execute_script(
        "return !!document.querySelector('#events tr[data-kind=\"alarm_ack\"]')"), 20, "the alarm_ack in the list")
    browser.switch_to.window(second)
    wait_for(lambda: browser.execute_script("return document.getElementById('alarm').hidden"), 20,
             "the banner to clear on the second page")
    browser.close()
    browser.switch_to.window(first)


@pytest.mark.slow  # a broker restart is also held by test_notify.py
def test_the_fall_reaches_the_webhook_and_mqtt_once_the_broker_is_back(demo, alerts):
    """The notifier heard the demo's fall while the broker was down: the webhook has it at once;
    MQTT only once the broker is started again, then with nothing lost; every delivery carries the
    event id (duplicates recognisable)."""
    if alerts is None:
        pytest.skip("mosquitto is not installed (Debian: apt-get install mosquitto)")
    from common.messages import Event

    def falls_at_hook():
        return [h for h in alerts.hooks.at("/hook") if h.status == 200 and Event.from_json(h.body).kind == "fall"]

    hits = wait_for(falls_at_hook, 120, "the fall at the webhook", procs=[demo.proc, alerts.notifier])
    (fall,) = _history(demo.endpoint, PREFIX, "kind=fall")
    assert {Event.from_json(h.body).id for h in hits} == {h.headers["Idempotency-Key"] for h in hits} == {fall.id}
    time.sleep(2.0)
    assert alerts.watcher.on(f"{PREFIX}/events/fall") == []  # no broker, no delivery yet
    alerts.broker.start()
    got = wait_for(lambda: alerts.watcher.on(f"{PREFIX}/events/fall"), 60, "the fall on MQTT",
                   procs=[alerts.notifier])
    assert {json.loads(payload)["id"] for payload, _ in got} == {fall.id}
    # only the chosen kinds travel: the fall, and no camera_lost (the cameras are all up)
    delivered = {Event.from_json(h.body).kind for h in alerts.hooks.at("/hook")}
    assert delivered == {"fall"}, delivered


@pytest.mark.slow  # waits for the demo's end; the plan's drawing is held in test_plan.py
def test_the_demo_ends_with_a_plan_svg_of_the_run(demo):
    import xml.etree.ElementTree as ET

    assert demo.proc.popen.wait(timeout=180) == 0, demo.proc.tail()
    text = demo.log()
    assert re.search(r"plan view: .*run/plan\.svg", text), text[-2000:]
    root = ET.fromstring((demo.out / "run" / "plan.svg").read_text())
    ns = "{http://www.w3.org/2000/svg}"
    assert len(root.findall(f".//{ns}g[@class='path']")) >= 1
    assert [g.get("data-kind") for g in root.findall(f".//{ns}g[@class='event']")].count("fall") == 1
    assert len(root.findall(f".//{ns}polyline[@class='truth']")) == 1


# --------------------------------------------------------------------------- an hour of frames (slow)


HOUR_FRAMES = 54_000     # an hour at 15 frames/s
PUBLISH_S = 60.0         # ... published in about a minute


def _heap_bytes(driver) -> int:
    driver.execute_cdp_cmd("HeapProfiler.collectGarbage", {})
    driver.execute_cdp_cmd("HeapProfiler.collectGarbage", {})
    metrics = driver.execute_cdp_cmd("Performance.getMetrics", {})["metrics"]
    return int(next(m["value"] for m in metrics if m["name"] == "JSHeapUsedSize"))


@pytest.mark.slow
def test_a_page_left_open_for_an_hour_of_frames_keeps_a_flat_heap(tmp_path):
    import math

    import zenoh

    from procs import Router

    from common.messages import CameraStatus, Event, Status, TrackFrame, TrackState

    driver = _chrome_or_skip()
    site = synth.default_site(tmp_path / "site")
    token_file = tmp_path / "view.token"
    token_file.write_text("a-long-enough-test-token\n")
    port = free_port()
    measured: dict[str, object] = {}
    with Router() as router:
        view = Proc("view", [*PYTHON_CLI, "view", "--site", str(site.base_dir / "site.toml"), "--listen",
                             f"127.0.0.1:{port}", "--token-file", str(token_file), "--mode", "client",
                             "--connect", router.endpoint], tmp_path / "view.log", env={"PYTHONPATH": str(ROOT)})
        p = site.prefix
        pubs = {k: router.session.declare_publisher(k, congestion_control=zenoh.CongestionControl.BLOCK)
                for k in (keys.tracks_key(p), keys.status_key(p))}
        t0 = 1_800_000_000_000_000_000
        period = 1_000_000_000 // 15
        postures = ["standing", "standing", "sitting", "bending", "lying"]
        kinds = ["sit_down", "stand_up", "dwell_start", "dwell_end", "enter", "exit", "fall", "camera_lost"]

        def publish(i: int) -> None:
            stamp = t0 + i * period
            tracks = []
            for k in range(2):  # two people walking circles; each gets a new track id every 1000 frames
                a = (i + 500 * k) / 150.0
                tracks.append(TrackState(id=1 + 2 * (i // 1000) + k, x=4 + 2 * math.cos(a), y=3 + 1.5 * math.sin(a),
                                         z_top=1.7, volume_m3=0.07, posture=postures[(i // 100 + k) % 5],
                                         reliability=0.9, vx=0.1, vy=0.0, still=False))
            pubs[keys.tracks_key(p)].put(messages.encode(TrackFrame(frame=i, stamp_ns=stamp, tracks=tracks,
                                                                    cameras=site.camera_ids)))
            if i % 15 == 0:
                cams = [CameraStatus(cam=c, state="ok", received=i, dropped=0, late=0, undecodable=0, rate_hz=15.0,
                                     latency_ms=20.0, last_seen_ns=stamp, clock_offset_ms=0.0)
                        for c in site.camera_ids]
                pubs[keys.status_key(p)].put(messages.encode(Status(stamp_ns=stamp, cameras=cams, frame_sets=i,
                                                                    frame_sets_dropped=0)))
            if i % 100 == 50:
                kind = kinds[(i // 100) % len(kinds)]
                track = -1 if kind == "camera_lost" else tracks[0].id
                e = Event(id=messages.event_id(stamp, kind, track), kind=kind, track=track, stamp_ns=stamp, frame=i,
                          x=tracks[0].x, y=tracks[0].y,
                          details={"camera": "cam1"} if kind == "camera_lost" else {"hotspot": "sofa"})
                router.session.put(keys.event_key(p, kind, track), e.to_json())

        try:
            wait_for(lambda: "voxelwatch view: http" in view.output(), 60, "the view", procs=[view])
            driver.get(f"http://127.0.0.1:{port}/?token=a-long-enough-test-token")
            driver.execute_cdp_cmd("Performance.enable", {})
            wait_for(lambda: driver.execute_script("return document.getElementById('link').textContent === 'live'"),
                     30, "the page's stream")
            for i in range(2000):  # warm up: every kind of update has run before the first measurement
                publish(i)
                time.sleep(0.001)
            wait_for(lambda: driver.execute_script("return voxelwatchView.framesSeen") > 100, 30, "frames on the page")
            time.sleep(6.0)  # a timeline redraw
            before = _heap_bytes(driver)
            rss_before_kb = view.rss_kb()
            seen_before = driver.execute_script("return voxelwatchView.framesSeen")
            start = time.monotonic()
            for i in range(2000, 2000 + HOUR_FRAMES):
                publish(i)
                lag = start + (i - 2000) * PUBLISH_S / HOUR_FRAMES - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
            measured["publish_s"] = round(time.monotonic() - start, 1)
            time.sleep(6.0)
            after = _heap_bytes(driver)
            seen = driver.execute_script("return voxelwatchView.framesSeen") - seen_before
            rows = driver.execute_script("return document.querySelectorAll('#events tbody tr').length")
            markers = driver.execute_script("return document.querySelectorAll('#markers .person').length")
            assert view.alive(), view.tail()
            rss_kb = view.rss_kb()
        finally:
            driver.quit()
            for pub in pubs.values():
                pub.undeclare()
            view.stop()
    measured.update(heap_before_mb=round(before / 2**20, 2), heap_after_mb=round(after / 2**20, 2),
                    frames_drawn=seen, event_rows=rows, markers=markers,
                    view_rss_mb=(round(rss_before_kb / 1024, 1), round(rss_kb / 1024, 1)))
    print("measured:", measured)
    assert seen > 2000, measured  # the page really was driven (a slow page skips frames, it never queues them)
    assert rows <= 300 and markers <= 4, measured
    assert after - before < HEAP_GROWTH_BOUND, measured
    assert rss_kb - rss_before_kb < RSS_GROWTH_BOUND_KB, measured


# --------------------------------------------------------------------------- a view that starts late


@pytest.mark.slow  # a second live run: the banner and acknowledgement are held above, the history in test_server.py
def test_a_view_started_after_a_fall_shows_it_from_the_history_and_acknowledges_it(tmp_path):
    """The fusion server's store already holds a fall, an older fall someone acknowledged, and a
    sit-down; a view started now shows the one alarm still waiting, and acknowledges it."""
    from procs import Listener, Router, start_fusion

    from fusion_server.event_store import EventStore

    site = synth.default_site(tmp_path / "site")
    now = time.time_ns()

    def ev(kind: str, ago_s: float, **details) -> messages.Event:
        stamp = now - int(ago_s * 1e9)
        return messages.Event(id=messages.event_id(stamp, kind, 1), kind=kind, track=1, stamp_ns=stamp, frame=-1,
                              x=2.0, y=3.0, details=details)

    old, sit, fall = ev("fall", 3600), ev("sit_down", 600), ev("fall", 60)
    old_ack = messages.Event(id=f"{old.id}-ack", kind="alarm_ack", track=1, stamp_ns=old.stamp_ns + 10**9, frame=-1,
                             x=2.0, y=3.0, details={"event": old.id, "alarm": "fall", "by": "Ada's son"})
    store = EventStore(tmp_path / "events.sqlite")
    store.add_many([old, old_ack, sit, fall])
    store.close()
    token_file = tmp_path / "view.token"
    token_file.write_text("another-long-test-token\n")
    port = free_port()
    url = f"http://127.0.0.1:{port}/"
    with Router() as router:
        listener = Listener(router.session, site.prefix)
        procs = []
        try:
            fusion = start_fusion(site.base_dir / "site.toml", endpoint=router.endpoint, store=tmp_path / "events.sqlite",
                                  out=None, cache_dir=tmp_path / "cache", log_dir=tmp_path)
            procs.append(fusion)
            listener.wait_fusion(fusion)
            view = Proc("view", [*PYTHON_CLI, "view", "--site", str(site.base_dir / "site.toml"), "--listen",
                                 f"127.0.0.1:{port}", "--token-file", str(token_file), "--mode", "client",
                                 "--connect", router.endpoint], tmp_path / "view.log", env={"PYTHONPATH": str(ROOT)})
            procs.append(view)
            wait_for(lambda: "voxelwatch view: http" in view.output(), 60, "the view", procs=procs)
            opener, _ = _opener()
            assert _status(opener, url + "?token=another-long-test-token")[0] == 200

            def snapshot() -> dict:
                with opener.open(url + "api/stream", timeout=10) as r:
                    first = b""
                    while not first.endswith(b"\n\n"):
                        first += r.read(1)
                return json.loads(first.decode().split("data: ", 1)[1])

            alarms = wait_for(lambda: snapshot()["alarms"], 30, "the alarm from the history", procs=procs)
            assert [a["id"] for a in alarms] == [fall.id]  # the acknowledged fall waits for nobody
            timeline = json.loads(_status(opener, url + "api/timeline?since=0")[1])  # not only since midnight
            (person,) = timeline["people"]
            assert person["marks"] == [[old.stamp_ns, "fall"], [sit.stamp_ns, "sit_down"], [fall.stamp_ns, "fall"]]
            code, body = _status(opener, url + "api/ack", json.dumps({"event": fall.id}).encode(),
                                 {"Content-Type": "application/json"})
            assert code == 200 and json.loads(body)["ack"]["details"] == {"event": fall.id, "alarm": "fall", "by": "view"}
            assert snapshot()["alarms"] == []
            heard = wait_for(lambda: listener.events_of("alarm_ack"), 20, "the published alarm_ack", procs=procs)
            assert [e.details["event"] for e in heard] == [fall.id]
        finally:
            stop_all(procs)
            listener.close()
    store = EventStore(tmp_path / "events.sqlite")
    try:
        assert store.get(f"{fall.id}-ack") is not None
    finally:
        store.close()
