"""The participant's whole study in a real headless Chromium, against a real ``study.py`` with a tiny Tetris
condition: at 390 px and 1280 px, start, consent, instructions, a practice where a press visibly changes the
scripted dot, the reaction-time check, the teaching page reached through the study's proxy with a press
acknowledged, Finish and save, Continue, the questionnaire and the end; the researcher's table; and a page
on another origin that frames the study gets nothing.

Needs Debian's chromium and the ``playwright`` package; skipped, saying why, where either is missing.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import time
import urllib.request
from pathlib import Path
from typing import TYPE_CHECKING

import pytest

sys.path.insert(
    0, str(Path(__file__).resolve().parents[1] / "interactive")
)  # the browser tests' shared setup
from chromium import ARGS, CHROMIUM, decoy_site, needs_chromium

if TYPE_CHECKING:
    from playwright.sync_api import Page

ROOT = Path(__file__).resolve().parents[2]
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = [needs_chromium, pytest.mark.serial]  # drives a browser: run alone
URL = re.compile(r"(https?://127\.0\.0\.1:\d+/)(\S*)")
# CE on 6x8 boards: one watched game per iteration, short, so Finish and save ends within seconds
TETRIS = [
    "domain=tetris",
    "agent=cem",
    "agent.iterations=20",
    "agent.population=6",
    "agent.games_per_candidate=1",
]
TETRIS += ["agent.eval_games=1", "agent.watch_pieces=40", "domain.width=6", "domain.height=8"]
COMMON = ["trainer.wait_for_page_s=120", "threads=1", "logger.backend=none"]
NO_SIDEWAYS_SCROLL = "() => document.documentElement.scrollWidth <= window.innerWidth"


def quoted(values: list[str]) -> str:
    return "[" + ",".join(f"'{v}'" for v in values) + "]"


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """``study.py`` serving a one-condition Tetris study: its participants' link, researcher's link and
    directory."""
    directory = tmp_path_factory.mktemp("browser") / "study"
    log = directory.parent / "study.log"
    args = [
        sys.executable,
        str(ROOT / "study.py"),
        "study=pilot",
        "study.name=browser",
        f"study.dir={directory}",
        "study.port=0",
        "study.practice_s=5",
        "study.calibration.trials=2",
        f"study.common={quoted(COMMON)}",
        f"study.conditions=[{{label:tetris_tiny,overrides:{quoted(TETRIS)}}}]",
    ]
    with log.open("w") as out:
        proc = subprocess.Popen(args, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    links: dict[str, str] = {}
    deadline = time.monotonic() + 90
    while len(links) < 2 and time.monotonic() < deadline and proc.poll() is None:
        for base, rest in URL.findall(log.read_text()):
            links["admin" if rest.startswith("admin") else "participants"] = base + rest
        time.sleep(0.2)
    if len(links) < 2:
        os.killpg(proc.pid, signal.SIGKILL)
        pytest.fail(f"study.py did not print its links:\n{log.read_text()[-3000:]}")
    yield links["participants"], links["admin"], directory
    proc.send_signal(signal.SIGTERM)
    try:
        assert proc.wait(timeout=60) == 0, log.read_text()[-3000:]
    finally:
        with contextlib.suppress(ProcessLookupError):  # a worker that outlived it
            os.killpg(proc.pid, signal.SIGKILL)


def fits(page: Page) -> None:
    assert page.evaluate(NO_SIDEWAYS_SCROLL), f"sideways scroll at {page.viewport_size} on {page.url}"


def through_calibration(page: Page, base: str) -> str:
    """Start, consent, instructions, practice (a press steers the dot), calibration; returns the code."""
    page.goto(base)
    page.click("#start")
    page.wait_for_url(re.compile(r"/p/[A-Z2-9]{12}/$"))
    code = page.url.rstrip("/").rsplit("/", 1)[-1]
    page.wait_for_selector("#consent:not([hidden])")
    assert "agent" in page.inner_text("#consent-text")
    fits(page)
    page.click("#agree")
    page.wait_for_selector("#instructions:not([hidden])")
    fits(page)
    page.click("#instructions-next")
    page.wait_for_selector("#practice:not([hidden])")
    fits(page)
    page.wait_for_function("() => document.getElementById('lean-text').textContent.includes('%')")
    page.wait_for_timeout(900)  # the dot has made a step
    before = float(page.get_attribute("#lean", "data-right"))
    page.keyboard.press("/")  # Good for the step it just took
    after = float(page.get_attribute("#lean", "data-right"))
    assert after != before, "a press did not change the practice dot's leaning"
    assert "more often" in page.inner_text("#practice-last")
    page.click("#p-bad")
    assert float(page.get_attribute("#lean", "data-right")) != after
    page.wait_for_selector("#practice-next:not([disabled])", timeout=15000)
    page.click("#practice-next")
    page.wait_for_selector("#calibration:not([hidden])")
    fits(page)
    for _ in range(2):
        page.focus("#target-box")
        page.keyboard.press("Space")
        page.wait_for_selector("#target:not([hidden])", timeout=10000)
        page.wait_for_timeout(250)  # a person's reaction (under 50 ms counts as pressing too soon)
        page.keyboard.press("Space")
    page.wait_for_selector("#teaching:not([hidden])")
    fits(page)
    return code


def teach_and_finish(page: Page, directory: Path, code: str) -> None:
    """The teaching page through the proxy: a press acknowledged, Finish and save, Continue."""
    page.click("#teach-link")
    page.wait_for_url(re.compile(r"/teach/$"))
    page.wait_for_selector("#good:not([disabled])", timeout=90000)
    fits(page)
    refused = []
    for _ in range(20):  # a press the run refuses (nothing judged on screen yet) says so; the next one counts
        page.keyboard.press("/")
        page.wait_for_timeout(600)
        if page.inner_text("#given") != "0":
            break
        refused.append(page.inner_text("#last-press"))
    assert page.inner_text("#given") == "1", refused
    assert "→" in page.inner_text("#last-press")  # the run's acknowledgement, relayed by the study
    assert page.is_hidden("#weight") and "fusion" not in page.inner_text("body")  # blind to the condition
    page.once("dialog", lambda d: d.accept())
    page.click("#finish")
    page.wait_for_selector("#summary:not([hidden])", timeout=60000)
    assert page.is_hidden("#summary-run")  # no run paths or terminal commands for a participant
    fits(page)
    page.click("#summary-continue a")
    page.wait_for_url(re.compile(r"/p/[A-Z2-9]{12}/$"))
    page.wait_for_selector("#questionnaire:not([hidden])", timeout=30000)
    fits(page)
    presses = directory / "participants" / code / "run" / "presses.jsonl"
    assert presses.exists() and presses.read_text().count("\n") >= 1


def answer(page: Page) -> None:
    page.click("#answers button[type=submit]")  # unanswered: the page asks for them
    assert "Please answer" in page.inner_text("#answers-error")
    for box in page.query_selector_all("#answers fieldset[data-kind=likert]"):
        box.query_selector_all("input")[2].check()
    page.fill("#answers textarea", "It was fun.")
    page.click("#answers button[type=submit]")
    page.wait_for_selector("#done:not([hidden])")
    assert "press" in page.inner_text("#done-summary")
    fits(page)


def test_the_whole_participant_flow_at_390_and_1280_px(study):
    base, admin, directory = study
    with playwright.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
        narrow = browser.new_page(viewport={"width": 390, "height": 844})
        wide = browser.new_page(viewport={"width": 1280, "height": 800})
        codes = [through_calibration(narrow, base), through_calibration(wide, base)]  # both runs start
        for page, code in zip((narrow, wide), codes, strict=True):
            teach_and_finish(page, directory, code)
            answer(page)
        researcher = browser.new_page(viewport={"width": 1280, "height": 800})
        researcher.goto(admin)
        try:
            researcher.wait_for_function("() => document.querySelectorAll('#rows tr').length === 2")
        except playwright.Error:
            pytest.fail(f"the researcher's page shows:\n{researcher.inner_text('body')}")
        table = researcher.inner_text("#rows")
        assert all(code in table for code in codes) and "tetris_tiny" in table and "done" in table
        for page in (narrow, wide):  # the participant's page never shows the condition
            assert "tetris_tiny" not in page.content()
        browser.close()


def test_a_page_on_another_origin_cannot_frame_the_study(study):
    base, _, _ = study
    joined = urllib.request.Request(base + "api/join", data=b'{"simulated": true}', method="POST")
    with urllib.request.urlopen(joined, timeout=10) as r:
        code = json.load(r)["code"]
    pages = [base, f"{base}p/{code}/", f"{base}p/{code}/teach/"]
    site, decoy = decoy_site(pages)
    try:
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page()
            page.goto(decoy)
            time.sleep(2.0)
            framed = [f for f in page.frames if f != page.main_frame]
            assert len(framed) == 3
            for frame in framed:  # the browser refused each frame: its error page, none of the study's
                assert frame.url.startswith("chrome-error://"), frame.url
                assert "study.js" not in frame.content() and "app.js" not in frame.content()
            browser.close()
    finally:
        site.shutdown()
