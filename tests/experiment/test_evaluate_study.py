"""evaluate.py runs=<study dir>: participants compared between subjects, questionnaire, simulated named."""

from __future__ import annotations

import csv
import itertools
import json
import math
import shutil
from pathlib import Path

import pytest
from omegaconf import OmegaConf
from script_runner import run_script

from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.experiment import study_report
from hfrl_torch.experiment.aggregate import Run
from hfrl_torch.experiment.cli import compose_train
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.run import RunFiles, learn
from hfrl_torch.experiment.study_report import (
    EXACT_LIMIT,
    _merged,
    aggregate_study,
    study_dir_of,
    unpaired_permutation,
)
from hfrl_torch.feedback.log import load_feedback_log
from hfrl_torch.study import layout

TINY = [
    "agent=cem",
    "trainer=oracle",
    "domain.width=6",
    "domain.height=8",
    "agent.population=10",
    "agent.games_per_candidate=2",
    "agent.eval_games=4",
    "agent.watch_pieces=40",
    "logger.backend=none",
    "threads=1",
]
CONDITIONS = {
    "linear": ["fusion=linear"],
    "human_only": ["fusion=human_only"],
    "solo": ["fusion=linear", "fusion.weight=adaptive"],
}
QUESTIONNAIRE = [
    {"id": "effort", "kind": "likert", "text": "It took effort.", "points": 7},
    {"id": "improved", "kind": "likert", "text": "It improved.", "points": 5},
    {"id": "comments", "kind": "text", "text": "Anything else?", "max_chars": 2000},
]
# code: condition, simulated, step, iterations run (None: no run), answers
PARTICIPANTS = {
    "AAAA": ("linear", True, "done", 3, {"effort": 5, "improved": 4, "comments": "fun"}),
    "BBBB": ("human_only", True, "done", 3, {"effort": 1, "improved": 2, "comments": ""}),
    "CCCC": ("solo", False, "questionnaire", 2, {"effort": 7, "improved": 5, "comments": "hard, but ok"}),
    "DDDD": ("linear", False, "done", 2, {"effort": 3, "improved": 4, "comments": ""}),
    "EEEE": ("human_only", True, "done", 2, {"effort": 2, "improved": 1, "comments": "meh"}),
    "FFFF": ("linear", False, "declined", None, None),
    "GGGG": ("human_only", True, "instructions", None, None),
    "HHHH": ("linear", True, "teaching", 0, None),  # its run crashed before a first iteration
}


def _record(code: str, index: int) -> dict:
    condition, simulated, step, _, answers = PARTICIPANTS[code]
    order = [*layout.STEPS, layout.DECLINED]
    steps = order[: order.index(step) + 1] if step != layout.DECLINED else ["consent", layout.DECLINED]
    return {
        "code": code,
        "index": index,
        "condition": condition,
        "step": step,
        "steps": {s: 1.7e9 + i for i, s in enumerate(steps)},
        "simulated": simulated,
        "calibration": None,
        "answers": answers,
        "run_dir": f"{layout.PARTICIPANTS}/{code}/{layout.RUN}",
        "ended": None,
    }


@pytest.fixture(scope="module")
def study(tmp_path_factory, one_thread) -> Path:
    """A study directory whose participants' runs are real tiny runs of train.py's loop (CE + oracle)."""
    root = tmp_path_factory.mktemp("study") / "pilot"
    conditions = [{"label": k, "overrides": v} for k, v in CONDITIONS.items()]
    root.mkdir()
    (root / layout.STUDY_JSON).write_text(
        json.dumps({"name": "pilot", "seed": 0, "conditions": conditions, "questionnaire": QUESTIONNAIRE})
    )
    for index, code in enumerate(PARTICIPANTS):
        home = root / layout.PARTICIPANTS / code
        home.mkdir(parents=True)
        (home / layout.PARTICIPANT_JSON).write_text(json.dumps(_record(code, index)))
        condition, _, _, iterations, _ = PARTICIPANTS[code]
        if iterations is None:
            continue
        run = home / layout.RUN
        if iterations == 0:
            run.mkdir()
            (run / "config.yaml").write_text("seed: 7\n")
            continue
        over = [*TINY, *CONDITIONS[condition], f"agent.iterations={iterations}", f"seed={index}"]
        if code == "AAAA":  # as a study's worker runs it
            out = run_script("train.py", *over, f"hydra.run.dir={run}", timeout=300)
            assert out.returncode == 0, out.stderr[-2000:]
        else:  # train.py's loop in this process, and the config.yaml train.py writes
            cfg = compose_train(*over)
            run.mkdir()
            (run / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=True))
            learn(CEMLearner(cfg, run), RunFiles(run, cfg))
    journal = root / layout.PARTICIPANTS / "CCCC" / layout.RUN / "presses.jsonl"
    press = {"wall": 1.7e9, "value": 1.0, "source": "human:browser", "episode": 0, "step": 3, "sim": None}
    lines = [{"schema": "hfrl_torch.presses", "version": 1, "created": 1.7e9}]
    lines += [press | {"n": n} for n in range(3)]
    journal.write_text("".join(json.dumps(x) + "\n" for x in lines))
    return root


@pytest.fixture(scope="module")
def reported(study) -> tuple[Path, str, str]:
    """``python evaluate.py runs=<study>`` once: its results directory, stdout and stderr."""
    out = run_script("evaluate.py", f"runs={study}", timeout=300)
    assert out.returncode == 0, out.stderr[-3000:]
    return study / layout.RESULTS, out.stdout, out.stderr


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


def _by_hand(a: list[float], b: list[float]) -> float:
    """Two-sided exact permutation p of the difference of means, written out."""
    pooled, extreme, total = a + b, 0, 0
    observed = abs(sum(a) / len(a) - sum(b) / len(b))
    for chosen in itertools.combinations(range(len(pooled)), len(a)):
        x = [pooled[i] for i in chosen]
        y = [pooled[i] for i in range(len(pooled)) if i not in chosen]
        total += 1
        extreme += abs(sum(x) / len(x) - sum(y) / len(y)) >= observed - 1e-12
    return extreme / total


def _pooled_d(a: list[float], b: list[float]) -> float:
    def var(v: list[float]) -> float:
        m = sum(v) / len(v)
        return sum((x - m) ** 2 for x in v) / (len(v) - 1)

    pooled = math.sqrt(((len(a) - 1) * var(a) + (len(b) - 1) * var(b)) / (len(a) + len(b) - 2))
    return (sum(a) / len(a) - sum(b) / len(b)) / pooled


def test_the_unpaired_permutation_test_is_exact_when_small_and_seeded_otherwise(monkeypatch):
    # 1, 2 against 3, 4, 5: of the C(5, 2) = 10 relabellings, {1, 2} and {4, 5} are as extreme as |1.5 - 4|
    assert unpaired_permutation([1.0, 2.0], [3.0, 4.0, 5.0]) == (0.2, "exact, 10 relabellings")
    assert _by_hand([1.0, 2.0], [3.0, 4.0, 5.0]) == 0.2
    a, b = [10.0 + i for i in range(12)], [float(i) for i in range(12)]
    assert math.comb(24, 12) > EXACT_LIMIT
    p, how = unpaired_permutation(a, b)
    assert how == "Monte Carlo, 20000 relabellings (seed 0)" and p == pytest.approx(1 / 20001)
    assert unpaired_permutation(a, b) == (p, how)  # seeded
    mixed, other = [3.0, 1.0, 4.0, 1.0, 5.0, 9.0, 2.0, 6.0], [2.0, 7.0, 1.0, 8.0, 2.0, 8.0, 1.0, 8.0, 2.0]
    p_mc, how = unpaired_permutation(mixed, other)
    assert math.comb(17, 8) > EXACT_LIMIT and how.startswith("Monte Carlo")
    monkeypatch.setattr(study_report, "EXACT_LIMIT", math.comb(17, 8))
    p_exact, how = unpaired_permutation(mixed, other)
    assert how == "exact, 24310 relabellings" and p_mc == pytest.approx(p_exact, abs=0.01)


def test_conditions_are_compared_between_subjects_against_a_hand_computation(reported, study):
    out, stdout, _ = reported
    people = {r["code"]: r for r in _csv(out / "per_participant.csv")}
    for code in ("AAAA", "BBBB", "CCCC", "DDDD", "EEEE"):  # the value compared: each run's last point
        rows = (study / layout.PARTICIPANTS / code / "run" / "metrics.jsonl").read_text().splitlines()
        last = json.loads(rows[-1])
        assert float(people[code]["value"]) == pytest.approx(last["eval/mean_policy_lines_mean"])
        assert int(people[code]["points"]) == PARTICIPANTS[code][3] == int(float(people[code]["last_x"]))
    linear = [float(people[c]["value"]) for c in ("AAAA", "DDDD")]
    human = [float(people[c]["value"]) for c in ("BBBB", "EEEE")]
    rows = {r["condition"]: r for r in _csv(out / "summary.csv")}
    assert rows["linear"]["reference"] == "linear" and rows["linear"]["p_value"] == ""
    h = rows["human_only"]
    assert h["participants"] == "2" and h["codes"] == "BBBB EEEE"
    assert float(h["p_value"]) == pytest.approx(_by_hand(human, linear))
    assert h["test"] == "unpaired permutation, exact, 6 relabellings"
    assert float(h["p_holm"]) == float(h["p_value"])  # the only test: Holm leaves it
    assert float(h["difference"]) == pytest.approx(sum(human) / 2 - sum(linear) / 2)
    assert float(h["effect_size"]) == pytest.approx(_pooled_d(human, linear))
    said = next(x for x in stdout.splitlines() if x.startswith("human_only: "))
    assert f"Holm p = {float(h['p_holm']):.3f}, 2 participants, 2 simulated" in said
    assert float(h["ci95_low"]) < float(h["mean"]) < float(h["ci95_high"])
    assert "unpaired permutation test" in stdout and "between subjects" in stdout
    assert json.loads(stdout.strip().splitlines()[-1])["analysed"] == 5


def test_a_one_participant_condition_gets_no_interval_or_p_and_says_why(reported):
    out, stdout, _ = reported
    solo = {r["condition"]: r for r in _csv(out / "summary.csv")}["solo"]
    assert solo["participants"] == "1" and solo["ci95_low"] == "" and solo["p_value"] == ""
    assert solo["p_holm"] == "" and solo["test"] == "none (1 participant: no spread to test)"
    line = next(x for x in stdout.splitlines() if x.startswith("| solo"))
    assert "| none (1 participant) |" in line and "no spread to test" in line


def test_simulated_participants_are_named_in_the_title_header_tables_and_csvs(reported):
    out, stdout, _ = reported
    md = (out / "summary.md").read_text()
    assert (
        md.splitlines()[0]
        == "# Study pilot: results with 3 SIMULATED participant(s), not human-subject results"
    )
    assert "Participants analysed: 5: 3 simulated (scripted clients" in md and "and 2 people" in md
    assert "| linear [1 of 2 simulated] (reference) |" in md and "| human_only [2 of 2 simulated] |" in md
    assert "| solo |" in md  # a person alone
    people = {r["code"]: r["simulated"] for r in _csv(out / "per_participant.csv")}
    assert people == {c: str(v[1]) for c, v in PARTICIPANTS.items()}
    assert {r["code"]: r["simulated"] for r in _csv(out / "questionnaire_text.csv")} == {
        "AAAA": "True",
        "CCCC": "False",
        "EEEE": "True",
    }
    likert = _csv(out / "questionnaire_likert.csv")
    assert {(r["item"], r["condition"]): r["simulated"] for r in likert}[("effort", "human_only")] == "2"
    assert md.rstrip("\n") in stdout


def test_declined_and_stopped_participants_are_counted_not_analysed(reported):
    out, _, _ = reported
    md = (out / "summary.md").read_text()
    assert (
        "Enrolled: 8." in md
        and "1 declined consent" in md
        and "never reached teaching: 1 at instructions" in md
    )
    assert "reached teaching but left out: 1 (its run has no metrics: HHHH)." in md
    people = {r["code"]: r for r in _csv(out / "per_participant.csv")}
    assert people["FFFF"]["analysed"] == "False" and people["FFFF"]["excluded"] == "declined"
    assert people["GGGG"]["excluded"] == "never reached teaching (at instructions)"
    assert people["GGGG"]["steps_reached"] == "consent instructions"
    assert people["HHHH"]["analysed"] == "False" and people["HHHH"]["value"] == ""
    codes = " ".join(r["codes"] for r in _csv(out / "summary.csv"))
    assert "FFFF" not in codes and "GGGG" not in codes and "HHHH" not in codes


def test_feedback_counts_and_final_metrics_per_participant(reported, study):
    out, _, _ = reported
    people = {r["code"]: r for r in _csv(out / "per_participant.csv")}
    for code in ("AAAA", "DDDD"):
        run = study / layout.PARTICIPANTS / code / "run"
        events = load_feedback_log(run / "feedback.jsonl")
        assert int(people[code]["feedback_logged"]) == len(events) > 0
        assert int(people[code]["feedback_good"]) + int(people[code]["feedback_bad"]) == len(events)
        last = json.loads((run / "metrics.jsonl").read_text().splitlines()[-1])
        assert float(people[code]["final:feedback/learned_total"]) == last["feedback/learned_total"]
    assert people["CCCC"]["presses_journaled"] == "3" and people["AAAA"]["presses_journaled"] == ""
    assert (out / "curves.png").stat().st_size > 1000 and (out / "effort.png").stat().st_size > 1000
    assert list((out / "tensorboard").glob("events.out.tfevents.*"))


def test_the_questionnaire_is_summarised_per_condition_and_compared(reported):
    out, stdout, _ = reported
    likert = {(r["item"], r["condition"]): r for r in _csv(out / "questionnaire_likert.csv")}
    effort = likert[("effort", "linear")]  # AAAA 5, DDDD 3
    assert (
        effort["n"] == "2"
        and float(effort["mean"]) == 4.0
        and float(effort["sd"]) == pytest.approx(math.sqrt(2))
    )
    assert [effort[f"answered_{k}"] for k in range(1, 8)] == ["0", "0", "1", "0", "1", "0", "0"]
    human = likert[("effort", "human_only")]  # BBBB 1, EEEE 2 against 5, 3
    assert float(human["p_value"]) == pytest.approx(_by_hand([1, 2], [5, 3])) == pytest.approx(2 / 6)
    improved = likert[("improved", "human_only")]  # 2, 1 against 4, 4
    assert float(improved["p_value"]) == pytest.approx(_by_hand([2, 1], [4, 4]))
    # Holm over the two Likert comparisons (solo has one answer: no test)
    p = sorted([float(human["p_value"]), float(improved["p_value"])])
    assert sorted([float(human["p_holm"]), float(improved["p_holm"])]) == pytest.approx(
        [min(1, 2 * p[0]), max(min(1, 2 * p[0]), p[1])]
    )
    assert likert[("effort", "solo")]["p_value"] == "" and likert[("effort", "solo")]["sd"] == ""
    assert (
        "answered_6" not in likert[("improved", "linear")]
        or likert[("improved", "linear")]["answered_6"] == ""
    )
    text = _csv(out / "questionnaire_text.csv")
    assert [(r["condition"], r["code"], r["answer"]) for r in text] == [
        ("linear", "AAAA", "fun"),
        ("solo", "CCCC", "hard, but ok"),
        ("human_only", "EEEE", "meh"),
    ]
    assert "hard, but ok" not in stdout  # text answers go to the CSV only
    assert "questionnaire_text.csv: linear 1, human_only 1, solo 1" in stdout


def test_window_leaves_out_participants_who_ended_before_it_and_last_averages_their_own_end(study, tmp_path):
    result = aggregate_study(
        OmegaConf.create({"runs": str(study), "window": [2, 3], "out": str(tmp_path / "w")}), study
    )
    rows = {r["condition"]: r for r in _csv(Path(result["summary_csv"]))}
    assert rows["linear"]["participants"] == "1" and rows["linear"]["left_out"] == "DDDD"
    assert rows["human_only"]["left_out"] == "EEEE" and rows["human_only"]["p_value"] == ""
    assert "Left out of the comparison (no point in the window): " in Path(result["summary_md"]).read_text()
    result = aggregate_study(
        OmegaConf.create({"runs": str(study), "last": 2, "out": str(tmp_path / "l")}), study
    )
    people = {r["code"]: r for r in _csv(Path(result["per_participant_csv"]))}
    rows = (study / layout.PARTICIPANTS / "AAAA" / "run" / "metrics.jsonl").read_text().splitlines()
    tail = [json.loads(r)["eval/mean_policy_lines_mean"] for r in rows[-2:]]
    assert float(people["AAAA"]["value"]) == pytest.approx(sum(tail) / 2)
    assert "each run's last 2" in Path(result["summary_md"]).read_text()


def test_bad_study_input_fails_with_one_line_naming_the_file(study, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(study, broken, ignore=shutil.ignore_patterns("results"))
    bad = broken / layout.PARTICIPANTS / "BBBB" / layout.PARTICIPANT_JSON
    bad.write_text('{"code": "BBBB", "index": ')
    out = run_script("evaluate.py", f"runs={broken}", timeout=300)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert out.stderr.startswith("error: ") and str(bad) in out.stderr and "corrupt" in out.stderr
    bad.write_text(json.dumps(_record("BBBB", 1) | {"answers": {"effort": 9}}))
    with pytest.raises(
        UserError, match=r"BBBB/participant.json is corrupt: answer effort=9 is not an integer in 1..7"
    ):
        aggregate_study(OmegaConf.create({"runs": str(broken), "out": str(tmp_path / "o")}), broken)
    with pytest.raises(ConfigError, match="mixes study directory"):
        study_dir_of(OmegaConf.create({"runs": [str(broken), str(tmp_path)]}))
    assert study_dir_of(OmegaConf.create({"runs": str(tmp_path)})) is None
    with pytest.raises(ConfigError, match="baseline='nothing' is not one condition here"):
        aggregate_study(
            OmegaConf.create({"runs": str(study), "baseline": "nothing", "out": str(tmp_path)}), study
        )


DOMAINS = {"t": "tetris", "k": "keepaway", "n": "keepaway"}


def _hand_study(root: Path) -> Path:
    """A study of people only, mixing a Tetris-like and a keepaway-like metric, with hand-written curves."""
    values = {"t_a": [1, 2, 3], "t_b": [4, 5, 6], "k_a": [20, 22], "k_b": [10, 12]}
    labels = [*values, "nobody"]
    (root / layout.STUDY_JSON).parent.mkdir(parents=True)
    (root / layout.STUDY_JSON).write_text(
        json.dumps(
            {
                "name": "mixed",
                "conditions": [{"label": k, "overrides": [f"domain={DOMAINS[k[0]]}"]} for k in labels],
                "questionnaire": [{"id": "q", "kind": "likert", "points": 5}],
            }
        )
    )
    index = 0
    for label, finals in values.items():
        x, y = (
            ("iteration", "eval/mean_policy_lines_mean")
            if label[0] == "t"
            else ("episode", "eval/episode_seconds_mean")
        )
        for v in finals:
            code = f"P{index:03d}"
            record = {"code": code, "index": index, "condition": label, "step": "done", "simulated": False}
            run = root / layout.PARTICIPANTS / code / layout.RUN
            run.mkdir(parents=True)
            answers = {"q": 1 + index % 5}
            (run.parent / layout.PARTICIPANT_JSON).write_text(json.dumps(record | {"answers": answers}))
            (run / "config.yaml").write_text(f"seed: {index}\n")
            (run / "metrics.jsonl").write_text(
                json.dumps({x: 1, y: 0.0}) + "\n" + json.dumps({x: 2, y: v}) + "\n"
            )
            index += 1
    late = root / layout.PARTICIPANTS / "LATE" / layout.RUN  # keepaway: too few episodes for a point
    late.mkdir(parents=True)
    record = {"code": "LATE", "index": index, "condition": "k_a", "step": "done", "simulated": False}
    (late.parent / layout.PARTICIPANT_JSON).write_text(json.dumps(record))
    (late / "config.yaml").write_text("seed: 0\nagent:\n  log_episodes: 10\n")
    (late / "metrics.jsonl").write_text(
        json.dumps({"axis": "hours", "hours": 0.01, "episode_s_mean": 3.0}) + "\n"
    )
    return root


def test_a_mixed_study_of_people_compares_each_metric_within_itself(tmp_path):
    study = _hand_study(tmp_path / "mixed")
    result = aggregate_study(OmegaConf.create({"runs": str(study), "out": str(tmp_path / "o")}), study)
    md = Path(result["summary_md"]).read_text()
    assert md.splitlines()[0] == "# Study mixed: results" and "SIMULATED" not in md
    assert "0 simulated (scripted clients; participant.json simulated: true) and 10 people" in md
    assert (
        "1 (its run has no point of eval/episode_seconds_mean yet: a keepaway run gets one point per "
        "agent.log_episodes=10 episodes: LATE)" in md
    )
    assert "| nobody | 0 | (no participant analysed) |" in md
    rows = {r["condition"]: r for r in _csv(Path(result["summary_csv"]))}
    assert rows["t_b"]["reference"] == "t_a" and rows["k_b"]["reference"] == "k_a"
    assert rows["k_a"]["p_value"] == "" and float(rows["k_b"]["difference"]) == -10.0
    # {1,2,3} against {4,5,6}: 2 of the C(6,3) = 20 relabellings as extreme; 10, 12 against 20, 22: 2 of 6
    assert float(rows["t_b"]["p_value"]) == pytest.approx(0.1) == _by_hand([4, 5, 6], [1, 2, 3])
    assert float(rows["k_b"]["p_value"]) == pytest.approx(2 / 6)
    assert float(rows["t_b"]["p_holm"]) == pytest.approx(0.2) and float(
        rows["k_b"]["p_holm"]
    ) == pytest.approx(2 / 6)
    assert float(rows["t_b"]["effect_size"]) == pytest.approx(3.0)  # means 3 apart, pooled sd 1
    assert float(rows["t_b"]["diff_ci95_low"]) == pytest.approx(3 - 1.96 * math.sqrt(2 / 3))
    again = aggregate_study(
        OmegaConf.create({"runs": str(study), "baseline": "t_b", "out": str(tmp_path / "b")}), study
    )
    rows = {r["condition"]: r for r in _csv(Path(again["summary_csv"]))}
    assert rows["t_a"]["reference"] == "t_b" and float(rows["t_a"]["difference"]) == -3.0
    assert rows["k_b"]["reference"] == "k_a"
    likert = {r["condition"]: r for r in _csv(Path(again["questionnaire_likert_csv"]))}
    # answers 1 + index % 5: t_a 1 2 3, t_b 4 5 1, k_a 2 3, k_b 4 5; each domain against its own reference
    assert likert["t_a"]["reference"] == "t_b" and likert["k_b"]["reference"] == "k_a"
    assert float(likert["k_b"]["p_value"]) == pytest.approx(_by_hand([4, 5], [2, 3]))
    assert float(likert["t_a"]["difference"]) == pytest.approx(2 - 10 / 3)


def test_a_participant_of_several_learners_counts_once_as_their_mean():
    y = "eval/episode_seconds_mean"
    a = Run(Path("r"), {}, [{"episode": 10, y: 4.0, "weight": 1.0}, {"episode": 20, y: 6.0, "weight": 0.5}])
    b = Run(Path("r"), {}, [{"episode": 10, y: 2.0, "weight": 0.0}])  # a team that played fewer episodes
    merged = _merged([a, b])
    assert merged.rows == [{"episode": 10.0, y: 3.0, "weight": 0.5}]
    assert _merged([a]) is a
