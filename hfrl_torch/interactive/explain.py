"""The page's plain sentences on the numbers it shows: what the weight on the person's feedback is.

The number is the fusion weight on H^ (the agent's model of the person's feedback), whatever sets it:
the trust factor (thesis eq. 4.4: agreement between H^ and the environment's value, weighted by
performance), a fixed number, Knox & Stone's annealing, or ``fusion.weight=adaptive`` (CE's own search, or
a bandit judged on episode returns). None of these measures the person, and the sentence says so.
"""

from __future__ import annotations

WEIGHT_NAME = "Weight on your feedback"

# what the weight w does in each rule, in words (H^: what the agent learned from your presses)
_ROLE = {
    "linear": "the agent picks by its own value plus w times what it learned from your presses",
    "exponential": "the agent picks by its own value times (1 + what it learned from you, to the power w)",
    "action_biasing": "the agent picks by its own value plus w times what it learned from your presses",
    "control_sharing": "the agent follows what it learned from your presses with probability w (at most 1)",
    "reward_shaping": "the agent learns from the game's reward plus w times what it learned from you",
}


def weight_sentence(
    scheme: str,
    kind: str,
    domain: str,
    value: float | None = None,
    factor: float | None = None,
    arms: list[float] | None = None,
) -> str:
    """What the weight on H^ of fusion ``scheme`` is, set as ``kind`` (``constant``, ``annealed``, ``trust``,
    ``search``, ``bandit``): one or two plain sentences for the page."""
    if scheme == "none":
        return "This run does not use your presses to choose moves (fusion=none): they are only saved."
    if scheme == "human_only":
        return "The agent acts on what it learned from your presses alone (fusion=human_only): no weight."
    role = _ROLE.get(scheme, f"the fusion rule {scheme} uses w")
    score = "the lines of its games" if domain == "tetris" else "how long the keepers kept the ball"
    if kind == "trust":
        how = (
            "w is the trust factor (thesis eq. 4.4): how often the move the agent's model of your presses "
            f"rates best matches the move its game-trained value rates best, weighted by {score}. It "
            "measures that agreement, not you, and changes after every game with or without presses."
        )
    elif kind == "annealed":
        how = (
            f"w started at {value:g} and shrinks by a factor {factor:g} after every game "
            "(Knox & Stone's annealing), whatever you press."
        )
    elif kind == "search":
        how = (
            "w is searched by the cross-entropy method as one more setting (fusion.weight=adaptive): each "
            "practice round keeps the weights whose games scored best. It measures how much your "
            "teaching helps the score, not you."
        )
    elif kind == "bandit":
        choices = "" if not arms else f" among {', '.join(f'{a:g}' for a in arms)}"
        how = (
            f"w is chosen{choices} by a bandit (fusion.weight=adaptive) that favours the weight whose recent "
            f"episodes went best, judged on {score}. It measures how much your teaching helps, not you."
        )
    else:
        shown = "" if value is None else f"={value:g}"
        how = f"w is fixed for this run (fusion.weight{shown}): it does not change."
    return f"The weight w: {role}. {how}"
