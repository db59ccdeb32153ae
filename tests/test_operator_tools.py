"""The operator's tools end to end, as a user runs them: `toptag demo --view --record` on a short
scenario (one bus, two RSUs), the live view checked in a real browser (Debian's chromium, headless,
driven by Playwright; `make test` installs it), the recording replayed into fresh RSU and bus
processes, and the bus fusion re-run offline on it.

Everything waits on events (the view's log, the demo's progress, pixels appearing), never on time."""
from __future__ import annotations

import base64
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import REPO, clean_env

from services.processes import stop_process
from services.recording import read_recording
from services.view.app import FUSED, TRUTH, USED_TAG
from toptag.waiting import wait_until

pytestmark = pytest.mark.system

CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync"]
VIEWPORT = {"width": 1280, "height": 800}
BUS = "bus-42"
RSUS = ("rsu-sw", "rsu-ne")
REPLAY_S = 20.0
FIGURE = REPO / "docs" / "figures" / "live-view.png"


SCENARIO = REPO / "toptag" / "data" / "demo" / "scenario-short.json"  # bus-42 through rsu-sw and rsu-ne


def colour_pixels(img: np.ndarray, rgb, tol: int = 40) -> int:
    """How many pixels of an (H, W, 3) image are within ``tol`` of a colour on every channel."""
    return int((np.abs(img[..., :3].astype(int) - np.asarray(rgb)).max(axis=-1) <= tol).sum())


def panels(img: np.ndarray) -> dict[str, np.ndarray]:
    """The screenshot's panels (the view's blueprint: the map top left, the cameras top right)."""
    h, w = img.shape[:2]
    top = int(0.04 * h)  # Rerun's top bar
    return {"map": img[top:int(0.72 * h), : w // 2], "cameras": img[top:int(0.55 * h), w // 2:]}


def _read_png(path: Path) -> np.ndarray:
    import cv2

    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def _view_shows_bus_and_overlay(img: np.ndarray) -> dict:
    p = panels(img)
    return {"map_fused": colour_pixels(p["map"], FUSED), "map_truth": colour_pixels(p["map"], TRUTH),
            "camera_tags": colour_pixels(p["cameras"], USED_TAG), "camera_fused": colour_pixels(p["cameras"], FUSED),
            "map_tags": colour_pixels(p["map"], USED_TAG, tol=25)}  # yellow: not the orange RSU footprints


def _good(c: dict) -> bool:
    return c["map_fused"] > 40 and c["map_truth"] > 40 and c["camera_tags"] > 40


class Demo:
    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.recording = tmp / "run.mcap"
        self.report = tmp / "report.json"
        self.logs = tmp / "logs"
        self.out = tmp / "demo.out"
        argv = [sys.executable, "-m", "toptag", "demo", "--scenario", str(SCENARIO), "--duration", "900",
                "--view", "--record", str(self.recording), "--record-frames", "--report", str(self.report),
                "--logs", str(self.logs), "--period", "1"]
        with open(self.out, "wb") as f:
            self.proc = subprocess.Popen(argv, cwd=REPO, env=clean_env(), stdout=f, stderr=subprocess.STDOUT,
                                         stdin=subprocess.DEVNULL, start_new_session=True)

    def text(self) -> str:
        return self.out.read_text(errors="replace")

    def log(self, name: str) -> str:
        try:
            return (self.logs / f"{name}.log").read_text(errors="replace")
        except FileNotFoundError:
            return ""

    def url(self) -> str | None:
        m = re.search(r"live view: (http://\S+)", self.text())
        return m.group(1) if m else None

    def fixes(self) -> int:
        found = re.findall(rf"{BUS}\s+fixes\s+(\d+)", self.text())
        return int(found[-1]) if found else 0


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo with the live view and a recording, screenshots taken while it runs; stopped (SIGTERM,
    as Ctrl-C) once the bus has been fixed for a while."""
    from playwright.sync_api import sync_playwright

    tmp = tmp_path_factory.mktemp("demo")
    d = Demo(tmp)
    d.shot = None
    d.counts = None
    t0 = time.monotonic()
    d.phases = {}
    try:
        assert wait_until(lambda: d.url() is not None or d.proc.poll() is not None, 90), d.text()[-3000:]
        assert d.url(), d.text()[-3000:]
        d.phases["view url"] = time.monotonic() - t0
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_FLAGS[1:],
                                         headless=True)
            try:
                page = browser.new_page(viewport=VIEWPORT)
                # Nothing but the viewer itself: the page's web-font links would otherwise stall each
                # screenshot ("waiting for fonts") on a machine without internet.
                page.route(re.compile(r"^(?!https?://127\.0\.0\.1[:/]).*"), lambda route: route.abort())
                page.goto(d.url(), timeout=120_000)
                cdp = page.context.new_cdp_session(page)
                d.phases["page loaded"] = time.monotonic() - t0
                # The view has drawn a camera image with the RSU's detections over it...
                assert wait_until(lambda: "first camera image with detections" in d.log("view")
                                  or d.proc.poll() is not None, 180), d.log("view")[-3000:]
                d.phases["first overlay drawn"] = time.monotonic() - t0
                # ...then the browser shows it: screenshots until the pixels say so.
                shot = tmp / "view.png"

                def shown() -> bool:
                    # DevTools' own capture: Playwright's screenshot first waits for web fonts, which
                    # never settle here while the viewer keeps the page busy.
                    shot.write_bytes(base64.b64decode(cdp.send("Page.captureScreenshot", {"format": "png"})["data"]))
                    d.counts = _view_shows_bus_and_overlay(_read_png(shot))
                    return _good(d.counts) or d.proc.poll() is not None
                # The tags are on a camera only while the bus is in its view (a few seconds of each 17.7 s
                # loop) and the RSU processed that frame; on a loaded machine the RSUs process few frames and
                # the browser's viewer lags: keep looking (a fresh clone at load 25 needed more than 240 s).
                wait_until(shown, 600, 2.0)
                d.shot = shot
                d.phases["screenshot shows it"] = time.monotonic() - t0
            finally:
                browser.close()
        assert wait_until(lambda: d.fixes() >= 30 or d.proc.poll() is not None, 180), d.text()[-3000:]
        d.phases["30 fixes"] = time.monotonic() - t0
    finally:
        if d.proc.poll() is None:
            os.kill(d.proc.pid, signal.SIGTERM)
        try:
            d.proc.wait(60)
        except subprocess.TimeoutExpired:
            stop_process(d.proc)
    d.phases["demo stopped"] = time.monotonic() - t0
    print("demo phases (s):", {k: round(v, 1) for k, v in d.phases.items()}, "pixels:", d.counts)
    return d


def test_live_view_in_a_browser_shows_the_buses_on_the_map_and_the_tags_on_the_camera(demo):
    assert demo.shot is not None and demo.counts is not None, demo.text()[-2000:]
    c = demo.counts
    assert _good(c), (c, demo.phases)
    # The checks tell the panels apart: no fused-pose magenta on the cameras, no tag yellow on the map.
    assert c["camera_fused"] < 0.1 * c["map_fused"] and c["map_tags"] < 0.1 * c["camera_tags"], c
    FIGURE.parent.mkdir(parents=True, exist_ok=True)
    if os.environ.get("TOPTAG_UPDATE_FIGURES"):
        shutil.copy(demo.shot, FIGURE)


def test_demo_records_every_kind_of_message(demo):
    assert demo.proc.returncode == 0, demo.text()[-3000:]
    assert "recording written to" in demo.text()
    kinds = {}
    for m in read_recording(demo.recording):
        name = m.message_type.__name__ if m.message_type else "other"
        kinds[name] = kinds.get(name, 0) + 1
    for name in ("Frame", "ImuBatch", "GroundTruth", "GnssFix", "PoseFix", "FusedPose", "RsuStatus", "TagDetections",
                 "Approach"):
        assert kinds.get(name, 0) > 0, kinds
    assert "other" not in kinds


@pytest.fixture(scope="module")
def replayed(demo, tmp_path_factory):
    """`toptag demo --replay`: the recorded drive (the simulator's outputs only, shifted to now) through
    a fresh router, fresh RSUs and a fresh bus, scored by the demo's monitor as the originals were."""
    tmp = tmp_path_factory.mktemp("replay")
    report = tmp / "report.json"
    # The bus's first pass (the scenario loops every 17.7 s): enough to compare, and short.
    p = subprocess.run([sys.executable, "-m", "toptag", "demo", "--scenario", str(SCENARIO),
                        "--replay", str(demo.recording), "--duration", str(REPLAY_S), "--report", str(report),
                        "--logs", str(tmp / "logs")], cwd=REPO, env=clean_env(), capture_output=True, text=True,
                       timeout=600)
    assert p.returncode == 0, p.stdout[-3000:] + p.stderr[-3000:]
    return json.loads(report.read_text()), (tmp / "logs" / "replay.log").read_text()


def test_a_replayed_drive_through_fresh_rsus_and_bus_is_as_accurate(demo, replayed):
    original = json.loads(demo.report.read_text())["buses"][BUS]
    summary, replay_log = replayed
    again = summary["buses"][BUS]
    assert all(code == 0 for code in summary["exit_codes"].values()), summary["exit_codes"]
    assert "lateness against the recorded pacing" in replay_log
    assert again["fixes_received"] >= 10 and len(again["fixes_by_rsu"]) == len(RSUS), again
    # Same accuracy: the fresh processes' fixes and fused poses against the recorded (shifted) truth.
    for key in ("fix_pos_rms_m", "fused_pos_rms_m"):
        assert original[key] is not None and again[key] is not None, (original, again)
        # Real-camera corner noise (issue 11's calibrated image model) makes single fixes ~5 cm: a replay
        # that gets fewer fixes on a busy machine fuses fewer of them, hence the 4 cm allowance.
        assert again[key] < max(2 * original[key], original[key] + 0.04), (key, original, again)
    assert again["fix_pos_rms_m"] < 0.10 and again["fused_pos_rms_m"] < 0.08, again  # fewer fixes: see above


def test_offline_fusion_of_the_recorded_demo_is_repeatable(demo, tmp_path):
    outs = []
    for i in range(2):
        out = tmp_path / f"r{i}.json"
        p = subprocess.run([sys.executable, "-m", "toptag", "eval", "replay", str(demo.recording), "--bus", BUS,
                            "--out", str(out)], cwd=REPO, capture_output=True, text=True, timeout=300)
        assert p.returncode == 0, p.stderr
        outs.append(json.loads(out.read_text()))
    assert outs[0] == outs[1]  # bit for bit, digest of every estimate included
    r = outs[0]
    assert r["fixes"] > 20 and r["fused_vs_truth"]["n"] > 20, r
    assert r["fused_vs_truth"]["rms_m"] < 0.05, r
