"""Evaluate a policy: ``python evaluate.py policy=<run dir|checkpoint|dellacherie|random> games=30``."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hfrl_torch.app import check_overrides, guarded
from hfrl_torch.experiment.evaluate import evaluate


@hydra.main(version_base=None, config_path="conf", config_name="evaluate")
@guarded
def main(cfg: DictConfig) -> None:
    evaluate(cfg)


if __name__ == "__main__":
    check_overrides(sys.argv[1:], "evaluate")
    main()
