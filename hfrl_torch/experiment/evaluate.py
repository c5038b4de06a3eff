"""What ``evaluate.py`` does: play a policy on its domain (the domain's own evaluation, found through the
registry) or report on runs (``runs=``: run and multirun directories, or one study directory, whose
participants are compared between subjects), and print the summary with one JSON line."""

from __future__ import annotations

import json

from omegaconf import DictConfig

from hfrl_torch.experiment.aggregate import aggregate
from hfrl_torch.experiment.cli import checked
from hfrl_torch.experiment.config import validate_evaluate
from hfrl_torch.experiment.registry import domain_for
from hfrl_torch.experiment.study_report import aggregate_study, study_dir_of


def evaluate(cfg: DictConfig) -> dict[str, object]:
    """Evaluate and print the summary, then one JSON line on stdout."""
    if not checked():
        validate_evaluate(cfg)
    if cfg.get("runs") is not None:
        study = study_dir_of(cfg)
        result = aggregate(cfg) if study is None else aggregate_study(cfg, study)
        print(json.dumps(result), flush=True)
        return result
    domain = domain_for(cfg)
    result = domain.evaluate(cfg)
    print(domain.summary(result))
    print(json.dumps(result), flush=True)
    return result
