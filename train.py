"""Train an agent: ``python train.py domain=tetris agent=cem`` (see ``conf/train.yaml``)."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hfrl_torch.experiment.cli import guarded, precheck
from hfrl_torch.experiment.config import validate_train
from hfrl_torch.experiment.train import train


@hydra.main(version_base=None, config_path="conf", config_name="train")
@guarded
def main(cfg: DictConfig) -> float | None:
    return train(cfg).score  # the objective of a sweeper such as Optuna


if __name__ == "__main__":
    precheck(sys.argv[1:], "train", validate_train)
    main()
