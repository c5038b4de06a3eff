"""The experiment runner between the agents and ``train.py`` / ``evaluate.py``."""
