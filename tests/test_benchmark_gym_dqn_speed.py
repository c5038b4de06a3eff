"""``benchmarks/gym_dqn_speed.py`` on a tiny budget: it runs both sides with the same settings and prints one
JSON object. Its speed is not asserted (that is what the benchmark measures, on a quiet machine)."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path

import pytest

SCRIPT = Path(__file__).resolve().parent.parent / "benchmarks" / "gym_dqn_speed.py"
TINY = ["agent.frames=128", "agent.eval_every=64", "agent.learn_after=64", "agent.eval_episodes=2"]


def test_the_benchmark_prints_both_sides_as_json(monkeypatch, capsys, one_thread) -> None:
    spec = importlib.util.spec_from_file_location("gym_dqn_speed", SCRIPT)
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    monkeypatch.setattr(sys, "argv", [str(SCRIPT), "--repeats", "1", "--no-warmup", "--set", *TINY])
    script.main()
    out = json.loads(capsys.readouterr().out)  # stdout is the one JSON object, progress went to stderr
    assert out["benchmark"] == "gym_dqn_speed" and out["settings"]["frames"] == 128
    assert out["settings"]["boards"] == 8 and out["settings"]["buffer_size"] == 20000  # the gym defaults
    for side in ("project", "torchrl"):
        (run,) = out["runs"][side]
        assert run["frames"] == 128 and run["updates"] == 12  # 4 updates a batch once 64 frames are in
        assert len(run["greedy_returns"]) == 3  # at frames 0, 64 and 128
        assert 0 < run["eval_wall_s"] < run["wall_s"] and run["train_frames_per_s"] > run["frames_per_s"] > 0
    for measure, ratio in out["ratios"].items():
        project, torchrl = out["medians"]["project"][measure], out["medians"]["torchrl"][measure]
        assert ratio["of_medians"] == pytest.approx(project / torchrl, abs=1e-3)
        assert out["meets_target"][measure] == (ratio["of_medians"] >= 0.67)
    assert set(out["threads"].values()) == {1}
