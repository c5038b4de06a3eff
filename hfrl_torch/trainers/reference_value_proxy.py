"""The value proxy on any task: feedback from a reference's action values, as Tetris's value proxy gives it
from the change of Dellacherie's board value.

A SIMULATED trainer, not a person. ``trainer.reference`` names the values: a saved ``domain=gym`` policy (a
run directory or checkpoint: its Q, or its fused Q and H^, or a TAMER run's H^) or a ``module:callable``
returning action values ``[B, A]``. The feedback on an action is the sign (``mode="sign"``) or a scaled amount
(``"scaled"``) of its advantage, its value less the mean of the task's actions' values in that state: +1
for a better than average action, -1 for a worse one, none where all actions are worth the same. Unlike the
oracle (right or wrong, with L and C), it says how much better, and it is silent where the values do not
tell the actions apart. An after-state value is not known when a gym step is judged, which is why the
action's value stands in for Tetris's V(after) - V(before).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase

from hfrl_torch import keys
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.trainers.value_proxy import ValueProxyTrainer

__all__ = ["ReferenceValueProxy", "action_values"]

Values = Callable[[torch.Tensor], object]  # observations [B, ...] -> action values [B, A]


def action_values(values: Values, obs: torch.Tensor, actions: int) -> torch.Tensor:
    """The reference's finite action values ``[B, A]`` (float64) in ``obs``; ``ValueError`` with one line if
    it returns anything else (actions, a wrong shape, values that are not finite)."""
    b = obs.shape[0]
    try:
        out = torch.as_tensor(values(obs))
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"failed on observations of shape {list(obs.shape)} ({exc})") from None
    if out.shape != torch.Size([b, actions]) or not out.is_floating_point():
        raise ValueError(
            f"returned {out.dtype} of shape {list(out.shape)} for {b} observations; the value proxy needs "
            f"float action values [{b}, {actions}]"
        )
    q = out.detach().to(torch.float64).cpu()
    if not bool(torch.isfinite(q).all()):
        raise ValueError("returned action values that are not finite")
    return q


class ReferenceValueProxy(ValueProxyTrainer):
    """Feedback from the advantage of the action taken under a reference's action values (module docstring;
    source ``"simulated:value_proxy"``): Tetris's value proxy with the advantage as its change of value.

    :param values: the reference's action values of an observation batch.
    :param actions: A, the task's number of actions.
    :param mode: ``"sign"`` gives +1 / -1; ``"scaled"`` gives ``scale * advantage``, clipped to the largest
        value a ``FeedbackEvent`` holds.
    :param scale: the factor of ``"scaled"``.
    :param reaction: seconds between the step and the event (> 0).
    :param log: feedback log every event is appended to.
    """

    def __init__(
        self,
        values: Values,
        actions: int,
        mode: str = "sign",
        scale: float = 1.0,
        reaction: float = 0.3,
        log: FeedbackLog | None = None,
    ) -> None:
        super().__init__(mode, scale, reaction=reaction, log=log)
        self.values, self.actions = values, int(actions)

    def value_change(
        self, obs: TensorDictBase, action: torch.Tensor, active: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The taken action's value less the mean of the actions' values, per board [B] (float64)."""
        q = action_values(self.values, obs.get(keys.OBSERVATION), self.actions)
        taken = q.gather(-1, action.reshape(-1, 1).to(torch.int64).cpu()).squeeze(-1)
        return taken - q.mean(-1)
