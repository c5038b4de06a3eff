"""Evaluate a policy: ``python evaluate.py policy=<run dir|checkpoint|dellacherie|random> games=30``."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hfrl_torch.experiment.cli import guarded, precheck
from hfrl_torch.experiment.config import validate_evaluate
from hfrl_torch.experiment.evaluate import evaluate


@hydra.main(version_base=None, config_path="conf", config_name="evaluate")
@guarded
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    precheck(sys.argv[1:], "evaluate", validate_evaluate)
    main()
