"""End to end in a real headless Chromium: train.py trainer=interactive (Tetris, and domain=keepaway), a page,
keys pressed, and what the page says checked against what the run saved.

What is covered: each press filed under the placement (or keepaway moment) on screen the reaction allowance
before it, as the page is told and as the feedback log holds it; keys after using the speed slider and the
buttons; the layout at 390 px and 1280 px (nothing wider than the window, the Good and Bad buttons never
move); a dropped connection and a reloaded page (nothing lost or counted twice); Finish and save and its
summary page; Ctrl-C with a page open (the page says so within 2 s, a press after it is not counted, the
run exits within 2 s).

Needs Debian's chromium (``/usr/bin/chromium``, installed by ``.ci/run``) and the ``playwright`` package
(which drives it; no browser download). Skipped, saying why, where either is missing.
"""

from __future__ import annotations

import contextlib
import json
import re
import signal
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest
import torch
from chromium import ARGS, CHROMIUM, needs_chromium

from hfrl_torch.common.checkpoint import load_checkpoint
from hfrl_torch.feedback.log import load_feedback_log

if TYPE_CHECKING:
    from playwright.sync_api import Page

ROOT = Path(__file__).resolve().parents[2]
playwright = pytest.importorskip("playwright.sync_api", reason="the playwright package is not installed")
pytestmark = needs_chromium
REACTION_S = 0.3
# test-side only: remember every frame the page receives and every key pressed, with their times
RECORD_FRAMES = """
window.__frames = [];
window.__covers = [];  // every text the board's cover showed
new MutationObserver(() => {
  const c = document.getElementById("cover-text");
  const last = window.__covers[window.__covers.length - 1];
  if (c && c.textContent && last !== c.textContent) window.__covers.push(c.textContent);
}).observe(document, { subtree: true, childList: true, characterData: true });
window.__keys = [];
window.__opened = 0;
document.addEventListener("keydown", (e) => window.__keys.push(performance.now()), true);
const PageSocket = window.WebSocket;
window.WebSocket = class extends PageSocket {
  constructor(...args) {
    super(...args);
    this.addEventListener("open", () => { window.__opened = performance.now(); });
    this.addEventListener("message", (e) => {
      const m = JSON.parse(e.data);
      if (m.type === "tetris" || m.type === "keepaway") window.__frames.push({ t: performance.now(), ...m });
    });
  }
};
"""
# resolves at a moment when the frame on screen REACTION_S ago is unambiguous (no frame change within
# `margin` ms either side, and it came on this connection), another frame has replaced it on screen (so that
# filing under the one before shows), and presses are taken
SAFE_MOMENT = """([r, margin]) => new Promise((resolve) => {
  const check = () => {
    const f = window.__frames, now = performance.now(), at = now - r * 1000;
    let i = -1;
    for (let j = 0; j < f.length; j++) if (f[j].t <= at) i = j;
    const next = i + 1 < f.length ? f[i + 1].t : Infinity;
    const ok = i >= 0 && f[i].t >= window.__opened && at - f[i].t > margin && next - at > margin &&
      now - next > margin &&
      f[i].action !== "-";  // keepaway: a decision of this episode is on screen
    if (ok && !document.getElementById("good").disabled) {
      resolve(true);
    } else setTimeout(check, 5);
  };
  check();
})"""
# the frames on screen REACTION_S before the last key press: the one then, and its neighbour when the
# moment lies within `margin` ms of a frame change (arrival and press times are measured on the page);
# and the frame on screen at the press itself
FILED = """([r, margin]) => {
  const f = window.__frames, t = window.__keys[window.__keys.length - 1], at = t - r * 1000;
  const strip = ({ board, before_clear, keepers, takers, ...rest }) => rest;
  let i = -1, k = -1;
  for (let j = 0; j < f.length; j++) { if (f[j].t <= at) i = j; if (f[j].t <= t) k = j; }
  const near = [f[i]];
  if (i > 0 && at - f[i].t < margin) near.push(f[i - 1]);
  if (i + 1 < f.length && f[i + 1].t - at < margin) near.push(f[i + 1]);
  return { near: near.map(strip), now: strip(f[k]) };
}"""
LAYOUT = """() => {
  const width = document.documentElement.clientWidth;
  const wide = [...document.querySelectorAll("body *")].filter((e) => {
    const r = e.getBoundingClientRect();
    return r.width > 0 && (r.right > width + 0.5 || r.left < -0.5);
  }).map((e) => e.id || e.tagName);
  return { width, scroll: document.documentElement.scrollWidth, wide };
}"""
BUTTONS = """() => ["good", "bad"].map((id) => {
  const r = document.getElementById(id).getBoundingClientRect();
  return [r.x, r.y, r.width, r.height];
})"""


def _url(proc: subprocess.Popen, said: deque[str], timeout: float = 120) -> str:
    """The page's URL from train.py's stderr; the lines after it go on into ``said`` (a full pipe would block
    the run), so that a failing test can show what the run printed."""
    deadline = time.time() + timeout
    assert proc.stderr is not None
    while time.time() < deadline:
        line = proc.stderr.readline()
        said.append(line)
        if "Teach the agent in your browser:" in line:
            threading.Thread(target=said.extend, args=(proc.stderr,), daemon=True).start()
            return line.split("browser:", 1)[1].strip()
        if not line and proc.poll() is not None:
            break
    raise AssertionError("train.py did not print the page's URL")


@contextlib.contextmanager
def _teach(run_dir: Path, *overrides: str) -> Iterator[tuple[subprocess.Popen, Page]]:
    """train.py with the browser trainer on a free port and a Chromium page on it, once it teaches."""
    args = [sys.executable, str(ROOT / "train.py"), "trainer=interactive", "trainer.port=0", *overrides]
    args += ["logger.backend=none", f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    said: deque[str] = deque(maxlen=40)
    try:
        url = _url(proc, said)
        with playwright.sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.add_init_script(RECORD_FRAMES)
            console: deque[str] = deque(maxlen=20)
            page.on("console", lambda m: console.append(f"{m.type}: {m.text}\n"))
            page.goto(url)
            try:
                _pressable(page, 90_000)
                yield proc, page
            except Exception as e:
                run_said, page_said = "".join(said).replace("\r", "\n"), "".join(console)
                raise AssertionError(
                    f"{e}\n--- train.py's stderr:\n{run_said}\n--- the page's console:\n{page_said}"
                ) from e
            browser.close()
    finally:
        if proc.poll() is None:
            proc.kill()


def _pressable(page: Page, timeout_ms: int) -> None:
    """Wait until Good can be pressed; if it cannot, fail with what the page says instead."""
    try:
        page.wait_for_function("!document.getElementById('good').disabled", timeout=timeout_ms)
    except playwright.TimeoutError:
        said = page.inner_text("#status")
        raise AssertionError(f"Good still disabled after {timeout_ms} ms; the page says {said!r}") from None


def _twice_at_once(page: Page, key: str) -> None:
    """Press ``key`` twice within one task of the page, so that no reply from the run can come in between
    (a person pressing twice quickly on a slow connection), then wait until the run has confirmed both."""
    page.evaluate(
        "(k) => { for (const i of [0, 1]) document.dispatchEvent(new KeyboardEvent('keydown', {key: k})); }",
        key,
    )
    page.wait_for_function("Object.keys(S.asked).length === 0", timeout=10_000)


def _given(page: Page) -> int:
    return int(page.inner_text("#given"))


def _press_safely(page: Page, key: str, margin: float = 80) -> dict[str, Any]:
    """Press ``key`` at a moment when the frame on screen the allowance before is unambiguous; returns the
    frames on screen the allowance before the key went down (``near``: that one, and its neighbour if that
    moment was within 20 ms of a frame change), the one on screen at it (``now``) and what the page says
    the press was filed under (``said``). A press the run refuses, saying why (on a loaded machine the game
    may end between the safe moment and the key), is not counted and is tried again, up to 3 times."""
    refused = []
    for _ in range(3):
        before = _given(page)
        page.evaluate(SAFE_MOMENT, [REACTION_S, margin])
        page.evaluate("document.getElementById('last-press').classList.remove('refused')")
        page.keyboard.press(key)
        page.wait_for_function(
            f"Number(document.getElementById('given').textContent) === {before + 1} ||"
            " document.getElementById('last-press').classList.contains('refused')"
        )
        said = page.inner_text("#last-press")
        if _given(page) == before + 1:
            return {**page.evaluate(FILED, [REACTION_S, 20]), "said": said}
        assert "not counted" in said and _given(page) == before, said
        refused.append(said)
    raise AssertionError(f"3 presses in a row were refused: {refused}")


def _filed(press: dict[str, Any]) -> dict[str, Any]:
    """The frame among ``press["near"]`` the page says the press was filed under (AssertionError: none)."""
    for frame in press["near"]:
        if f"(placement {frame['placement']} of game {frame['game']})" in press["said"]:
            return frame
    raise AssertionError(f"{press['said']!r} is none of {press['near']}")


def _fits(page: Page, width: int) -> None:
    page.set_viewport_size({"width": width, "height": 900})
    page.wait_for_timeout(50)
    layout = page.evaluate(LAYOUT)
    assert layout["scroll"] <= width and layout["wide"] == [], layout


COLUMNS = """() => {
  const v = document.getElementById("view").getBoundingClientRect();
  return Array.from(document.querySelectorAll("#columns span"), (s) => {
    const r = s.getBoundingClientRect();
    return [s.textContent, r.x + r.width / 2, v.x + 2, v.width - 4];
  });
}"""


def _numbered(page: Page, width: int) -> None:
    """The board's columns are numbered 1..width under the board, each number under its own column."""
    spans = page.evaluate(COLUMNS)
    assert [t for t, *_ in spans] == [str(i) for i in range(1, width + 1)], spans
    for i, (_, centre, left, inner) in enumerate(spans):
        assert abs(centre - (left + (i + 0.5) * inner / width)) < 2, (i, spans)


def _unmoved(page: Page, states: list[str]) -> None:
    """The Good and Bad buttons stay where they are while the page goes through ``states``."""
    where = page.evaluate(BUTTONS)
    for key in states:
        page.keyboard.press(key)
        page.wait_for_timeout(150)
        assert page.evaluate(BUTTONS) == where, key


MOVED_OFF_4 = "document.getElementById('speed-value').innerText != '4'"


def test_tetris_presses_are_filed_and_counted_as_saved_through_reconnects_and_finish(tmp_path):
    run_dir = tmp_path / "live"
    overrides = ["trainer.actions_per_s=4", "agent.iterations=50", "agent.population=10"]
    overrides += ["agent.games_per_candidate=1", "agent.eval_games=2", "agent.watch_pieces=60"]
    with _teach(run_dir, *overrides) as (proc, page):
        # the default weight (adaptive): CE compares its arms on the same games after each practice round
        assert "placement" in page.inner_text("#status") and "(fusion.weight=adaptive)" in page.inner_text(
            "#weight-sentence"
        )
        presses = [_press_safely(page, key) for key in ["/", "/", "z"]]
        # keys after the slider: its number follows the drag, then keys go on working
        # shown while dragging, before the change is sent. Under load the first drag sometimes leaves the
        # slider where it was (cause not found); a person would drag again, and so does this
        for _ in range(3):
            box = page.locator("#speed").bounding_box()
            page.mouse.move(box["x"] + box["width"] * 0.17, box["y"] + box["height"] / 2)
            page.mouse.down()
            page.mouse.move(box["x"] + box["width"] * 0.10, box["y"] + box["height"] / 2, steps=4)
            try:
                page.wait_for_function(MOVED_OFF_4, timeout=2000)
                break
            except playwright.TimeoutError:
                page.mouse.up()
        else:
            raise AssertionError("three drags did not move the speed slider off 4")
        page.mouse.up()
        presses.append(_press_safely(page, "/"))
        page.focus("#speed")  # even with the slider focused
        presses.append(_press_safely(page, "z"))
        page.click(
            "#pause"
        )  # paused and resumed with the button, each once the server has said so, then keys
        page.wait_for_function("document.querySelector('#pause').textContent.startsWith('Resume')")
        page.click("#pause")
        page.wait_for_function("document.querySelector('#pause').textContent.startsWith('Pause')")
        presses.append(_press_safely(page, "/"))
        for p in presses:  # filed under what was on screen 0.3 s before, which is not what is on screen
            seen, word = _filed(p), "Good" if p["said"].startswith("Good") else "Bad"
            assert (
                p["said"]
                == f"{word} → {seen['label']} (placement {seen['placement']} of game {seen['game']})"
            )
            assert (seen["game"], seen["placement"]) != (p["now"]["game"], p["now"]["placement"])

        _numbered(page, 10)
        steered = page.inner_text("#steered")  # what the teaching did to the agent's moves, in numbers
        assert re.search(r"Your teaching changed (\d+) of its (\d+) moves this game\.$", steered), steered
        _unmoved(page, ["p", "p", "h", "h"])  # paused, away: other words, same buttons
        _fits(page, 390)
        _numbered(page, 10)
        _unmoved(page, ["p", "p", "h", "h"])
        _fits(page, 1280)
        for key in ["p", "h"]:  # a second press before the first is confirmed undoes it
            _twice_at_once(page, key)
        assert page.evaluate("[S.paused, S.here]") == [False, True], page.inner_text("#status")

        counted, where = _given(page), page.evaluate(BUTTONS)
        page.evaluate("S.ws.close()")  # the connection drops: a press then is not counted
        page.wait_for_function(
            "document.getElementById('status').textContent.includes('Connection to the run lost')"
        )  # and the run holds still for it: with the page away, 50 practice rounds would take well under 1 s
        assert "the agent waits up to 10 s for this page" in page.inner_text("#status")
        page.keyboard.press("/")
        assert "not counted" in page.inner_text("#last-press") and _given(page) == counted
        assert page.evaluate(BUTTONS) == where  # the buttons stay put
        _pressable(page, 30_000)
        presses.append(_press_safely(page, "/"))
        page.reload()  # a new page: it shows the run's count, not zero
        _pressable(page, 60_000)
        assert _given(page) == counted + 1
        presses.append(_press_safely(page, "z"))
        (tmp_path / "page.png").write_bytes(page.screenshot())

        page.wait_for_function(  # since the reload, a game of the person's ended and the page said how
            "window.__covers.some((c) => /^Game over: \\d+ lines? in game \\d+\\. Practising/.test(c))",
            timeout=60_000,
        )
        asked: list[str] = []
        page.once("dialog", lambda d: (asked.append(d.message), d.dismiss()))
        page.click("#finish")  # asked first; "Cancel" leaves the run going
        time.sleep(1.0)
        assert asked and "Finish and save now?" in asked[0] and not page.is_visible("#summary")
        page.once("dialog", lambda d: d.accept())
        page.click("#finish")
        page.wait_for_selector("#summary", state="visible", timeout=60_000)
        summary = page.inner_text("#summary")
        assert "You finished the session" in summary and f"{len(presses)} presses counted" in summary
        assert f"resume={run_dir}" in page.inner_text("#summary-resume")
        saved = page.inner_text("#summary-saved")
        assert f"Checkpoint: {run_dir / 'checkpoints' / 'last.pt'}" in saved
        assert f"Your presses: {run_dir / 'feedback.jsonl'}" in saved
        points = page.evaluate("S.ended.curve")  # the agent's curve, rounds with the person filled
        change = page.inner_text("#summary-change")
        assert any(p[2] >= 0.5 for p in points) and "lines per test game. With you (filled)" in change
        assert page.locator("#summary-list li").count() == len(presses)
        assert f"This summary: {run_dir / 'teaching_summary.json'}" in saved
        assert "reloading it or opening it again will not show this summary" in page.inner_text(
            "#summary-keep"
        )
        with page.expect_download() as download:
            page.click("#summary-download")
        copy = json.loads(Path(download.value.path()).read_text())
        _fits(page, 390)
        assert proc.wait(timeout=60) == 0
    kept = json.loads((run_dir / "teaching_summary.json").read_text())
    assert kept["given"] == copy["given"] == len(presses) and kept["reason"] == "finished_by_you"
    assert [p["filed"] for p in kept["presses"]] == [p["filed"] for p in copy["presses"]]

    events = load_feedback_log(run_dir / "feedback.jsonl")
    assert len(events) == len(presses) and len({e.id for e in events}) == len(events)
    assert [e.value for e in events] == [1.0 if p["said"].startswith("Good") else -1.0 for p in presses]
    assert [(e.episode, e.step) for e in events] == [
        (_filed(p)["round"] - 1, _filed(p)["placement"] - 1) for p in presses
    ]
    assert {e.source for e in events} == {"human:browser"}
    state = load_checkpoint(run_dir)["state"]
    assert torch.count_nonzero(torch.as_tensor(state["human"]["weight"])) > 0  # H^ learned from the person


def _stop_with_ctrl_c(proc: subprocess.Popen, page: Page, presses: int) -> tuple[float, float, int]:
    """SIGINT to train.py with the page open: seconds until the page says the run is stopping, until the run
    has exited, and its exit status; a press made after the stop must not be counted."""
    proc.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    page.wait_for_function(  # in words, on the page: the status line, or the summary once the run has ended
        "document.getElementById('status').textContent.startsWith('The run is stopping') ||"
        " !document.getElementById('summary').hidden",
        timeout=5_000,
        polling=10,
    )
    told = time.monotonic() - t0
    page.keyboard.press("/")  # after the stop: not counted
    rc = proc.wait(timeout=10)
    stopped = time.monotonic() - t0
    page.wait_for_selector("#summary", state="visible", timeout=5_000)
    assert "stopped from the terminal" in page.inner_text("#summary-title")
    assert f"{presses} presses counted" in page.inner_text("#summary-presses") and _given(page) == presses
    return told, stopped, rc


def test_ctrl_c_with_a_tetris_page_open_is_said_at_once_and_stops_within_2_s(tmp_path):
    run_dir = tmp_path / "live"
    overrides = ["trainer.actions_per_s=4", "agent.iterations=20", "agent.population=10"]
    overrides += ["agent.games_per_candidate=1", "agent.eval_games=2", "agent.watch_pieces=200"]
    with _teach(run_dir, *overrides) as (proc, page):
        _press_safely(page, "/")
        told, stopped, rc = _stop_with_ctrl_c(proc, page, 1)
    assert told < 2.0 and stopped < 2.0 and rc == 130, (told, stopped, rc)
    assert [e.value for e in load_feedback_log(run_dir / "feedback.jsonl")] == [1.0]


def test_keepaway_presses_are_filed_under_the_moment_shown_before_them_and_ctrl_c_stops(tmp_path):
    run_dir = tmp_path / "live"
    overrides = ["domain=keepaway", "trainer.wait_for_page_s=60", "agent.hours=0.05", "agent.table_bits=12"]
    with _teach(run_dir, *overrides) as (proc, page):
        assert "keepers" in page.inner_text("#help") and page.inner_text("#speed-unit").startswith(
            "decisions"
        )
        presses = [_press_safely(page, key, margin=30) for key in ["/", "z"]]
        page.wait_for_function("document.getElementById('steered').textContent !== ''", timeout=15_000)
        steered = page.inner_text("#steered")  # what the teaching did to the keepers' decisions, in numbers
        assert re.search(r"Your teaching changed (\d+) of their (\d+) decisions this episode\.$", steered), (
            steered
        )
        box = page.locator("#speed").bounding_box()
        page.mouse.click(box["x"] + 3, box["y"] + box["height"] / 2)  # the slowest speed, then keys
        presses.append(_press_safely(page, "/", margin=30))
        for p in presses:  # "keeper 2 passes to keeper 3 (episode 4, 2.3 s)": the moment 0.3 s before
            episode, seconds = re.search(r"\(episode (\d+), ([\d.]+) s\)$", p["said"]).groups()
            near = [(f["episode"], f["time_s"]) for f in p["near"]]
            assert (int(episode), float(seconds)) in near, (p["said"], near)
            assert (p["now"]["episode"], p["now"]["time_s"]) not in near  # not the moment of the press
        _fits(page, 390)
        _unmoved(page, ["p", "p", "h", "h"])
        _fits(page, 1280)
        told, stopped, rc = _stop_with_ctrl_c(proc, page, len(presses))
        _fits(page, 390)
    assert told < 2.0 and stopped < 2.0 and rc == 130, (told, stopped, rc)
    events = load_feedback_log(run_dir / "feedback.jsonl")
    assert [e.value for e in events] == [1.0, -1.0, 1.0] and {e.source for e in events} == {"human:browser"}
    assert all(0.0 <= e.time <= 200.0 and e.episode >= 0 for e in events)  # on the field's simulated clock
    human = load_checkpoint(run_dir)["state"]["human"]
    assert human["trainer"]["given"] == 3 and torch.count_nonzero(human["human_weight"]) > 0
