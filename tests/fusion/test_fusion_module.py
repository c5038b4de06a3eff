"""FusionModule on TorchRL's conventions: keys named like ``QValueModule``'s, one-hot or index actions (or as
the action spec says), batched and unbatched tensordicts, and in a policy on ``GymEnv("CartPole-v1")``
alone and in a ``SerialEnv``."""

from __future__ import annotations

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule, TensorDictSequential
from torchrl.data import Bounded, Categorical, Composite, OneHot
from torchrl.envs import GymEnv, SerialEnv

from hfrl_torch import keys
from hfrl_torch.fusion import ConstantWeight, Fusion, FusionModule, TrustWeight
from hfrl_torch.fusion.fusion import changed_by_teaching

R = torch.tensor([[1.0, 2.0, 0.0], [3.0, 0.0, 1.0]])
H = torch.tensor([[2.0, 0.0, 0.0], [0.0, 0.0, 4.0]])


def _fusion(w: float = 1.0) -> Fusion:
    return Fusion("linear", "none", ConstantWeight(w))


def test_default_keys_and_index_actions_as_before():
    td = TensorDict({keys.ENV_VALUES: R, keys.HUMAN_VALUES: H}, [2])
    FusionModule(_fusion(), "greedy")(td)
    assert td[keys.FUSED_VALUES].tolist() == [[3.0, 2.0, 0.0], [3.0, 0.0, 5.0]]
    assert td[keys.ACTION].tolist() == [0, 2] and td[keys.FUSION_WEIGHT].tolist() == [1.0, 1.0]


def test_named_keys_are_read_and_written_where_asked():
    module = FusionModule(
        _fusion(0.5),
        "greedy",
        env_values_key="action_value",
        human_values_key=("human", "values"),
        action_mask_key="legal",
        fused_values_key=("fused", "values"),
        fusion_weight_key="w",
        action_key=("agent", "act"),
    )
    assert module.in_keys == ["action_value", ("human", "values"), "legal"]
    assert module.out_keys == [("fused", "values"), "w", ("agent", "act")]
    legal = torch.tensor([[False, True, True], [True, True, True]])
    td = TensorDict({"action_value": R, "human": {"values": H}, "legal": legal}, [2])
    module(td)
    assert td["fused", "values"].tolist() == [[2.0, 2.0, 0.0], [3.0, 0.0, 3.0]]
    assert td["agent", "act"].tolist() == [1, 0]  # action 0 of row 0 is masked; the first of a tie
    assert td["w"].tolist() == [0.5, 0.5]
    for own in (keys.FUSED_VALUES, keys.FUSION_WEIGHT, keys.ACTION):
        assert own not in td


def test_one_hot_actions_by_name_and_by_spec():
    td = TensorDict({keys.ENV_VALUES: R, keys.HUMAN_VALUES: H}, [2])
    FusionModule(_fusion(), "greedy", action_space="one-hot")(td)
    assert td[keys.ACTION].tolist() == [[1, 0, 0], [0, 0, 1]] and td[keys.ACTION].dtype == torch.int64
    spec = Composite({keys.ACTION: OneHot(3, shape=(2, 3), dtype=torch.bool)}, shape=(2,))
    td = TensorDict({keys.ENV_VALUES: R, keys.HUMAN_VALUES: H}, [2])
    FusionModule(_fusion(), "greedy", spec=spec)(td)
    assert td[keys.ACTION].dtype == torch.bool and spec[keys.ACTION].is_in(td[keys.ACTION])
    td = TensorDict({keys.ENV_VALUES: R, keys.HUMAN_VALUES: H}, [2])
    FusionModule(_fusion(), "greedy", spec=Categorical(3, shape=(2,)))(td)
    assert td[keys.ACTION].tolist() == [0, 2]


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"action_space": "binary"}, "action_space='binary' is invalid; allowed: categorical, one-hot"),
        ({"action_space": "categorical", "spec": OneHot(3)}, "contradicts its spec, which is one-hot"),
        (
            {"spec": Bounded(-1.0, 1.0, shape=(1,))},
            "spec BoundedContinuous is invalid; allowed: OneHot, Categorical",
        ),
    ],
)
def test_bad_action_spaces_are_one_line_errors(kwargs, message):
    with pytest.raises(ValueError, match=message):
        FusionModule(_fusion(), "greedy", **kwargs)


def test_unbatched_values_fuse_like_one_row():
    td = TensorDict({keys.ENV_VALUES: R[1], keys.HUMAN_VALUES: H[1]}, [])
    FusionModule(_fusion(2.0), "greedy", action_space="one-hot")(td)
    assert td[keys.FUSED_VALUES].tolist() == [3.0, 0.0, 9.0]
    assert td[keys.FUSION_WEIGHT].shape == () and float(td[keys.FUSION_WEIGHT]) == 2.0
    assert td[keys.ACTION].tolist() == [0, 0, 1]
    td = TensorDict({keys.ENV_VALUES: R[1], keys.HUMAN_VALUES: H[1]}, [])
    FusionModule(_fusion(2.0), "greedy")(td)
    assert td[keys.ACTION].shape == () and int(td[keys.ACTION]) == 2


def test_two_batch_dimensions_keep_their_shape_and_count_every_row():
    fusion = Fusion("linear", "none", TrustWeight.from_initial(0.5))
    r, h = R.expand(3, 2, 3), H.expand(3, 2, 3)
    td = TensorDict({keys.ENV_VALUES: r, keys.HUMAN_VALUES: h}, [3, 2])
    FusionModule(fusion, "greedy")(td)
    assert td[keys.ACTION].tolist() == [[0, 0]] * 3 and td[keys.FUSION_WEIGHT].shape == (3, 2)
    # argmax R against argmax H^: 1 vs 0 and 0 vs 2, so none of the six decisions matches
    assert fusion.matches.rates().tolist() == [0.0]


# --------------------------------------------------------------- CartPole through GymEnv


class _Linear(torch.nn.Module):
    """Fixed action values from CartPole's observation: push towards where the pole leans (R), or the other
    way (H^), so that the fused choice depends on the weight."""

    def __init__(self, sign: float) -> None:
        super().__init__()
        self.sign = sign

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        lean = obs[..., 2:3] + obs[..., 3:4]
        return self.sign * torch.cat([-lean, lean], -1)


def _policy(env, fusion: Fusion, **kwargs) -> TensorDictSequential:
    q = TensorDictModule(_Linear(1.0), in_keys=["observation"], out_keys=["action_value"])
    h = TensorDictModule(_Linear(-1.0), in_keys=["observation"], out_keys=["h_values"])
    fuse = FusionModule(
        fusion, "greedy", env_values_key="action_value", human_values_key="h_values", **kwargs
    )
    return TensorDictSequential(q, h, fuse)


def _cartpole(categorical: bool) -> GymEnv:
    return GymEnv("CartPole-v1", categorical_action_encoding=categorical)


@pytest.mark.parametrize("categorical", [False, True])
@pytest.mark.parametrize("batched", [False, True])
def test_a_cartpole_rollout_with_the_module_in_the_policy(categorical, batched):
    env = SerialEnv(2, lambda: _cartpole(categorical)) if batched else _cartpole(categorical)
    env.set_seed(0)
    fusion = Fusion("linear", "none", TrustWeight.from_initial(0.5))
    policy = _policy(env, fusion, spec=env.full_action_spec)
    td = env.rollout(30, policy, break_when_any_done=False)
    lead = (2, 30) if batched else (30,)
    action = td[keys.ACTION]
    assert action.shape == ((*lead, 2) if not categorical else lead)
    assert env.full_action_spec[keys.ACTION].is_in(action[..., 0, :] if not categorical else action[..., 0])
    assert td[keys.FUSION_WEIGHT].shape == lead and bool((td[keys.FUSION_WEIGHT] == 0.5).all())
    # the fused choice is argmax of R + 0.5 H^ = 0.5 R: R's choice, every step
    index = action.argmax(-1) if not categorical else action
    assert torch.equal(index, td["action_value"].argmax(-1))
    if not batched:
        env.close()
    assert fusion.matches.rates().isnan().tolist() == [False]  # every step was counted


def test_unbatched_cartpole_with_h_deciding_follows_h():
    env = _cartpole(False)
    env.set_seed(1)
    policy = _policy(env, Fusion("human_only", "none", ConstantWeight(1.0)), action_space="one-hot")
    td = env.rollout(20, policy)
    assert torch.equal(td[keys.ACTION].argmax(-1), td["h_values"].argmax(-1))
    assert td.shape[0] < 20  # H^ pushes the way the pole leans: it falls within 20 steps
    env.close()


def test_a_move_is_said_to_be_changed_by_the_teaching_only_where_the_environment_alone_prefers_another():
    env = torch.tensor(
        [[1.0, 3.0, 2.0, 5.0], [1.0, 3.0, 3.0, 0.0], [4.0, 1.0, 0.0, 0.0]], dtype=torch.float64
    )
    mask = torch.tensor([[True, True, True, False], [True] * 4, [True] * 4])
    # the masked 5.0 is no choice, so 3.0 beats the 2.0 played; a tie is no change; R's own choice is none
    assert changed_by_teaching(env, torch.tensor([2, 2, 0]), mask).tolist() == [1, -1, -1]
    fused = torch.tensor([[0.0, 0.0, 9.0, 0.0], [0.0] * 4, [0.0, 2.0, 0.0, 1.0]])
    # with the fused values: a move they do not prefer explored, it was not the teaching's
    assert changed_by_teaching(env, torch.tensor([2, 2, 3]), mask, fused).tolist() == [1, -1, -1]
    assert changed_by_teaching(env, torch.tensor([2, 2, 1]), mask, fused).tolist() == [1, -1, 0]
