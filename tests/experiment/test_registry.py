"""The registries train.py and evaluate.py dispatch through: domains and learners found by name, added from
outside the package, and refused with one line naming what is allowed."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from hfrl_torch.common.errors import ConfigError
from hfrl_torch.experiment import registry
from hfrl_torch.experiment.config import validate_evaluate, validate_train
from hfrl_torch.experiment.evaluate import evaluate
from hfrl_torch.experiment.learners.tetris_cem import CEMLearner
from hfrl_torch.experiment.learners.tetris_pg import PolicyGradientLearner
from hfrl_torch.experiment.run import Learner


def test_an_agent_on_a_domain_it_does_not_learn_names_the_ones_that_do():
    with pytest.raises(ConfigError) as info:
        registry.learner_for("cem", "keepaway")
    assert str(info.value) == (
        "domain=keepaway agent=cem is invalid: agent=cem learns tetris; domain=keepaway is learned by "
        "agent=dqn, agent=sarsa (e.g. domain=keepaway agent=sarsa)"
    )
    assert registry.learner_for("dqn", "keepaway").domain == "keepaway"
    assert registry.learner_for("cem") is CEMLearner


def test_the_weights_evidence_and_scale_are_the_learners_own():
    assert registry.evidence_givers() == {"compared": ["cem"], "searched": ["cem"]}
    assert PolicyGradientLearner.default_scaling == "none" and CEMLearner.default_scaling == "decision"
    assert registry.learner_for("sarsa", "keepaway").default_scaling == "spread"


def _toy_cfg(**values):
    base = {
        "seed": 0,
        "threads": 1,
        "device": "cpu",
        "domain": {"name": "toy", "size": 3},
        "agent": {"name": "toy_agent"},
        "fusion": {"name": "none", "weight": "trust"},
        "trainer": {"name": "none"},
        "logger": {"backend": "none"},
        "policy": None,
    }
    return OmegaConf.create({**base, **values})


def test_a_domain_and_its_learner_registered_from_outside_are_checked_and_evaluated(capsys):
    """What a user's own package does: register a domain and a learner, then train.py's checks and
    evaluate.py's dispatch find them, with no change to experiment/."""
    seen = []

    def check(cfg):
        if cfg.domain.size < 1:
            raise ConfigError(f"domain.size={cfg.domain.size} is invalid: must be >= 1")
        seen.append("domain")

    class ToyLearner(Learner):
        domain, agent = "toy", "toy_agent"

        @classmethod
        def check(cls, cfg):
            seen.append("learner")

    toy = registry.Domain(
        "toy", check, check, lambda cfg: {"score": 1.5}, lambda r: f"toy: {r['score']}", "toy_agent"
    )
    registry.register_domain(toy)
    registry.register_learner(ToyLearner)
    try:
        validate_train(_toy_cfg())
        assert seen == ["domain", "learner"]
        with pytest.raises(ConfigError, match=r"domain.size=0 is invalid"):
            validate_train(_toy_cfg(domain={"name": "toy", "size": 0}))
        validate_evaluate(_toy_cfg())
        assert evaluate(_toy_cfg()) == {"score": 1.5}
        assert capsys.readouterr().out.splitlines() == ["toy: 1.5", '{"score": 1.5}']
        with pytest.raises(ConfigError, match=r"agent=cem learns tetris"):
            validate_train(_toy_cfg(agent={"name": "cem"}))
        with pytest.raises(ValueError, match="registered already"):
            registry.register_domain(registry.Domain("toy", check, check, print, str, "other"))
    finally:
        registry.DOMAINS.pop("toy")
        registry.LEARNERS.pop(("toy", "toy_agent"))
    with pytest.raises(ConfigError, match=r"domain.name='toy' is invalid; allowed: tetris, keepaway"):
        validate_evaluate(_toy_cfg())
