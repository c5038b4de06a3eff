"""The compiled cycle takes its constants from the torch modules that name them: a skill constant
changed there, before the compiled code is compiled, moves the torch path and the compiled path
alike. The compiled modules import the constants when they are imported (with the keepaway package),
numba freezes them when it compiles, and its disk cache would hand back code compiled with the old
value; so each run is a fresh process with its own empty numba cache, and the changed run imports
the compiled skills module again after the change, before anything is compiled."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

# Prints BlockPass's point on both paths for one scene, with skills.MARK_DISTANCE set to argv[1]
# (if given) before the compiled skills module imports it (again).
SCRIPT = r"""
import importlib
import json
import sys

import torch

from hfrl_torch.envs.keepaway import skills
from hfrl_torch.envs.keepaway.compiled import skills as compiled_skills
from hfrl_torch.envs.keepaway.compiled.glue import task_arrays
from hfrl_torch.envs.keepaway.params import TASKS, KeepawayConfig

if len(sys.argv) > 1:
    skills.MARK_DISTANCE = float(sys.argv[1])
    compiled_skills = importlib.reload(compiled_skills)

keepers = torch.tensor([[[-8.0, -8.0], [8.0, -8.0], [8.0, 8.0]]])
takers = torch.tensor([[[6.0, -6.0], [7.0, -5.0], [-3.0, -1.0]]])
ball = keepers[:, 0] + 0.5
with_ball = torch.tensor([0])
torch_point = skills.block_pass_target(keepers, takers, with_ball, ball)[0]
_, ip, _, _ = task_arrays(KeepawayConfig(takers=3, **TASKS["exact"]))
view = torch.cat((ball[:, None], keepers, takers), 1)[0].double().numpy()
compiled_point = compiled_skills._block_point(view, 0, ip)
print(json.dumps({"torch": torch_point.tolist(), "compiled": [float(v) for v in compiled_point]}))
"""


def block_points(tmp_path: Path, mark_distance: float | None) -> dict[str, list[float]]:
    """BlockPass's point on both paths in a fresh process, with ``skills.MARK_DISTANCE`` patched."""
    cache = tmp_path / f"numba-{mark_distance}"
    cache.mkdir()
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache), "PYTHONPATH": str(Path(__file__).parents[3])}
    args = [] if mark_distance is None else [str(mark_distance)]
    out = subprocess.run(
        [sys.executable, "-c", SCRIPT, *args], env=env, capture_output=True, text=True, timeout=300
    )
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.splitlines()[-1])


def test_a_skill_constant_changed_in_skills_py_moves_both_paths(tmp_path: Path) -> None:
    """BlockPass marks the most open keeper (keeper 2 here, 22 m from the ball) MARK_DISTANCE towards
    the ball: 4 m as shipped, 6 m with skills.MARK_DISTANCE = 6 on both paths."""
    keeper = (8.0, 8.0)
    for mark, points in ((4.0, block_points(tmp_path, None)), (6.0, block_points(tmp_path, 6.0))):
        for path in ("torch", "compiled"):
            x, y = points[path]
            assert (x - keeper[0]) ** 2 + (y - keeper[1]) ** 2 == pytest.approx(mark**2, rel=1e-5), path
        assert points["torch"] == pytest.approx(points["compiled"], abs=1e-5)
