"""A study on disk and its workers: who is at which step, what each step takes, and each participant's
``train.py`` run (see docs/study.md and the layout in :mod:`hfrl_torch.study.layout`).

Everything a participant did is on disk (``participant.json``, written atomically, and ``events.jsonl``)
before :meth:`Study.advance` returns, so a study killed at any moment resumes where it was: opening it
again restarts the workers of the participants who were teaching (``resume=`` their run). The web server
calls :meth:`Study.poll` every fraction of a second to reap workers; nothing here blocks for long except
:meth:`Study.open` (it waits for a killed study's workers to finish saving) and :meth:`Study.close`.
"""

from __future__ import annotations

import contextlib
import json
import shutil
import sys
import threading
import time
from collections.abc import Mapping
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.study import calibration, codes, layout
from hfrl_torch.study.config import StudyConfig
from hfrl_torch.study.design import condition_for
from hfrl_torch.study.workers import (
    STOP_TIMEOUT_S,
    TRAIN_SCRIPT,
    Worker,
    free_port,
    fresh_command,
    has_checkpoint,
    holds_run,
    previous_pid,
    resume_command,
    wait_gone,
)

MAX_RESTARTS = 2  # a crashed worker is restarted (resume=) this many times, then the teaching step ends
CONFIG_EXIT = 2  # train.py's exit status for bad input: restarting cannot help
OPEN_WAIT_S = 60.0  # how long opening a study waits for a killed study's worker to finish saving
ACTIONS = {
    "consent": ("agree", "decline"),
    "instructions": ("next",),
    "practice": ("next",),
    "calibration": ("next", "skip"),
    "teaching": ("next",),
    "questionnaire": ("next",),
}


class JoinRefused(UserError):
    """No new participant can join (enrollment=codes, or the study is full)."""


class StudyFull(JoinRefused):
    """Every place of the study (``max_participants``) is taken."""


class StepConflict(Exception):
    """The page is on another step than the participant (a stale page, a reload): ``state`` is the current
    one."""

    def __init__(self, state: dict[str, Any]) -> None:
        super().__init__(f"the participant is at step {state['step']!r}")
        self.state = state


@dataclass
class Participant:
    """One participant's record (``participant.json``)."""

    code: str
    index: int
    condition: str
    step: str = "consent"
    steps: dict[str, float] = field(default_factory=dict)
    simulated: bool = False
    calibration: dict[str, Any] | None = None
    answers: dict[str, Any] | None = None
    run_dir: str = ""
    ended: str | None = None
    stopped: bool = False
    restarts: int = 0

    def to_dict(self) -> dict[str, Any]:
        """The record as JSON."""
        return asdict(self)

    @classmethod
    def from_dict(cls, record: Mapping[str, Any]) -> Participant:
        """A record read back (unknown keys, such as ``run_path``, are left out)."""
        names = cls.__dataclass_fields__
        return cls(**{k: v for k, v in record.items() if k in names})


class Study:
    """A study on disk: its participants, their steps and their workers (train.py runs)."""

    def __init__(
        self,
        cfg: StudyConfig,
        directory: Path,
        python: str,
        train_script: Path,
        credits: Mapping[str, str],
    ) -> None:
        self.cfg = cfg
        self.directory = directory
        self.python = python
        self.train_script = train_script
        self.credits = dict(credits)
        self.researcher_token = ""
        self._participants: dict[str, Participant] = {}
        self._premade: frozenset[str] = frozenset()
        self._workers: dict[str, Worker] = {}
        self._summaries: dict[str, dict[str, Any]] = {}
        self._lock = threading.RLock()
        # workers are forked from this one thread, which lives until close(): their PR_SET_PDEATHSIG fires
        # when the thread that forked them ends, whichever thread calls the study
        self._spawner = ThreadPoolExecutor(max_workers=1, thread_name_prefix="study-workers")
        self._closed = False

    @classmethod
    def open(
        cls,
        cfg: StudyConfig,
        directory: Path | str,
        python: str = sys.executable,
        train_script: Path = TRAIN_SCRIPT,
        credits: Mapping[str, str] | None = None,
    ) -> Study:
        """Create the study in ``directory``, or resume the one there (its teaching participants' workers
        start again). ``credits``: each condition's ``human.credit`` (as train.py composes it); a
        calibration sets the gamma delay density of the conditions that credit by ``gamma``.
        ConfigError when the directory holds a study with another config."""
        directory = Path(directory).resolve()
        study = cls(cfg, directory, python, Path(train_script), credits or {})
        saved = directory / layout.STUDY_JSON
        if saved.exists():
            try:
                difference = cfg.difference(layout.read_json(saved))
            except (OSError, ValueError) as exc:
                raise ConfigError(
                    f"{saved} cannot be read ({exc}): is {directory} a study directory?"
                ) from None
            if difference is not None:
                raise ConfigError(
                    f"{directory} holds a study with another config ({difference}); run it with its own "
                    "config or choose another study.dir"
                )
            resumed = True
        else:
            if (directory / layout.PARTICIPANTS).exists() or holds_run(directory):
                raise ConfigError(f"{directory} holds other files than a study's: choose another study.dir")
            resumed = False
        (directory / layout.PARTICIPANTS).mkdir(parents=True, exist_ok=True)
        layout.write_json(saved, cfg.to_dict())
        study._load_secrets()
        for record in layout.read_participants(directory):
            p = Participant.from_dict(record)
            study._participants[p.code] = p
        layout.append_event(
            directory, "resumed" if resumed else "created", participants=len(study._participants)
        )
        for p in study._participants.values():
            if p.step == "teaching" and not p.stopped:
                wait_gone(layout.worker_pid(directory, p.code), OPEN_WAIT_S)
                study._try_launch(p)
        return study

    def _load_secrets(self) -> None:
        token_path = self.directory / layout.RESEARCHER_TOKEN
        if self.cfg.researcher_token is not None:
            self.researcher_token = self.cfg.researcher_token
        elif token_path.exists():
            self.researcher_token = token_path.read_text().strip()
        else:
            self.researcher_token = codes.new_token()
            layout.write_secret(token_path, self.researcher_token + "\n")
        if self.cfg.enrollment != "codes":
            return
        codes_path = self.directory / layout.CODES_TXT
        if codes_path.exists():
            premade = [c for c in (codes.normalise(x) for x in codes_path.read_text().split()) if c]
        else:
            taken: set[str] = set()
            for _ in range(self.cfg.codes):
                taken.add(codes.new_code(taken))
            premade = sorted(taken)
            layout.write_secret(codes_path, "".join(c + "\n" for c in premade))
        self._premade = frozenset(premade)

    @property
    def premade_codes(self) -> list[str]:
        """The pre-made codes (enrollment=codes), for the researcher to hand out."""
        return sorted(self._premade)

    # participants

    def join(self, simulated: bool) -> Participant:
        """Enrol a new participant (open enrollment) and assign their condition by the design."""
        if self.cfg.enrollment != "open":
            raise JoinRefused(
                "this study takes participants by their codes only: enter the code you were given"
            )
        with self._lock:
            return self._enrol(codes.new_code(set(self._participants)), bool(simulated))

    def _enrol(self, code: str, simulated: bool) -> Participant:
        index = len(self._participants)
        if index >= self.cfg.max_participants:
            raise StudyFull(f"the study is full ({self.cfg.max_participants} participants)")
        p = Participant(
            code=code,
            index=index,
            condition=condition_for(index, self.cfg.labels(), self.cfg.seed),
            steps={"consent": round(time.time(), 3)},
            simulated=simulated,
            run_dir=layout.relative_run_dir(code),
        )
        layout.participant_dir(self.directory, code).mkdir(parents=True, exist_ok=True)
        self._save(p)
        self._participants[code] = p
        layout.append_event(self.directory, "enrolled", code=code, index=index, simulated=simulated)
        return p

    def get(self, code: str) -> Participant | None:
        """The participant with ``code`` (a pre-made code is enrolled on its first use); None for any
        other string."""
        key = codes.normalise(code)
        if key is None:
            return None
        with self._lock:
            p = self._participants.get(key)
            if p is None and key in self._premade:
                p = self._enrol(key, simulated=False)
            return p

    def _require(self, code: str) -> Participant:
        p = self.get(code)
        if p is None:
            raise KeyError(code)
        return p

    def _save(self, p: Participant) -> None:
        layout.write_json(layout.participant_json(self.directory, p.code), p.to_dict())

    def _enter(self, p: Participant, step: str, **fields: Any) -> None:
        p.step = step
        p.steps[step] = round(time.time(), 3)
        self._save(p)
        layout.append_event(self.directory, "step", code=p.code, step=step, **fields)

    def state(self, code: str) -> dict[str, Any]:
        """What the participant's page is told (never the condition). KeyError for an unknown code."""
        with self._lock:
            p = self._require(code)
            ready = p.step == "teaching" and not p.stopped and self.teaching_endpoint(p.code) is not None
            return {
                "step": p.step,
                "study": self.cfg.public(),
                "teaching": {"ready": ready, "url": f"/p/{p.code}/teach/"},
                "stopped": p.stopped,
                "ended": p.ended,
                "summary": self._summary(p),
            }

    def _summary(self, p: Participant) -> dict[str, Any] | None:
        if p.code in self._summaries:
            return self._summaries[p.code]
        if p.step not in ("questionnaire", "done"):
            return None
        path = self.directory / p.run_dir / layout.TEACHING_SUMMARY
        try:
            summary = json.loads(path.read_text())
        except (OSError, ValueError):
            return None
        self._summaries[p.code] = summary
        return summary

    def advance(
        self, code: str, step: str, action: str, data: Mapping[str, Any] | None = None
    ) -> dict[str, Any]:
        """Do ``action`` on ``step`` and return the new state. StepConflict (with the current state) when
        ``step`` is not the participant's; ValueError (one line) for an action or data the step does not
        take; KeyError for an unknown code."""
        data = {} if data is None else data
        with self._lock:
            p = self._require(code)
            if step != p.step:
                raise StepConflict(self.state(code))
            allowed = ACTIONS.get(p.step, ())
            if action not in allowed:
                raise ValueError(
                    f"action={action!r} is invalid at step {p.step!r}; allowed: {', '.join(allowed) or '-'}"
                )
            if not isinstance(data, Mapping):
                raise ValueError("data must be an object")
            getattr(self, f"_on_{p.step}")(p, action, data)
            return self.state(code)

    @staticmethod
    def _no_data(data: Mapping[str, Any], *allowed: str) -> None:
        extra = sorted(set(data) - set(allowed))
        if extra:
            raise ValueError(
                f"data key {extra[0]!r} is invalid here; allowed: {', '.join(allowed) or 'none'}"
            )

    def _on_consent(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        self._no_data(data)
        if action == "decline":
            p.ended = "declined"
            self._enter(p, layout.DECLINED)
        else:
            self._enter(p, "instructions")

    def _on_instructions(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        self._no_data(data)
        self._enter(p, "practice")

    def _on_practice(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        self._no_data(data)
        if self.cfg.calibration.trials > 0:
            self._enter(p, "calibration")
        else:
            self._start_teaching(p)

    def _on_calibration(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        if action == "skip":
            self._no_data(data)
            if not self.cfg.calibration.optional:
                raise ValueError("the calibration cannot be skipped in this study")
        else:
            self._no_data(data, "delays_s")
            if "delays_s" not in data:
                raise ValueError("data.delays_s is missing: the measured delays in seconds")
            p.calibration = calibration.fit(data["delays_s"])
        self._start_teaching(p)

    def _on_teaching(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        self._no_data(data)
        self._reap(p.code)
        if p.step != "teaching":
            return
        if p.code in self._workers or p.stopped:
            raise ValueError("the teaching session is still going: finish it on the teaching page first")
        self._enter(p, "questionnaire")

    def _on_questionnaire(self, p: Participant, action: str, data: Mapping[str, Any]) -> None:
        self._no_data(data, "answers")
        p.answers = self._answers(data.get("answers", {}))
        self._enter(p, "done")

    def _answers(self, answers: Any) -> dict[str, Any]:
        """The answers checked against the items: a Likert item takes an integer 1..points, a text item a
        string of at most max_chars; an item left out (or null) was not answered."""
        if not isinstance(answers, Mapping):
            raise ValueError("data.answers must be an object of item id: answer")
        items = {i.id: i for i in self.cfg.questionnaire}
        out: dict[str, Any] = {}
        for key, value in answers.items():
            item = items.get(key)
            if item is None:
                raise ValueError(
                    f"answers has no item {str(key)[:40]!r}; items: {', '.join(items) or 'none'}"
                )
            if value is None:
                continue
            if item.kind == "likert":
                if not isinstance(value, int) or isinstance(value, bool) or not 1 <= value <= item.points:
                    raise ValueError(
                        f"answers.{key}={repr(value)[:20]} is invalid: must be an integer 1..{item.points}"
                    )
            elif not isinstance(value, str) or len(value) > item.max_chars:
                raise ValueError(
                    f"answers.{key} is invalid: must be text of at most {item.max_chars} characters"
                )
            out[key] = value
        return out

    # workers

    def _start_teaching(self, p: Participant) -> None:
        self._enter(p, "teaching")
        if not p.stopped:
            self._try_launch(p)

    def _overrides(self, p: Participant) -> list[str]:
        """The condition's train.py overrides, the study's common ones and the calibration's."""
        out = [*self.cfg.condition(p.condition).overrides, *self.cfg.common]
        cal = p.calibration
        if cal is not None:
            out.append(f"trainer.reaction_s={cal['reaction_s']}")
            if self.credits.get(p.condition) == "gamma" and cal.get("gamma_shape") is not None:
                out += [f"human.gamma_shape={cal['gamma_shape']}", f"human.gamma_scale={cal['gamma_scale']}"]
        return out

    def _launch(self, p: Participant) -> bool:
        """Start the participant's worker (resuming the run its directory holds); False (nothing started)
        while a previous worker of the same run is still going."""
        pid_path = layout.worker_pid(self.directory, p.code)
        if p.code in self._workers or previous_pid(pid_path) is not None:
            return False
        run = self.directory / p.run_dir
        resume = has_checkpoint(run)
        if not resume and holds_run(run):  # killed before its first checkpoint: nothing to resume from
            aside = run.with_name(f"{run.name}.unfinished-{int(time.time())}")
            shutil.move(run, aside)
            layout.append_event(self.directory, "run_set_aside", code=p.code, to=aside.name)
        used = {w.port for w in self._workers.values()}
        port, token = free_port(avoid=used), codes.new_token()
        if resume:
            command = resume_command(self.python, self.train_script, run, port, token)
        else:
            seed = self.cfg.seed * 1000 + p.index
            command = fresh_command(
                self.python, self.train_script, self._overrides(p), run, port, token, seed
            )
        worker = Worker(command, port, token, layout.worker_log(self.directory, p.code), pid_path)
        self._spawner.submit(worker.start).result()
        self._workers[p.code] = worker
        layout.append_event(
            self.directory, "worker_start", code=p.code, pid=worker.pid, port=port, resume=resume
        )
        return True

    def _try_launch(self, p: Participant) -> None:
        """:meth:`_launch`, where a worker that cannot be started (no port, no process) counts as a crash;
        nothing after :meth:`close` (the participant's run starts when the study is opened again)."""
        if self._closed:
            return
        try:
            self._launch(p)
        except OSError as exc:
            layout.append_event(self.directory, "worker_start_failed", code=p.code, error=str(exc)[:200])
            if p.restarts < MAX_RESTARTS:
                p.restarts += 1
                self._save(p)
                return
            p.ended = f"the run could not start ({str(exc)[:80]})"
            self._enter(p, "questionnaire")

    def teaching_endpoint(self, code: str) -> tuple[int, str] | None:
        """``(port, worker token)`` of the participant's worker once it accepts connections; else None."""
        key = codes.normalise(code)
        with self._lock:
            worker = self._workers.get(key) if key else None
            if worker is None or worker.check() is not None or not worker.ready:
                return None
            return worker.port, worker.token

    def _reap(self, code: str) -> None:
        """Act on the end of ``code``'s worker, if it ended: by the study's stop (nothing more), by itself
        (the participant moves to the questionnaire), or by a crash (restarted, at most MAX_RESTARTS)."""
        worker = self._workers.get(code)
        if worker is None:
            return
        status = worker.check()
        if status is None:
            return
        del self._workers[code]
        with contextlib.suppress(OSError):
            worker.pid_path.unlink()
        p = self._participants[code]
        by = "study" if worker.stopping else ("itself" if status == 0 else "crash")
        layout.append_event(self.directory, "worker_exit", code=code, status=status, by=by)
        if by == "study" or p.step != "teaching":
            return
        if by == "itself":
            p.ended = "finished"
            self._enter(p, "questionnaire")
            return
        if status != CONFIG_EXIT and p.restarts < MAX_RESTARTS:
            p.restarts += 1
            self._save(p)
            self._try_launch(p)
            return
        p.ended = f"the run failed (exit status {status})"
        self._enter(p, "questionnaire")

    def poll(self) -> None:
        """Reap ended workers and start those waiting for a previous worker to go (call it often)."""
        with self._lock:
            for code in list(self._workers):
                self._reap(code)
            for p in self._participants.values():
                if p.step == "teaching" and not p.stopped and p.code not in self._workers:
                    self._try_launch(p)

    def stop(self, code: str) -> None:
        """The researcher pauses the participant: their worker stops (SIGTERM: it saves); the page says so."""
        with self._lock:
            p = self._require(code)
            p.stopped = True
            self._save(p)
            layout.append_event(self.directory, "stopped", code=p.code)
            worker = self._workers.get(p.code)
            if worker is not None:
                worker.terminate()

    def resume(self, code: str) -> None:
        """The researcher lets a stopped participant go on: in the teaching step their run continues
        (``resume=``) as soon as the stopped worker is gone."""
        with self._lock:
            p = self._require(code)
            p.stopped = False
            self._save(p)
            layout.append_event(self.directory, "resumed_participant", code=p.code)
            if p.step == "teaching":
                self._reap(p.code)
                self._try_launch(p)

    def overview(self) -> list[dict[str, Any]]:
        """Every participant for the researcher: step, condition, progress, presses, worker state."""
        with self._lock:
            rows = []
            for p in sorted(self._participants.values(), key=lambda x: x.index):
                worker = self._workers.get(p.code)
                if worker is not None:
                    worker.check()
                run = self.directory / p.run_dir
                rows.append(
                    {
                        "code": p.code,
                        "index": p.index,
                        "condition": p.condition,
                        "step": p.step,
                        "steps": dict(p.steps),
                        "simulated": p.simulated,
                        "stopped": p.stopped,
                        "ended": p.ended,
                        "restarts": p.restarts,
                        "presses": _lines(run / layout.PRESSES),
                        "feedback": _lines(run / layout.FEEDBACK),
                        "progress": _last_line(run / layout.METRICS),
                        "worker": "none" if worker is None else worker.state,
                    }
                )
            return rows

    def close(self, timeout: float = STOP_TIMEOUT_S) -> None:
        """Stop every worker (SIGTERM: each saves) and wait for them; their participants stay in teaching
        and resume when the study is opened again."""
        with self._lock:
            self._closed = True
            workers = list(self._workers.items())
            for _, worker in workers:
                worker.terminate(timeout)
            for code, worker in workers:
                status = worker.wait(timeout)
                with contextlib.suppress(OSError):
                    worker.pid_path.unlink()
                layout.append_event(self.directory, "worker_exit", code=code, status=status, by="study")
                del self._workers[code]
            layout.append_event(self.directory, "closed")
        self._spawner.shutdown()


def _lines(path: Path) -> int:
    """Complete lines in ``path`` (0 when it does not exist)."""
    try:
        with open(path, "rb") as f:
            return sum(chunk.count(b"\n") for chunk in iter(lambda: f.read(1 << 16), b""))
    except OSError:
        return 0


def _last_line(path: Path) -> dict[str, Any] | None:
    """The last complete JSON line of ``path`` (a curve's latest point), or None."""
    try:
        with open(path, "rb") as f:
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(size - 8192, 0))
            tail = f.read().split(b"\n")
    except OSError:
        return None
    for line in reversed(tail):
        with contextlib.suppress(ValueError):
            value = json.loads(line)
            if isinstance(value, dict):
                return value
    return None
