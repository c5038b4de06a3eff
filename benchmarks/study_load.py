"""Many participants at once: a real ``study.py`` on this machine, scripted participants, every press checked.

Starts ``study.py`` on a study made for the benchmark (``study=pilot`` with its name, directory, port,
participants, practice, common overrides and conditions replaced on the command line: Tetris CE and
keepaway Sarsa, each with linear fusion and with human only, short budgets), then sends ``--participants``
scripted participants into it at once (joins spread over ``--spread`` seconds): ``--chromium`` of them
in headless Chromium (Playwright, with tests/interactive/chromium.py's path and flags), the rest
through ``hfrl_torch.study.client`` (aiohttp: the study's HTTP API and the teaching WebSocket through the
study's proxy). Each presses Good or Bad at a person's pace (one press every 0.7-1.5 s while something
is on screen to judge) for ``--seconds`` of teaching, then Finish and save, then the questionnaire.

When all have finished (or ``--timeout`` passed), every acknowledged press is compared with the
participant's press journal and feedback log (``client.check_presses``). Prints ONE JSON object:

* ``participants``, ``finished`` (reached ``done``), ``acked``, ``logged`` (presses in the feedback logs),
  ``lost`` (acknowledged, not logged exactly once), ``duplicated``; ``ack_ms_p50``/``ack_ms_p99`` (send
  to acknowledgement, on the client's clock, through the study's proxy, in milliseconds);
* ``frame_late_share``: steady frame gaps longer than 1.5x the period the run announces (Tetris: one
  placement, ``1/actions_per_s``; keepaway: one 100 ms cycle at real time), over all steady gaps (the
  definition is in ``hfrl_torch/study/client.py``); Chromium's frames are timed in the page;
* ``wall_s``, ``cores``, the load average before and after, ``threads`` (each worker runs with
  ``threads=1``: with 20 runs on a few cores more threads per run only oversubscribe them; this process
  sets torch's to 1), and per-participant rows.

Progress goes to stderr. Not run in CI (minutes, and it loads the machine)::

    python benchmarks/study_load.py --participants 4
    python benchmarks/study_load.py --participants 20 --chromium 2 --seconds 60
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import random
import re
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import aiohttp
import torch
from playwright.async_api import Error as PlaywrightError
from playwright.async_api import async_playwright

from hfrl_torch.study import layout
from hfrl_torch.study.client import (
    GAMMA_SCALE,
    GAMMA_SHAPE,
    LATE_FACTOR,
    PRESS_GAP_S,
    STEPS_BEFORE_TEACHING,
    Participant,
    PressRecord,
    TeachRecord,
    check_presses,
    percentile,
)

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "interactive"))
from chromium import ARGS as CHROMIUM_ARGS  # noqa: E402
from chromium import CHROMIUM  # noqa: E402

URL = re.compile(r"https?://127\.0\.0\.1:(\d+)/")
TETRIS = ["domain=tetris", "agent=cem", "agent.iterations=4", "agent.population=10"]
TETRIS += ["agent.games_per_candidate=1", "agent.eval_games=2", "agent.watch_pieces=40"]
KEEPAWAY = ["domain=keepaway", "agent=sarsa", "agent.hours=0.02", "agent.table_bits=12"]
KEEPAWAY += ["agent.log_episodes=2"]  # a point of the curve every 2 episodes: a short session still has some
CONDITIONS = {
    "tetris_linear": [*TETRIS, "fusion=linear"],
    "keepaway_linear": [*KEEPAWAY, "fusion=linear"],
    "tetris_human_only": [*TETRIS, "fusion=human_only"],
    "keepaway_human_only": [*KEEPAWAY, "fusion=human_only"],
}
COMMON = ["trainer.wait_for_page_s=300", "threads=1", "logger.backend=none"]
# the page's side in Chromium: the teaching socket's presses, answers and frames, timed in the page
RECORD = """
window.__rec = { sent: {}, acks: [], errors: [], frames: [], settings: [] };
const PageSocket = window.WebSocket;
window.WebSocket = class extends PageSocket {
  constructor(...args) {
    super(...args);
    const send = this.send.bind(this);
    this.send = (data) => {
      try {
        const m = JSON.parse(data);
        if (m.type === "feedback") window.__rec.sent[m.id] = performance.now();
      } catch (e) {}
      send(data);
    };
    this.addEventListener("message", (e) => {
      const m = JSON.parse(e.data), t = performance.now();
      if (m.type === "ack" && m.message === "feedback") window.__rec.acks.push({ t, ...m });
      else if (m.type === "error" && m.id !== undefined && m.id >= 0) window.__rec.errors.push({ t, ...m });
      else if (m.type === "tetris" || m.type === "keepaway")
        window.__rec.frames.push({ t, type: m.type, phase: m.phase, game: m.game, episode: m.episode,
                                   real_time: m.real_time });
      else if (m.type === "settings" || m.type === "status" || m.type === "role")
        window.__rec.settings.push({ t, type: m.type, actions_per_s: m.actions_per_s, paused: m.paused,
                                     here: m.here, live: m.live, ending: m.ending, role: m.role });
    });
  }
};
"""


def say(text: str) -> None:
    """One progress line on stderr."""
    print(f"[{time.strftime('%H:%M:%S')}] {text}", file=sys.stderr, flush=True)


def study_command(
    directory: Path, participants: int, python: str, conditions: dict[str, list[str]]
) -> list[str]:
    """``study.py`` with the benchmark's study: the pilot's texts and questionnaire, its own conditions."""
    conditions = ",".join(
        "{label:" + label + ",overrides:[" + ",".join(f"'{o}'" for o in overrides) + "]}"
        for label, overrides in conditions.items()
    )
    return [
        python,
        str(ROOT / "study.py"),
        "study=pilot",
        "study.name=bench",
        f"study.dir={directory}",
        "study.port=0",
        f"study.max_participants={participants}",
        "study.practice_s=5",
        "study.common=[" + ",".join(f"'{o}'" for o in COMMON) + "]",
        f"study.conditions=[{conditions}]",
    ]


def start_study(command: list[str], log: Path, timeout: float = 120.0) -> tuple[subprocess.Popen, str]:
    """Start the study in its own process group (a kill reaches its workers too); its address once it
    prints it."""
    out = log.open("w")
    proc = subprocess.Popen(
        command, cwd=ROOT, stdout=out, stderr=subprocess.STDOUT, text=True, start_new_session=True
    )
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for line in log.read_text().splitlines():
            m = URL.search(line)
            if m and "admin" not in line:
                return proc, f"http://127.0.0.1:{m.group(1)}"
        if proc.poll() is not None:
            break
        time.sleep(0.2)
    stop_study(proc)
    raise SystemExit(f"study.py did not print its address:\n{log.read_text()[-3000:]}")


def stop_study(proc: subprocess.Popen, timeout: float = 60.0) -> int | None:
    """SIGTERM to the study (it stops its workers), SIGKILL to its group after ``timeout``."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGTERM)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    return proc.returncode


def late_share_of_page(rec: dict[str, Any]) -> tuple[int, int]:
    """Steady and late frame gaps of a Chromium page's record, by the client's rule."""
    events = sorted(
        [(e["t"], "frame", e) for e in rec["frames"]] + [(e["t"], "state", e) for e in rec["settings"]],
        key=lambda x: x[0],
    )
    state: dict[str, Any] = {}
    last: tuple[float, Any] | None = None
    steady = late = 0
    for t, kind, e in events:
        if kind == "state":
            if e["type"] == "settings":
                keys = ("actions_per_s", "paused", "here", "live", "ending")
                if any(e.get(k) != state.get(k) for k in keys):
                    last = None
                state.update({k: e.get(k) for k in keys})
            elif e["type"] == "role":
                state["role"] = e.get("role")
                last = None
            else:
                last = None
            continue
        speed = float(state.get("actions_per_s") or 0)
        ok = (
            state.get("role") == "teach"
            and state.get("live")
            and not state.get("paused")
            and state.get("here", True)
            and state.get("ending") is None
            and e.get("phase", "watch") == "watch"
            and speed > 0
        )
        if e["type"] == "tetris":
            unit, period = e.get("game"), 1000.0 / speed if speed else 0
        else:
            unit = e.get("episode")
            period = 100.0 * float(e.get("real_time") or 0) / speed if speed else 0
        if ok and period > 0 and last is not None and last[1] == unit:
            steady += 1
            late += (t - last[0]) / period > LATE_FACTOR
        last = (t, unit) if ok and period > 0 else None
    return steady, late


async def _settled(scripted: Participant, client: aiohttp.ClientSession, step: str) -> dict[str, Any]:
    """The participant's state once it has left ``step`` (or after 10 s)."""
    state = await scripted._state(client)
    for _ in range(50):
        if state["step"] != step:
            break
        await asyncio.sleep(0.2)
        state = await scripted._state(client)
    return state


async def _calibrate(page: Any, rng: random.Random, trials: int) -> None:
    """The page's reaction-time test: Space to start each trial, Space again a drawn delay after the
    circle shows (the client's gamma(2, 0.28), at least 0.15 s: sooner counts as pressing too soon)."""
    for _ in range(trials):
        await page.focus("#target-box")
        await page.keyboard.press("Space")
        await page.wait_for_selector("#target:not([hidden])", timeout=15_000)
        await asyncio.sleep(max(rng.gammavariate(GAMMA_SHAPE, GAMMA_SCALE), 0.15))
        await page.keyboard.press("Space")


async def _answer(page: Any, rng: random.Random) -> None:
    """The questionnaire's form: a drawn point of every Likert item, a sentence in the text box."""
    for box in await page.query_selector_all("#answers fieldset[data-kind=likert]"):
        inputs = await box.query_selector_all("input")
        await inputs[rng.randrange(len(inputs))].check()
    for text in await page.query_selector_all("#answers textarea"):
        await text.fill("scripted participant in Chromium")
    await page.click("#answers button[type=submit]")
    await page.wait_for_selector("#done:not([hidden])", timeout=30_000)


async def chromium_participant(
    base: str, seed: int, seconds: float, browser: Any, client: aiohttp.ClientSession
) -> dict[str, Any]:
    """A participant in Chromium: joins through the API (simulated), then goes through the study's pages
    by clicking and pressing keys, as a person would: consent, instructions, practice, the reaction-time
    test, the teaching page (keys at a person's pace, Finish and save, Continue) and the questionnaire. A
    step the page could not be driven through is done through the API and named in ``api_steps``."""
    rng = random.Random(seed)
    scripted = Participant(base, seed)
    row: dict[str, Any] = {"kind": "chromium", "api_steps": [], "ui_steps": []}
    scripted.record.code = row["code"] = await scripted._join(client)
    context = await browser.new_context(viewport={"width": 1280, "height": 900})
    await context.add_init_script(RECORD)
    page = await context.new_page()
    page.on("dialog", lambda d: asyncio.ensure_future(d.accept()))
    rec = None
    try:
        await page.goto(f"{base}/p/{scripted.record.code}/")
        state = await scripted._state(client)
        clicks = {"consent": "#agree", "instructions": "#instructions-next", "practice": "#practice-next"}
        while state["step"] in STEPS_BEFORE_TEACHING:
            step = state["step"]
            try:
                if step == "calibration":
                    await _calibrate(page, rng, int(state["study"]["calibration"]["trials"]))
                else:
                    wait_s = float(state["study"]["practice_s"]) + 15
                    await page.click(clicks[step], timeout=wait_s * 1000)
                state = await _settled(scripted, client, step)
                if state["step"] == step:
                    raise PlaywrightError(f"the page did not leave {step}")
                row["ui_steps"].append(step)
            except PlaywrightError:
                row["api_steps"].append(step)
                data = {"delays_s": scripted._delays(8)} if step == "calibration" else None
                state = await scripted._step(client, step, "agree" if step == "consent" else "next", data)
        try:
            await page.click("#teach-link", timeout=30_000)
            await page.wait_for_url(re.compile(r"/teach/$"))
            row["ui_steps"].append("teach-link")
        except PlaywrightError:
            row["api_steps"].append("teach-link")
            await page.goto(f"{base}/p/{scripted.record.code}/teach/")
        await page.wait_for_function("!document.getElementById('good').disabled", timeout=300_000)
        started = time.monotonic()
        while time.monotonic() - started < seconds:
            await asyncio.sleep(rng.uniform(*PRESS_GAP_S))
            if await page.evaluate("!document.getElementById('good').disabled"):
                await page.keyboard.press("/" if rng.random() < 0.7 else "z")
            elif await page.evaluate("document.getElementById('finish').disabled"):
                break  # the run ended by itself
        if not await page.evaluate("document.getElementById('finish').disabled"):
            await page.click("#finish")
        await page.wait_for_selector("#summary:not([hidden])", timeout=120_000)
        rec = await page.evaluate("window.__rec")
        try:
            await page.click("#summary-continue a", timeout=10_000)
            await page.wait_for_selector("#questionnaire:not([hidden])", timeout=60_000)
            await _answer(page, rng)
            row["ui_steps"].append("questionnaire")
        except PlaywrightError:
            row["api_steps"].append("questionnaire")
            state = await scripted._until(client, lambda s: s["step"] != "teaching", "the run did not end")
            if state["step"] == "questionnaire":
                answers = scripted._answers(state["study"]["questionnaire"])
                await scripted._step(client, "questionnaire", "next", {"answers": answers})
        row["step"] = (await scripted._state(client))["step"]
    except Exception as e:  # the row says how far it got
        row["error"] = f"{type(e).__name__}: {e}"
        if rec is None and not page.is_closed():
            with contextlib.suppress(PlaywrightError):
                rec = await page.evaluate("window.__rec")
    finally:
        await context.close()
    presses = []
    if rec:
        for a in rec["acks"]:
            sent = rec["sent"].get(str(a["id"]))
            if sent is not None:  # on the page's clock: matched to the journal by order and content only
                presses.append(PressRecord(a["id"], a["value"], sent / 1000, 0.0, a["t"] / 1000, 0.0, ack=a))
        row["steady_gaps"], row["late_gaps"] = late_share_of_page(rec)
        row["errors"] = [e["message"] for e in rec["errors"]]
    row["presses"] = presses
    return row


async def ws_participant(
    base: str, seed: int, seconds: float, client: aiohttp.ClientSession
) -> dict[str, Any]:
    """A participant through ``hfrl_torch.study.client``."""
    p = Participant(base, seed, presses=None, seconds=seconds, wait_s=600)
    record = await p.run(client)
    teach = record.teaching or TeachRecord()
    return {
        "kind": "websocket",
        "code": record.code,
        "step": record.steps[-1] if record.steps else None,
        "error": record.error,
        "presses": teach.presses,
        "steady_gaps": teach.steady_gaps,
        "late_gaps": teach.late_gaps,
        "worst_gap_ratio": round(teach.worst_gap_ratio, 2),
        "connections": teach.connections,
        "errors": [p.error for p in teach.presses if p.error] + teach.errors,
    }


async def crowd(base: str, args: argparse.Namespace) -> list[dict[str, Any]]:
    """All participants at once, their joins spread over ``--spread`` seconds."""
    rng = random.Random(args.seed)
    offsets = sorted(rng.uniform(0, args.spread) for _ in range(args.participants))
    browser = playwright = None
    if args.chromium:
        playwright = await async_playwright().start()
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
    timeout = aiohttp.ClientTimeout(total=None, sock_connect=30, sock_read=None)
    async with aiohttp.ClientSession(timeout=timeout) as client:

        async def one(i: int) -> dict[str, Any]:
            await asyncio.sleep(offsets[i])
            seed = args.seed * 1000 + i
            if i < args.chromium:
                row = await chromium_participant(base, seed, args.seconds, browser, client)
            else:
                row = await ws_participant(base, seed, args.seconds, client)
            acked = sum(p.ack is not None for p in row["presses"])
            say(
                f"participant {i} ({row['kind']}, {row.get('code')}): {row.get('step')}, "
                f"{acked} presses acked"
            )
            return row

        try:
            return await asyncio.wait_for(
                asyncio.gather(*(one(i) for i in range(args.participants))), args.timeout
            )
        finally:
            if browser is not None:
                await browser.close()
            if playwright is not None:
                await playwright.stop()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--participants", type=int, default=20)
    parser.add_argument("--chromium", type=int, default=2, help="of them driven by Chromium (Playwright)")
    parser.add_argument("--seconds", type=float, default=60.0, help="teaching time of each, then Finish")
    parser.add_argument("--spread", type=float, default=10.0, help="joins spread over this many seconds")
    parser.add_argument("--timeout", type=float, default=1200.0, help="give up on the crowd after this")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--domains", default="tetris,keepaway", help="the conditions' domains, comma-separated (default both)"
    )
    parser.add_argument("--study-dir", type=Path, default=None, help="default: a new temporary directory")
    parser.add_argument("--keep", action="store_true", help="keep the study directory (printed)")
    args = parser.parse_args()
    if not 0 <= args.chromium <= args.participants:
        raise SystemExit(f"--chromium={args.chromium} is invalid: must be in 0..--participants")
    if args.chromium and not Path(CHROMIUM).exists():
        raise SystemExit(f"--chromium={args.chromium} needs Chromium at {CHROMIUM}; pass --chromium 0")
    domains = args.domains.split(",")
    conditions = {k: v for k, v in CONDITIONS.items() if k.split("_")[0] in domains}
    if not conditions or not set(domains) <= {"tetris", "keepaway"}:
        raise SystemExit(f"--domains={args.domains} is invalid: allowed tetris, keepaway or both")
    torch.set_num_threads(1)
    directory = args.study_dir or Path(tempfile.mkdtemp(prefix="study_load_")) / "bench"
    load_before = os.getloadavg()
    started = time.perf_counter()
    proc, base = start_study(
        study_command(directory, args.participants, sys.executable, conditions),
        directory.parent / "study.log",
    )
    say(f"study.py serves {base} from {directory}")
    try:
        rows = asyncio.run(crowd(base, args))
        timed_out = False
    except TimeoutError:
        rows, timed_out = [], True
    crowd_s = time.perf_counter() - started
    load_after = os.getloadavg()
    code = stop_study(proc)
    say(f"study.py stopped ({code})")
    acked = logged = lost = duplicated = steady = late = 0
    ack_ms: list[float] = []
    by_condition: dict[str, dict[str, Any]] = {}
    for row in rows:
        presses: list[PressRecord] = row.pop("presses")
        ms = [p.ack_ms for p in presses if p.ack_ms is not None]
        ack_ms += ms
        if row.get("code") and layout.participant_json(directory, row["code"]).exists():
            row["condition"] = layout.read_json(layout.participant_json(directory, row["code"]))["condition"]
            group = by_condition.setdefault(
                row["condition"], {"participants": 0, "ms": [], "steady": 0, "late": 0}
            )
            group["participants"] += 1
            group["ms"] += ms
            group["steady"] += row.get("steady_gaps", 0)
            group["late"] += row.get("late_gaps", 0)
        row["ack_ms_p99"] = None if not ms else round(percentile(ms, 99) or 0, 1)
        steady += row.get("steady_gaps", 0)
        late += row.get("late_gaps", 0)
        if row.get("code"):
            # the page's clock is not the journal's: a Chromium press is matched by order and content only
            check = check_presses(
                layout.run_dir(directory, row["code"]),
                _wide(presses) if row["kind"] == "chromium" else presses,
            )
            row["check"] = check
            acked += check["acked"]
            logged += check["logged"]
            lost += check["lost"]
            duplicated += check["duplicated"]
    out = {
        "command": " ".join(sys.argv),
        "participants": args.participants,
        "chromium": args.chromium,
        "finished": sum(r.get("step") == "done" for r in rows),
        "acked": acked,
        "logged": logged,
        "lost": lost,
        "duplicated": duplicated,
        "ack_ms_p50": None if not ack_ms else round(percentile(ack_ms, 50) or 0, 1),
        "ack_ms_p99": None if not ack_ms else round(percentile(ack_ms, 99) or 0, 1),
        "ack_ms_max": None if not ack_ms else round(max(ack_ms), 1),
        "frame_late_share": None if not steady else round(late / steady, 4),
        "frame_gaps_steady": steady,
        "frame_gaps_late": late,
        "late_rule": f"a steady frame gap over {LATE_FACTOR}x the run's announced period",
        "seconds_teaching": args.seconds,
        "timed_out": timed_out,
        "wall_s": round(crowd_s, 1),
        "cores": os.cpu_count(),
        "load_before": [round(x, 2) for x in load_before],
        "load_after": [round(x, 2) for x in load_after],
        "by_condition": {
            label: {
                "participants": g["participants"],
                "ack_ms_p50": None if not g["ms"] else round(percentile(g["ms"], 50) or 0, 1),
                "ack_ms_p99": None if not g["ms"] else round(percentile(g["ms"], 99) or 0, 1),
                "frame_late_share": None if not g["steady"] else round(g["late"] / g["steady"], 4),
            }
            for label, g in sorted(by_condition.items())
        },
        "threads": {
            "worker": 1,
            "benchmark_torch": 1,
            "why": "each train.py worker runs with threads=1: with many runs on few cores, more threads per "
            "run only oversubscribe the cores",
        },
        "conditions": conditions,
        "study_exit": code,
        "rows": rows,
        "study_dir": str(directory) if args.keep else None,
    }
    if not args.keep and args.study_dir is None:
        shutil.rmtree(directory.parent, ignore_errors=True)
    print(json.dumps(out, indent=1))


def _wide(presses: list[PressRecord]) -> list[PressRecord]:
    """Presses timed on another clock: any journal time matches (the order and content still must)."""
    return [
        PressRecord(p.id, p.value, p.sent, 0.0, p.answered, float("inf"), ack=p.ack, error=p.error)
        for p in presses
    ]


if __name__ == "__main__":
    main()
