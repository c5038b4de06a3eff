"""One learner per module, each a :class:`~hfrl_torch.experiment.run.Learner` that ``train.py`` runs."""
