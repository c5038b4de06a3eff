"""The study directory's files: atomic writes survive a crash between the temporary file and the rename,
events are appended whole, and the run file names match the ones train.py writes."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import textwrap
from pathlib import Path

from hfrl_torch.common.checkpoint import LAST
from hfrl_torch.interactive.journal import JOURNAL_NAME
from hfrl_torch.interactive.live import SUMMARY_NAME
from hfrl_torch.study import layout


def test_names_match_the_run() -> None:
    assert Path(layout.CHECKPOINT).name == LAST
    assert layout.PRESSES == JOURNAL_NAME
    assert layout.TEACHING_SUMMARY == SUMMARY_NAME


def test_layout_imports_nothing_heavy() -> None:
    heavy = "('torch', 'aiohttp', 'omegaconf')"
    code = f"import sys, hfrl_torch.study.layout; print(sorted(m for m in {heavy} if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


def test_write_json_round_trip(tmp_path: Path) -> None:
    path = tmp_path / "p.json"
    layout.write_json(path, {"a": 1})
    layout.write_json(path, {"a": 2, "b": [1, 2]})
    assert layout.read_json(path) == {"a": 2, "b": [1, 2]}
    assert [p.name for p in tmp_path.iterdir()] == ["p.json"]


def test_crash_before_replace_keeps_old_file(tmp_path: Path) -> None:
    """A process killed after writing the temporary file and before os.replace leaves the old record."""
    path = tmp_path / "participant.json"
    layout.write_json(path, {"step": "consent"})
    script = textwrap.dedent(
        f"""
        import os
        from hfrl_torch.study import layout
        def crash(src, dst):
            os._exit(9)
        os.replace = crash
        layout.write_json({str(path)!r}, {{"step": "instructions"}})
        """
    )
    env = {**os.environ, "PYTHONPATH": str(Path(layout.__file__).resolve().parents[2])}
    result = subprocess.run([sys.executable, "-c", script], env=env, check=False)
    assert result.returncode == 9
    assert layout.read_json(path) == {"step": "consent"}
    layout.write_json(path, {"step": "practice"})  # the leftover temporary file does not get in the way
    assert layout.read_json(path) == {"step": "practice"}


def test_secret_is_private(tmp_path: Path) -> None:
    path = tmp_path / layout.RESEARCHER_TOKEN
    layout.write_secret(path, "x\n")
    assert stat.S_IMODE(path.stat().st_mode) == 0o600


def test_events_appended_and_torn_line_skipped(tmp_path: Path) -> None:
    layout.append_event(tmp_path, "created", participants=0)
    layout.append_event(tmp_path, "step", code="ABC", step="practice")
    with open(tmp_path / layout.EVENTS, "a") as f:
        f.write('{"event": "st')  # a line cut short by a crash
    events = layout.read_events(tmp_path)
    assert [e["event"] for e in events] == ["created", "step"]
    assert events[1]["code"] == "ABC" and isinstance(events[1]["t"], float)
    layout.append_event(tmp_path, "closed")
    lines = (tmp_path / layout.EVENTS).read_text().splitlines()
    assert json.loads(lines[0])["event"] == "created" and len(lines) == 3


def test_read_participants_in_order(tmp_path: Path) -> None:
    assert not layout.is_study(tmp_path)
    layout.write_json(tmp_path / layout.STUDY_JSON, {"name": "t"})
    for code, index in (("BBBBBBBBBBBB", 1), ("AAAAAAAAAAAA", 0), ("CCCCCCCCCCCC", 2)):
        layout.participant_dir(tmp_path, code).mkdir(parents=True)
        layout.write_json(
            layout.participant_json(tmp_path, code),
            {"code": code, "index": index, "run_dir": layout.relative_run_dir(code)},
        )
    records = layout.read_participants(tmp_path)
    assert layout.is_study(tmp_path) and layout.read_study(tmp_path) == {"name": "t"}
    assert [r["index"] for r in records] == [0, 1, 2]
    assert records[0]["run_path"] == str(tmp_path / "participants" / "AAAAAAAAAAAA" / "run")
