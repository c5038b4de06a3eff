"""StudyConfig: the pilot config is valid, and each bad value fails with one line naming it and what is
allowed."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from hydra import compose, initialize_config_dir

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment.cli import CONF_DIR, compose_train
from hfrl_torch.study.config import StudyConfig


def _set(raw: dict[str, Any], path: str, value: Any) -> None:
    node: Any = raw
    keys = path.split(".")
    for key in keys[:-1]:
        node = node[int(key)] if isinstance(node, list) else node[key]
    last = keys[-1]
    if isinstance(node, list):
        node[int(last)] = value
    else:
        node[last] = value


BAD = [
    ("name", "has space", "study.name='has space' is invalid"),
    ("name", "", "study.name='' is invalid"),
    ("title", "", "study.title='' is invalid: must be a non-empty string"),
    ("consent", None, "study.consent=None is invalid"),
    ("seed", -1, "study.seed=-1 is invalid: must be an integer in 0..2147483647"),
    ("seed", True, "study.seed=True is invalid"),
    ("port", 70000, "study.port=70000 is invalid: must be an integer in 0..65535"),
    ("host", "", "study.host='' is invalid"),
    ("allowed_hosts", "lab.example.org", "study.allowed_hosts='lab.example.org' is invalid: must be a list"),
    ("researcher_token", "short", "study.researcher_token is invalid: must be null (generated) or 16+"),
    ("enrollment", "invite", "study.enrollment='invite' is invalid; allowed: open, codes"),
    ("codes", 0, "study.codes=0 is invalid: must be an integer in 1..10000"),
    ("max_participants", 0, "study.max_participants=0 is invalid: must be an integer in 1..10000"),
    ("practice_s", 1, "study.practice_s=1 is invalid: must be a number in 5.0..600.0"),
    ("practice_s", float("nan"), "study.practice_s=nan is invalid"),
    ("calibration.trials", 51, "study.calibration.trials=51 is invalid: must be an integer in 0..50"),
    ("calibration.optional", "yes", "study.calibration.optional='yes' is invalid: must be true or false"),
    ("calibration", [1], "study.calibration=[1] is invalid"),
    ("questionnaire", {"a": 1}, "study.questionnaire={'a': 1} is invalid: must be a list of items"),
    (
        "questionnaire.0.kind",
        "slider",
        "study.questionnaire[0].kind='slider' is invalid; allowed: likert, text",
    ),
    ("questionnaire.0.points", 1, "study.questionnaire[0].points=1 is invalid: must be an integer in 2..11"),
    ("questionnaire.0.points", 12, "study.questionnaire[0].points=12 is invalid"),
    ("questionnaire.0.text", "", "study.questionnaire[0].text='' is invalid"),
    ("questionnaire.0.id", "a b", "study.questionnaire[0].id='a b' is invalid"),
    ("questionnaire.1.id", "effort", "study.questionnaire id 'effort' is used twice"),
    (
        "questionnaire.1.max_chars",
        0,
        "study.questionnaire[1].max_chars=0 is invalid: must be an integer in 1..10000",
    ),
    ("conditions", [], "study.conditions=[] is invalid: must be a non-empty list"),
    ("conditions.1.label", "tetris_a", "study.conditions label 'tetris_a' is used twice"),
    ("conditions.0.label", "", "study.conditions[0].label='' is invalid"),
    ("conditions.0.overrides", "domain=tetris", "study.conditions[0].overrides='domain=tetris' is invalid"),
    (
        "conditions.0.overrides",
        ["domain"],
        "study.conditions[0].overrides item 'domain' is invalid: must be key=value",
    ),
    ("conditions.0.overrides", ["seed=3"], "the study sets seed for each participant"),
    ("conditions.0.overrides", ["trainer.port=1"], "the study sets trainer.port"),
    ("common", ["trainer.blind=false"], "the study sets trainer.blind"),
    ("conditions.0.overrides", ["trainer=oracle"], "the study sets trainer for each participant"),
    ("conditions.0.overrides", ["hydra.run.dir=x"], "the study sets hydra.run.dir"),
    ("common", ["trainer.reaction_s=0.5"], "study.common item 'trainer.reaction_s=0.5' is invalid"),
    ("design", "random", "study.design='random' is invalid; allowed: blocked"),
]


@pytest.mark.parametrize(("path", "value", "message"), BAD, ids=[f"{p}={v!r}" for p, v, _ in BAD])
def test_bad_value_one_line(raw: dict[str, Any], path: str, value: Any, message: str) -> None:
    _set(raw, path, value)
    with pytest.raises(ConfigError) as info:
        StudyConfig.from_node(raw)
    text = str(info.value)
    assert "\n" not in text
    assert message in text


def test_codes_at_most_places(raw: dict[str, Any]) -> None:
    raw.update(enrollment="codes", codes=9, max_participants=8)
    with pytest.raises(ConfigError, match=r"study.codes=9 is invalid with enrollment=codes: must be at most"):
        StudyConfig.from_node(raw)
    raw["codes"] = 8
    assert StudyConfig.from_node(raw).codes == 8


def test_valid_round_trip(raw: dict[str, Any]) -> None:
    cfg = StudyConfig.from_node(raw)
    assert cfg.labels() == ["tetris_a", "keepaway_b"]
    assert cfg.difference(cfg.to_dict()) is None
    public = cfg.public()
    assert "conditions" not in public and "tetris_a" not in str(public)
    assert public["questionnaire"][1] == {
        "id": "comments",
        "kind": "text",
        "text": "Anything else?",
        "max_chars": 20,
    }


def test_difference_names_field(raw: dict[str, Any]) -> None:
    saved = StudyConfig.from_node(raw).to_dict()
    raw["port"] = 9000  # resumable
    raw["max_participants"] = 30
    assert StudyConfig.from_node(raw).difference(saved) is None
    raw["conditions"][0]["overrides"] = ["domain=tetris", "agent.iterations=3"]
    assert StudyConfig.from_node(raw).difference(saved).startswith("conditions: saved")


def test_pilot_composes() -> None:
    """conf/study.yaml + pilot.yaml: valid, four conditions mixing Tetris and keepaway, each of which train.py
    accepts with what the study adds (a calibrated reaction allowance and gamma fit included)."""
    with initialize_config_dir(str(Path(CONF_DIR)), version_base=None):
        node = compose("study", overrides=["study.port=0"], return_hydra_config=True)
    assert node.hydra.run.dir == "studies/pilot" and node.hydra.output_subdir is None
    cfg = StudyConfig.from_node(node.study)
    assert len(cfg.conditions) == 4 and cfg.dir == "studies/pilot"
    domains = set()
    for condition in cfg.conditions:
        train = compose_train(
            *condition.overrides,
            *cfg.common,
            "trainer=interactive",
            "trainer.port=0",
            "trainer.token=abcdefgh12345",
            "seed=1",
            "trainer.reaction_s=0.42",
            "human.gamma_shape=2.5",
            "human.gamma_scale=0.2",
        )
        domains.add(train.domain.name)
        assert train.trainer.name == "interactive" and train.trainer.reaction_s == 0.42
    assert domains == {"tetris", "keepaway"}
