"""The page's plain sentences on the numbers it shows: what the weight on the person's feedback is.

The number is the fusion weight on H^ (the agent's model of the person's feedback), whatever sets it:
the trust factor (thesis eq. 4.4: agreement between H^ and the environment's value, weighted by
performance), a fixed number, Knox & Stone's annealing, or an estimate from the returns (a bandit, CE's
paired comparison or its search). Each kind of weight words itself (``WeightSchedule.describe``); none of
them measures the person, and the sentence says so.
"""

from __future__ import annotations

from collections.abc import Callable

WEIGHT_NAME = "Weight on your feedback"

# what the weight w does in each rule, in words (H^: what the agent learned from your presses)
_ROLE = {
    "linear": "the agent picks by its own value plus w times what it learned from your presses",
    "exponential": "the agent picks by its own value times (1 + what it learned from you, to the power w)",
    "action_biasing": "the agent picks by its own value plus w times what it learned from your presses",
    "control_sharing": "the agent follows what it learned from your presses with probability w (at most 1)",
    "reward_shaping": "the agent learns from the game's reward plus w times what it learned from you",
}


# what an episode is judged by, and what it is called, on each domain's page
_SCORE = {
    "tetris": "the lines of its games",
    "keepaway": "how long the keepers kept the ball",
    "gym": "the return of its episodes",
}
_EPISODE = {"tetris": "game", "keepaway": "episode", "gym": "episode"}


def weight_sentence(scheme: str, describe: Callable[[str, str], str], domain: str) -> str:
    """What the weight on H^ of fusion ``scheme`` is: one or two plain sentences for the page. ``describe``
    is the fusion's own account of what sets the weight (``Fusion.describe_weight``), given what an episode
    is judged by and called on ``domain``'s page."""
    if scheme == "none":
        return "This run does not use your presses to choose moves (fusion=none): they are only saved."
    if scheme == "human_only":
        return "The agent acts on what it learned from your presses alone (fusion=human_only): no weight."
    role = _ROLE.get(scheme, f"the fusion rule {scheme} uses w")
    return f"The weight w: {role}. {describe(_SCORE[domain], _EPISODE[domain])}"
