"""The config's own resolvers: the choices a config implies, computed inside it so that they hold in sweeps.

Registered once, on import, before Hydra composes anything (``train.py`` and ``evaluate.py`` import this
package). ``python train.py --cfg job`` shows them as written; ``--resolve`` shows what they give.

- ``${implied_trainer:<fusion>}``: the trainer of ``trainer=auto`` (the default): the simulated oracle
  when the fusion scheme needs a trainer, none otherwise.
- ``${decision_period:<trainer>}``: keepaway holders decide every cycle (100 ms, the reference) without
  a trainer and every 5 cycles (500 ms, the thesis's human-feedback setting) when one watches.
- ``${keepaway_kernels:<device>,<trainer>}``: how keepaway's cycles run: ``cycle`` (whole cycles and the
  SMDP advance compiled) on the CPU, also when a person watches in the browser (the env then runs one
  compiled cycle per call, and the live view is drawn after each), ``torch`` on a GPU.
- ``${adaptive_prior_count:<domain>}``: the strength, in episodes, of the adaptive weight's prior for H^:
  4 for Tetris, 20 for keepaway, whose episodes are a few seconds each and so carry less evidence
  (measured: docs/results.md, the adaptive weight).
- ``${adaptive_arms:<domain>}``: the weights the adaptive weight's bandit chooses among: 0, 1 and 16 (no
  H^, an equal say, H^ decides), and in keepaway also 256, where H^ decides outright: its H^ is scaled by
  Q's spread, and at 16 Q still overrides it where its gaps are large (measured: docs/results.md, the
  keepaway lifetime).
- ``${run_dir:<resume>,<new>}``: where Hydra writes a run's files: a new run's own directory (``<new>``, or
  ``<new>_2``, ``<new>_3``... when a run started in the same second has it), or, when resuming,
  ``<resume>/resume-logs/<date>_<time>`` inside the resumed run.
"""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import ListConfig, OmegaConf

from hfrl_torch.fusion.bandit import DEFAULT_ARMS

RESOLVERS = (
    "implied_trainer",
    "decision_period",
    "keepaway_kernels",
    "adaptive_prior_count",
    "adaptive_arms",
    "run_dir",
)
PRIOR_EPISODES = {"tetris": 4.0, "keepaway": 20.0}
ARMS = {"keepaway": (*DEFAULT_ARMS, 256.0)}


def implied_trainer(fusion: str) -> str:
    """``none`` for ``fusion=none``, else ``oracle`` (a fusion fuses a trainer's H^ with the environment)."""
    return "none" if fusion == "none" else "oracle"


def decision_period(trainer: str) -> int:
    """Cycles between a keepaway holder's decisions: 1 without a trainer, 5 when one watches."""
    return 1 if trainer in (None, "none") else 5


def keepaway_kernels(device: str, trainer: str | None) -> str:
    """``cycle`` on the CPU (the browser trainer's view steps it one cycle per call), ``torch`` elsewhere.
    ``trainer`` is kept in the interpolation so that saved configs that name it still resolve."""
    return "cycle" if str(device) == "cpu" else "torch"


def adaptive_prior_count(domain: str) -> float:
    """Episodes' worth of the bandit's prior for the highest weight in ``domain``."""
    return PRIOR_EPISODES.get(domain, 4.0)


def adaptive_arms(domain: str) -> ListConfig:
    """The weights the adaptive weight's bandit chooses among in ``domain`` (a config list, so that
    ``--resolve`` can write it in place)."""
    return OmegaConf.create(list(ARMS.get(domain, DEFAULT_ARMS)))


def run_dir(resume: str | None, new: str) -> str:
    """``new`` (or the first of ``new_2``, ``new_3``... that no run holds) for a new run;
    ``<resume>/resume-logs/<now>`` for a resumed one."""
    if resume not in (None, "", "null"):
        return f"{resume}/resume-logs/{time.strftime('%Y-%m-%d_%H-%M-%S')}"
    name, k = new, 1
    while Path(name).exists():
        k += 1
        name = f"{new}_{k}"
    return name


def register() -> None:
    """Register the resolvers (idempotent)."""
    for name, fn in (
        ("implied_trainer", implied_trainer),
        ("decision_period", decision_period),
        ("keepaway_kernels", keepaway_kernels),
        ("adaptive_prior_count", adaptive_prior_count),
        ("adaptive_arms", adaptive_arms),
    ):
        if not OmegaConf.has_resolver(name):
            OmegaConf.register_new_resolver(name, fn)
    if not OmegaConf.has_resolver("run_dir"):  # cached: a run's directory is fixed once it is named
        OmegaConf.register_new_resolver("run_dir", run_dir, use_cache=True)


register()
