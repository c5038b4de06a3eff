"""The study's config (``conf/study/<name>.yaml``) as a checked dataclass: one-line errors naming the bad
value and what is allowed."""

from __future__ import annotations

import math
import re
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from omegaconf import DictConfig, ListConfig, OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.study.calibration import MAX_TRIALS
from hfrl_torch.study.design import DESIGNS

ENROLLMENTS = ("open", "codes")
ITEM_KINDS = ("likert", "text")
NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}")
# train.py settings the study sets for each worker; a condition or study.common may not set them
STUDY_KEYS = (
    "trainer",
    "trainer.host",
    "trainer.port",
    "trainer.token",
    "trainer.reaction_s",
    "trainer.blind",
    "seed",
    "resume",
)
# study.json fields that may change when a study resumes (they do not change who got what)
RESUMABLE = ("dir", "host", "port", "allowed_hosts", "researcher_token", "max_participants")


@dataclass(frozen=True)
class Item:
    """One questionnaire item: a Likert scale of ``points`` from ``low`` to ``high``, or free text."""

    id: str
    kind: str
    text: str
    points: int = 7
    low: str = ""
    high: str = ""
    max_chars: int = 2000


@dataclass(frozen=True)
class Condition:
    """One between-subjects condition: its label (never shown to participants) and train.py overrides."""

    label: str
    overrides: tuple[str, ...]


@dataclass(frozen=True)
class Calibration:
    """The reaction-time calibration: ``trials`` (0 switches it off), skippable when ``optional``."""

    trials: int = 8
    optional: bool = True


@dataclass(frozen=True)
class StudyConfig:
    """A study: its texts, steps, enrolment, questionnaire and conditions (see conf/study/pilot.yaml)."""

    name: str
    dir: str
    title: str
    consent: str
    instructions: str
    conditions: tuple[Condition, ...]
    seed: int = 0
    host: str = "127.0.0.1"
    port: int = 8800
    allowed_hosts: tuple[str, ...] = ()
    researcher_token: str | None = None
    enrollment: str = "open"
    codes: int = 20
    max_participants: int = 20
    practice_s: float = 30.0
    calibration: Calibration = field(default_factory=Calibration)
    questionnaire: tuple[Item, ...] = ()
    common: tuple[str, ...] = ()
    design: str = "blocked"

    @classmethod
    def from_node(cls, node: DictConfig | Mapping[str, Any]) -> StudyConfig:
        """The checked config of the Hydra node ``study`` (or a plain mapping)."""
        if isinstance(node, (DictConfig, ListConfig)):
            node = OmegaConf.to_container(node, resolve=True)
        if not isinstance(node, Mapping):
            raise ConfigError(f"study={node!r} is invalid: must be a mapping of the study's settings")
        return _parse(dict(node))

    def labels(self) -> list[str]:
        """The conditions' labels, in config order (the design draws over them)."""
        return [c.label for c in self.conditions]

    def condition(self, label: str) -> Condition:
        """The condition called ``label``."""
        for c in self.conditions:
            if c.label == label:
                return c
        raise KeyError(label)

    def to_dict(self) -> dict[str, Any]:
        """The resolved config as plain JSON (``study.json``)."""
        out = asdict(self)
        out["conditions"] = [{"label": c.label, "overrides": list(c.overrides)} for c in self.conditions]
        out["questionnaire"] = [public_item(i) for i in self.questionnaire]
        out["allowed_hosts"] = list(self.allowed_hosts)
        out["common"] = list(self.common)
        return out

    def public(self) -> dict[str, Any]:
        """What a participant's page is told of the study (no conditions, no tokens)."""
        return {
            "title": self.title,
            "consent": self.consent,
            "instructions": self.instructions,
            "practice_s": self.practice_s,
            "calibration": {"trials": self.calibration.trials, "optional": self.calibration.optional},
            "questionnaire": [public_item(i) for i in self.questionnaire],
        }

    def difference(self, saved: Mapping[str, Any]) -> str | None:
        """The first field (outside :data:`RESUMABLE`) in which ``saved`` (a study.json) differs from this
        config, as ``field: saved ... now ...``; None when they define the same study."""
        now = self.to_dict()
        for key in sorted(set(now) | set(saved)):
            if key in RESUMABLE:
                continue
            if now.get(key) != saved.get(key):
                return f"{key}: saved {_short(saved.get(key))}, now {_short(now.get(key))}"
        return None


def public_item(item: Item) -> dict[str, Any]:
    """An item as the page gets it (only the fields of its kind)."""
    if item.kind == "likert":
        return {
            "id": item.id,
            "kind": "likert",
            "text": item.text,
            "points": item.points,
            "low": item.low,
            "high": item.high,
        }
    return {"id": item.id, "kind": "text", "text": item.text, "max_chars": item.max_chars}


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 80 else text[:77] + "..."


def _str(node: Mapping[str, Any], key: str, where: str = "study.", empty: bool = False) -> str:
    value = node.get(key)
    if not isinstance(value, str) or not (empty or value.strip()):
        raise ConfigError(f"{where}{key}={_short(value)} is invalid: must be a non-empty string")
    return value


def _name(node: Mapping[str, Any], key: str, where: str = "study.") -> str:
    value = node.get(key)
    if not isinstance(value, str) or not NAME.fullmatch(value):
        allowed = "must be a name of letters, digits, _ . -"
        raise ConfigError(f"{where}{key}={_short(value)} is invalid: {allowed}")
    return value


def _int(node: Mapping[str, Any], key: str, low: int, high: int, where: str = "study.") -> int:
    value = node.get(key)
    if not isinstance(value, int) or isinstance(value, bool) or not low <= value <= high:
        raise ConfigError(f"{where}{key}={_short(value)} is invalid: must be an integer in {low}..{high}")
    return value


def _float(node: Mapping[str, Any], key: str, low: float, high: float) -> float:
    value = node.get(key)
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or not low <= value <= high:
        raise ConfigError(f"study.{key}={_short(value)} is invalid: must be a number in {low}..{high}")
    return float(value)


def _choice(node: Mapping[str, Any], key: str, allowed: tuple[str, ...], where: str = "study.") -> str:
    value = node.get(key)
    if value not in allowed:
        raise ConfigError(f"{where}{key}={_short(value)} is invalid; allowed: {', '.join(allowed)}")
    return value


def _strings(node: Mapping[str, Any], key: str, where: str = "study.") -> tuple[str, ...]:
    value = node.get(key, [])
    if value is None:
        value = []
    if not isinstance(value, list) or not all(isinstance(v, str) and v.strip() for v in value):
        raise ConfigError(f"{where}{key}={_short(value)} is invalid: must be a list of non-empty strings")
    return tuple(value)


def _overrides(node: Mapping[str, Any], key: str, where: str) -> tuple[str, ...]:
    values = _strings(node, key, where)
    for item in values:
        name, equals, _ = item.lstrip("+~").partition("=")
        if not equals:
            raise ConfigError(
                f"{where}{key} item {item!r} is invalid: must be key=value (a train.py override)"
            )
        if name in STUDY_KEYS or name.startswith("hydra"):
            raise ConfigError(
                f"{where}{key} item {item!r} is invalid: the study sets {name} for each participant; "
                f"a condition may not set {', '.join(STUDY_KEYS)} or hydra.*"
            )
    return values


def _item(raw: Any, i: int) -> Item:
    where = f"study.questionnaire[{i}]."
    if not isinstance(raw, Mapping):
        raise ConfigError(
            f"study.questionnaire[{i}]={_short(raw)} is invalid: must be a mapping with id, kind, text"
        )
    item_id = _name(raw, "id", where)
    kind = _choice(raw, "kind", ITEM_KINDS, where)
    text = _str(raw, "text", where)
    if kind == "likert":
        points = _int(raw, "points", 2, 11, where)
        return Item(
            item_id,
            kind,
            text,
            points=points,
            low=_str(raw, "low", where, empty=True) if "low" in raw else "",
            high=_str(raw, "high", where, empty=True) if "high" in raw else "",
        )
    return Item(
        item_id,
        kind,
        text,
        max_chars=_int({"max_chars": raw.get("max_chars", 2000)}, "max_chars", 1, 10000, where),
    )


def _condition(raw: Any, i: int) -> Condition:
    where = f"study.conditions[{i}]."
    if not isinstance(raw, Mapping):
        raise ConfigError(
            f"study.conditions[{i}]={_short(raw)} is invalid: must be a mapping with label, overrides"
        )
    label = _name(raw, "label", where)
    return Condition(label, _overrides(raw, "overrides", where))


def _parse(node: dict[str, Any]) -> StudyConfig:
    name = _name(node, "name")
    token = node.get("researcher_token")
    if token is not None and (not isinstance(token, str) or len(token) < 16 or not token.isascii()):
        raise ConfigError(
            "study.researcher_token is invalid: must be null (generated) or 16+ ASCII characters"
        )
    raw_conditions = node.get("conditions")
    if not isinstance(raw_conditions, list) or not raw_conditions:
        raise ConfigError(f"study.conditions={_short(raw_conditions)} is invalid: must be a non-empty list")
    conditions = tuple(_condition(c, i) for i, c in enumerate(raw_conditions))
    labels = [c.label for c in conditions]
    if len(set(labels)) != len(labels):
        dup = next(x for x in labels if labels.count(x) > 1)
        raise ConfigError(f"study.conditions label {dup!r} is used twice: labels must be unique")
    raw_items = node.get("questionnaire") or []
    if not isinstance(raw_items, list):
        raise ConfigError(f"study.questionnaire={_short(raw_items)} is invalid: must be a list of items")
    items = tuple(_item(x, i) for i, x in enumerate(raw_items))
    ids = [x.id for x in items]
    if len(set(ids)) != len(ids):
        dup = next(x for x in ids if ids.count(x) > 1)
        raise ConfigError(f"study.questionnaire id {dup!r} is used twice: item ids must be unique")
    calibration = node.get("calibration") or {}
    if not isinstance(calibration, Mapping):
        raise ConfigError(f"study.calibration={_short(calibration)} is invalid: must be {{trials, optional}}")
    trials = _int({"trials": calibration.get("trials", 8)}, "trials", 0, MAX_TRIALS, "study.calibration.")
    optional = calibration.get("optional", True)
    if not isinstance(optional, bool):
        raise ConfigError(f"study.calibration.optional={_short(optional)} is invalid: must be true or false")
    host = node.get("host", "127.0.0.1")
    if not isinstance(host, str) or not host or any(c.isspace() for c in host):
        raise ConfigError(f"study.host={_short(host)} is invalid: must be an address such as 127.0.0.1")
    enrollment = _choice({"enrollment": node.get("enrollment", "open")}, "enrollment", ENROLLMENTS)
    study = StudyConfig(
        name=name,
        dir=_str(node, "dir"),
        title=_str(node, "title"),
        consent=_str(node, "consent"),
        instructions=_str(node, "instructions"),
        conditions=conditions,
        seed=_int({"seed": node.get("seed", 0)}, "seed", 0, 2**31 - 1),
        host=host,
        port=_int({"port": node.get("port", 8800)}, "port", 0, 65535),
        allowed_hosts=_strings(node, "allowed_hosts"),
        researcher_token=token,
        enrollment=enrollment,
        codes=_int({"codes": node.get("codes", 20)}, "codes", 1, 10000),
        max_participants=_int(
            {"max_participants": node.get("max_participants", 20)}, "max_participants", 1, 10000
        ),
        practice_s=_float({"practice_s": node.get("practice_s", 30)}, "practice_s", 5.0, 600.0),
        calibration=Calibration(trials, optional),
        questionnaire=items,
        common=_overrides(node, "common", "study."),
        design=_choice({"design": node.get("design", "blocked")}, "design", DESIGNS),
    )
    if study.enrollment == "codes" and study.codes > study.max_participants:
        raise ConfigError(
            f"study.codes={study.codes} is invalid with enrollment=codes: must be at most "
            f"study.max_participants={study.max_participants} (each code is a place in the study)"
        )
    return study
