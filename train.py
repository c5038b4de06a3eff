"""Train an agent: ``python train.py domain=tetris agent=cem`` (see ``conf/train.yaml``)."""

from __future__ import annotations

import sys

import hydra
from omegaconf import DictConfig

from hfrl_torch.app import check_overrides, guarded, implied_overrides, resume_log_dir
from hfrl_torch.experiment.factories import validate_train_config
from hfrl_torch.experiment.train import train


@hydra.main(version_base=None, config_path="conf", config_name="train")
@guarded
def main(cfg: DictConfig) -> float | None:
    return train(cfg).score  # the objective of a sweeper such as Optuna


if __name__ == "__main__":
    implied = implied_overrides(sys.argv[1:])
    if implied:
        print(f"Implied by the command line: {' '.join(implied)}", file=sys.stderr)
    sys.argv += implied
    check_overrides(sys.argv[1:], "train", validate_train_config)
    sys.argv += resume_log_dir(sys.argv[1:])
    main()
