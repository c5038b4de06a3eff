"""Make the README's screenshots of the browser trainer with a scripted browser (Playwright driving Chromium).

    python docs/browser_screenshots.py [--out docs/img]

Nothing here is a person: a script presses the keys, by a fixed rule (Tetris: Good for a placement that
clears a line or adds no hole, Bad for one that adds holes, 0.4-0.7 s after the placement reached the
page; keepaway: Good and Bad in turn, 1-2.5 s apart), and every image is stamped as a scripted browser's.
It prints how many Tetris presses were filed under the placement they judged. The runs go to a temporary
directory; about 2.5 minutes. Needs Debian's chromium and the ``playwright`` package (the test extra).
"""

from __future__ import annotations

import argparse
import contextlib
import random
import shutil
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from PIL import Image
from playwright.sync_api import Error as PlaywrightError
from playwright.sync_api import Page, sync_playwright

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
STAMP = """() => {
  const d = document.createElement("div");
  d.textContent = "Screenshot from a scripted browser (Playwright + Chromium): " +
    "the presses are a script's, not a person's";
  Object.assign(d.style, { position: "fixed", right: "0", top: "0", background: "#223", color: "#ffe040",
    font: "12px system-ui, sans-serif", padding: "3px 8px", zIndex: 99 });
  document.body.appendChild(d);
}"""
# when each placement reached the page, and when each key went down (page clock)
RECORD = """
window.__arrived = {};
window.__keys = [];
document.addEventListener("keydown", () => window.__keys.push(performance.now()), true);
const PageSocket = window.WebSocket;
window.WebSocket = class extends PageSocket {
  constructor(...args) {
    super(...args);
    this.addEventListener("message", (e) => {
      const m = JSON.parse(e.data);
      if (m.type === "tetris") window.__arrived[`${m.game}:${m.placement}`] = performance.now();
    });
  }
};
"""
# resolves true at ``delay`` s after ``arrived`` (false, at once, if that moment has passed)
REACT = """([arrived, delay]) => new Promise((resolve) => {
  const wait = arrived + delay * 1000 - performance.now();
  if (wait < 0) resolve(false); else setTimeout(() => resolve(true), wait);
})"""
HOLES = """(board) => {
  let holes = 0;
  for (let c = 0; c < board[0].length; c++) {
    let roof = false;
    for (let r = board.length - 1; r >= 0; r--) { if (board[r][c]) roof = true; else if (roof) holes++; }
  }
  return holes;
}"""


def _train(run_dir: Path, *overrides: str) -> tuple[subprocess.Popen, str]:
    args = [sys.executable, str(ROOT / "train.py"), "trainer=interactive", "trainer.port=0", "threads=1"]
    args += [*overrides, "logger.backend=none", f"hydra.run.dir={run_dir}"]
    proc = subprocess.Popen(args, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    assert proc.stderr is not None
    for line in proc.stderr:
        if "Teach the agent in your browser:" in line:
            # go on reading its progress bars: a full pipe would block the run
            threading.Thread(target=proc.stderr.read, daemon=True).start()
            return proc, line.split("browser:", 1)[1].strip()
    raise RuntimeError("train.py did not print the page's URL")


def _shot(page: Page, path: Path) -> None:
    """The page as it is, stamped, in 128 colours (a small PNG)."""
    page.evaluate(STAMP)
    page.screenshot(path=str(path))
    image = Image.open(path).convert("RGB").quantize(colors=128, method=Image.Quantize.FASTOCTREE)
    image.save(path, optimize=True)
    print("wrote", path, path.stat().st_size, "bytes")


def _teach_tetris(page: Page, seconds: float, rng: random.Random, filed: list[tuple[float, bool]]) -> None:
    """Judge placements by the fixed rule for ``seconds``, pressing 0.4-0.7 s after each placement reached
    the page (a placement noticed too late for that is let go); appends to ``filed`` each press's delay
    after its placement reached the page and whether it was filed under that placement (as the page is
    told)."""
    end, seen, holes = time.monotonic() + seconds, (-1, -1), 0
    while time.monotonic() < end:
        frame = page.evaluate("S.frame")
        if frame and frame.get("placement") is not None and (frame["game"], frame["placement"]) != seen:
            seen = (frame["game"], frame["placement"])
            now = page.evaluate(HOLES, frame["board"])
            key = "/" if frame["cleared"] or now <= holes else "z"
            holes = now
            arrived = page.evaluate(f"window.__arrived['{seen[0]}:{seen[1]}']")
            if arrived is None or not page.evaluate(REACT, [arrived, rng.uniform(0.4, 0.7)]):
                continue
            if not page.locator("#good").is_disabled():
                given = page.inner_text("#given")
                page.keyboard.press(key)
                delay = (page.evaluate("window.__keys[window.__keys.length - 1]") - arrived) / 1000
                with contextlib.suppress(PlaywrightError):  # not taken (the game ended): no count
                    page.wait_for_function(
                        f"document.getElementById('given').textContent !== '{given}'", timeout=2000
                    )
                    said = page.inner_text("#last-press")
                    filed.append((delay, f"(placement {seen[1]} of game {seen[0]})" in said))
        time.sleep(0.02)


def tetris(out: Path, work: Path, rng: random.Random) -> None:
    overrides = ["trainer.wait_for_page_s=0", "agent.iterations=300", "agent.population=30"]
    overrides += ["agent.games_per_candidate=3", "agent.eval_games=10", "agent.watch_pieces=80"]
    proc, url = _train(work / "tetris", *overrides)
    filed: list[tuple[float, bool]] = []
    try:
        time.sleep(1.5)  # it practises alone first, at full speed: hollow points on the curve
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.add_init_script(RECORD)
            page.goto(url)
            page.wait_for_function("!document.getElementById('good').disabled", timeout=120_000)
            _teach_tetris(page, 40, rng, filed)
            page.wait_for_function("S.frame && S.frame.cleared > 0", timeout=120_000, polling=20)
            page.wait_for_timeout(100)  # the cleared rows glow
            _shot(page, out / "browser_trainer.png")
            page.keyboard.press("h")  # away: the board is covered with what is left
            page.wait_for_function("!document.getElementById('cover').hidden")
            page.wait_for_timeout(2500)
            _shot(page, out / "browser_trainer_away.png")
            page.keyboard.press("h")
            page.wait_for_function("!document.getElementById('good').disabled", timeout=120_000)
            _teach_tetris(page, 15, rng, filed)
            page.click("#finish")
            page.wait_for_selector("#summary", state="visible", timeout=120_000)
            _shot(page, out / "browser_trainer_summary.png")
            browser.close()
        proc.wait(timeout=60)
        right = sum(ok for _, ok in filed)
        delays = sorted(d for d, _ in filed)
        print(
            f"Tetris: {right} of {len(filed)} presses filed under the placement the script judged; "
            f"press delay after the placement reached the page {delays[0]:.2f}..{delays[-1]:.2f} s"
        )
    finally:
        if proc.poll() is None:
            proc.kill()


def keepaway(out: Path, work: Path, rng: random.Random) -> None:
    proc, url = _train(work / "keepaway", "domain=keepaway", "trainer.wait_for_page_s=0", "agent.hours=0.5")
    try:
        time.sleep(20)  # the keepers practise alone first, at full speed
        with sync_playwright() as p:
            browser = p.chromium.launch(executable_path=CHROMIUM, args=["--headless", "--no-sandbox"])
            page = browser.new_page(viewport={"width": 1280, "height": 900})
            page.goto(url)
            page.wait_for_function("!document.getElementById('good').disabled", timeout=120_000)
            for i in range(8):
                time.sleep(rng.uniform(1.0, 2.5))
                page.keyboard.press("/" if i % 2 == 0 else "z")
            page.wait_for_timeout(1000)  # the flash of the last press fades
            page.wait_for_function("S.frame && S.frame.target >= 0", timeout=60_000, polling=20)
            _shot(page, out / "browser_trainer_keepaway.png")
            page.set_viewport_size({"width": 390, "height": 844})
            page.wait_for_timeout(300)
            _shot(page, out / "browser_trainer_phone.png")
            browser.close()
        proc.send_signal(signal.SIGINT)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    rng = random.Random(0)
    with tempfile.TemporaryDirectory() as work:
        tetris(args.out, Path(work), rng)
        keepaway(args.out, Path(work), rng)


if __name__ == "__main__":
    main()
