"""Learning agents, one package per algorithm."""
