"""FeedbackFusion, TorchRL's transform checklist: standalone on hand-made data, inside Compose, inside the
batched TetrisEnv with partial resets, check_env_specs, offline on stored data; plus its checkpoint state.

``TransformedEnv(TetrisEnv(...), ...)`` needs TorchRL's ``ActionMask`` for random actions: the transformed
env's action spec is a copy whose mask the env does not update, so ``check_env_specs`` runs with
``Compose(ActionMask(), FeedbackFusion(...))``.
"""

from __future__ import annotations

import math

import pytest
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.envs import ActionMask, Compose, SerialEnv, TransformedEnv
from torchrl.envs.transforms import Transform
from torchrl.envs.utils import check_env_specs

from hfrl_torch import keys
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.fusion import HUMAN_REWARD_ESTIMATE, AnnealedWeight, FeedbackFusion, Fusion, TrustWeight

EST = HUMAN_REWARD_ESTIMATE


def _step_data(reward, estimate=None, done=None, feedback=None) -> TensorDict:
    b = len(reward)
    root = {} if estimate is None else {EST: torch.tensor(estimate).reshape(b, 1)}
    nxt = {
        keys.REWARD: torch.tensor(reward).reshape(b, 1),
        keys.DONE: torch.tensor([False] * b if done is None else done).reshape(b, 1),
    }
    if feedback is not None:
        nxt[keys.FEEDBACK] = torch.tensor(feedback).reshape(b, 1)
    return TensorDict({**root, "next": TensorDict(nxt, [b])}, [b])


def _step(t: FeedbackFusion, td: TensorDict) -> TensorDictBase:
    return t._step(td, td["next"])


# ---------------------------------------------------------------- standalone


@pytest.mark.parametrize(
    ("scheme", "w", "expected"),
    [
        ("none", 0.5, [1.0, 0.0, 4.0]),
        ("human_only", 0.5, [1.0, -2.0, 0.5]),
        ("linear", 0.5, [1.5, -1.0, 4.25]),
        ("reward_shaping", 0.5, [1.5, -1.0, 4.25]),
        # R (1 + sign(H) |H|^2): 1 * 2, 0, 4 * 1.25
        ("exponential", 2.0, [2.0, 0.0, 5.0]),
        # R (1 + sign(H) |H|^0.5): 1 * 2, 0, 4 (1 + sqrt 0.5)
        ("exponential", 0.5, [2.0, 0.0, 4.0 * (1.0 + math.sqrt(0.5))]),
    ],
)
def test_standalone_step_by_hand(scheme, w, expected):
    t = FeedbackFusion(scheme, w)
    out = _step(t, _step_data([1.0, 0.0, 4.0], estimate=[1.0, -2.0, 0.5]))
    assert out[keys.REWARD].shape == (3, 1)
    assert out[keys.REWARD].flatten().tolist() == pytest.approx(expected, abs=1e-6)
    assert out[keys.ENV_REWARD].flatten().tolist() == [1.0, 0.0, 4.0]
    # the estimate is consumed: next holds the default, so a stale value is never fused again
    assert out[EST].flatten().tolist() == [0.0, 0.0, 0.0]


def test_standalone_absent_estimate_reads_as_zero():
    out = _step(FeedbackFusion("linear", 3.0), _step_data([1.0, 2.0]))
    assert out[keys.REWARD].flatten().tolist() == [1.0, 2.0]
    out = _step(FeedbackFusion("human_only"), _step_data([1.0, 2.0]))
    assert out[keys.REWARD].flatten().tolist() == [0.0, 0.0]


def test_standalone_raw_feedback_and_both_sources():
    data = dict(reward=[1.0, 1.0, 1.0], estimate=[0.5, 0.5, 0.5], feedback=[1.0, 0.0, -1.0])
    only_feedback = FeedbackFusion("linear", 2.0, estimate_key=None, feedback_key=keys.FEEDBACK)
    assert _step(only_feedback, _step_data(**data))[keys.REWARD].flatten().tolist() == [3.0, 1.0, -1.0]
    # both: the person's own reward where given, H^ elsewhere
    both = FeedbackFusion("linear", 2.0, feedback_key=keys.FEEDBACK)
    assert _step(both, _step_data(**data))[keys.REWARD].flatten().tolist() == [3.0, 2.0, -1.0]
    with pytest.raises(KeyError, match="human_feedback"):
        _step(both, _step_data([1.0], estimate=[0.5]))


def test_standalone_episode_count_and_annealed_weight_with_partial_resets():
    t = FeedbackFusion("reward_shaping", AnnealedWeight(1.0, factor=0.5))
    t._reset(TensorDict({}, [3]), TensorDict({}, [3]))
    assert t.episodes.tolist() == [0, 0, 0]
    # board 1 ends its episode: its own step still uses episode 0's weight
    out = _step(t, _step_data([0.0, 0.0, 0.0], estimate=[1.0, 1.0, 1.0], done=[False, True, False]))
    assert out[keys.REWARD].flatten().tolist() == [1.0, 1.0, 1.0]
    assert t.episodes.tolist() == [0, 1, 0]
    # stepping a finished board again before its reset does not count another episode
    _step(t, _step_data([0.0, 0.0, 0.0], done=[False, True, False]))
    assert t.episodes.tolist() == [0, 1, 0]
    t._reset(TensorDict({keys.RESET: torch.tensor([[False], [True], [False]])}, [3]), TensorDict({}, [3]))
    out = _step(t, _step_data([0.0, 0.0, 0.0], estimate=[1.0, 1.0, 1.0], done=[True, True, False]))
    assert out[keys.REWARD].flatten().tolist() == [1.0, 0.5, 1.0]
    assert t.episodes.tolist() == [1, 2, 0]
    # a reset that flags only board 0 leaves board 1 finished
    t._reset(TensorDict({keys.RESET: torch.tensor([[True], [False], [False]])}, [3]), TensorDict({}, [3]))
    _step(t, _step_data([0.0, 0.0, 0.0], done=[True, True, True]))
    assert t.episodes.tolist() == [2, 2, 1]


def test_reset_writes_zero_defaults():
    t = FeedbackFusion("linear")
    out = t._reset(TensorDict({}, [2]), TensorDict({}, [2]))
    assert out[EST].tolist() == [[0.0], [0.0]] and out[keys.ENV_REWARD].tolist() == [[0.0], [0.0]]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"scheme": "control_sharing"}, "FusionModule"),
        ({"scheme": "bogus"}, "allowed"),
        ({"scheme": "linear", "estimate_key": None}, "where to read H"),
    ],
)
def test_rejects_bad_configuration(kwargs, match):
    with pytest.raises(ValueError, match=match):
        FeedbackFusion(**kwargs)


def test_state_round_trip_keeps_counters_and_schedule():
    t = FeedbackFusion(Fusion("none", "linear", TrustWeight.from_initial(0.5, learners=2)))
    t._reset(TensorDict({}, [2]), TensorDict({}, [2]))
    _step(t, _step_data([0.0, 0.0], done=[True, False]))
    t.schedule.end_episode([4.0, 4.0], [1.0, 1.0])
    fresh = FeedbackFusion(Fusion("none", "linear", TrustWeight.from_initial(0.5, learners=2)))
    fresh.load_state_dict(t.state_dict())
    assert fresh.episodes.tolist() == [1, 0]
    assert fresh.schedule.value().tolist() == pytest.approx([0.75, 0.75])
    _step(fresh, _step_data([0.0, 0.0], done=[True, False]))
    assert fresh.episodes.tolist() == [1, 0]  # board 0 was still finished


# ---------------------------------------------------------------- inside an env

RULES = TetrisRules(6, 6)


def _random_policy(seed: int):
    g = torch.Generator().manual_seed(seed)

    def policy(td: TensorDictBase) -> TensorDictBase:
        mask = td[keys.ACTION_MASK]
        action = torch.multinomial(mask.flatten(0, -2).float(), 1, generator=g).reshape(mask.shape[:-1])
        td.set(keys.ACTION, action)
        td.set(EST, ((action % 5).to(torch.float32) - 2.0).unsqueeze(-1) / 2.0)
        return td

    return policy


class _OracleFeedback(Transform):
    """A stand-in feedback channel: +1 when the placement cleared lines, else -1 every third board."""

    def __init__(self) -> None:
        super().__init__(in_keys=[keys.REWARD], out_keys=[keys.FEEDBACK])

    def _step(self, tensordict: TensorDictBase, next_tensordict: TensorDictBase) -> TensorDictBase:
        r = next_tensordict[keys.REWARD]
        b = torch.arange(r.shape[0]).unsqueeze(-1)
        fb = torch.where(r > 0, 1.0, torch.where(b % 3 == 0, -1.0, 0.0))
        return next_tensordict.set(keys.FEEDBACK, fb)

    def _reset(self, tensordict: TensorDictBase, tensordict_reset: TensorDictBase) -> TensorDictBase:
        return tensordict_reset.set(keys.FEEDBACK, torch.zeros(*tensordict_reset.batch_size, 1))

    def transform_observation_spec(self, observation_spec):
        observation_spec[keys.FEEDBACK] = self.parent.full_reward_spec[keys.REWARD].clone()
        return observation_spec


@pytest.mark.parametrize("scheme", ["none", "human_only", "linear", "exponential", "reward_shaping"])
def test_check_env_specs(scheme):
    env = TransformedEnv(TetrisEnv(batch=3, rules=RULES), Compose(ActionMask(), FeedbackFusion(scheme, 0.5)))
    check_env_specs(env, seed=0)
    assert EST in env.state_spec and keys.ENV_REWARD in env.observation_spec
    assert env.reward_keys == [keys.REWARD]


def test_check_env_specs_with_a_feedback_transform_in_compose():
    fusion = FeedbackFusion("linear", 0.5, feedback_key=keys.FEEDBACK)
    env = TransformedEnv(TetrisEnv(batch=3, rules=RULES), Compose(ActionMask(), _OracleFeedback(), fusion))
    check_env_specs(env, seed=0)


def test_inside_compose_fuses_the_feedback_written_before_it():
    fusion = FeedbackFusion("reward_shaping", 2.0, estimate_key=None, feedback_key=keys.FEEDBACK)
    env = TransformedEnv(TetrisEnv(batch=6, rules=RULES, seed=3), Compose(_OracleFeedback(), fusion))
    td = env.rollout(40, _random_policy(0), break_when_any_done=False)
    nxt = td["next"]
    assert torch.equal(nxt[keys.REWARD], nxt[keys.ENV_REWARD] + 2.0 * nxt[keys.FEEDBACK])
    assert (nxt[keys.FEEDBACK] != 0).any() and (nxt[keys.ENV_REWARD] > 0).any()


def test_batched_env_partial_resets_count_episodes_per_board():
    """Same seed and actions in the plain env and the transformed one: env_reward is the env's reward, the
    fused reward uses each board's own annealed weight, and only reset boards advance their episode."""
    b = 5
    fusion = FeedbackFusion("reward_shaping", AnnealedWeight(1.0, factor=0.5))
    env = TransformedEnv(TetrisEnv(batch=b, rules=RULES, seed=11), fusion)
    plain = TetrisEnv(batch=b, rules=RULES, seed=11)
    policy = _random_policy(1)
    td, ref = env.reset(), plain.reset()
    expected = torch.zeros(b, dtype=torch.int64)
    advanced = set()
    for _ in range(60):
        td = policy(td)
        ref[keys.ACTION] = td[keys.ACTION]
        out, ref_out = env.step(td)["next"], plain.step(ref)["next"]
        r = ref_out[keys.REWARD]
        assert torch.equal(out[keys.ENV_REWARD], r)
        weight = (0.5 ** expected.to(torch.float32)).unsqueeze(-1)
        assert torch.allclose(out[keys.REWARD], r + weight * td[EST])
        done = out[keys.DONE].squeeze(-1)
        expected += done.to(torch.int64)
        assert fusion.episodes.tolist() == expected.tolist()
        if done.any():
            advanced.add(tuple(done.tolist()))
            flags = TensorDict({keys.RESET: done.unsqueeze(-1)}, [b])
            td = env.reset(out.clone().update(flags))
            # without game_seed, which TetrisEnv's reset would take as games to replay
            ref = plain.reset(ref_out.exclude(keys.GAME_SEED).update(flags))
            assert fusion.episodes.tolist() == expected.tolist()  # resets do not count; done flags do
            assert td[EST].flatten().tolist() == [0.0] * b
        else:
            td, ref = out, ref_out
    assert any(0 < sum(flags) < b for flags in advanced), "no partial reset happened"
    assert expected.min() >= 1 and expected.max() > expected.min()


def test_offline_on_stored_rollout_reproduces_the_online_rewards():
    def make() -> FeedbackFusion:
        return FeedbackFusion("linear", AnnealedWeight(2.0, factor=0.7))

    env = TransformedEnv(TetrisEnv(batch=4, rules=RULES, seed=5), make())
    online = env.rollout(50, _random_policy(2), break_when_any_done=False)
    assert online["next", keys.DONE].any(-2).all(), "every board should finish a game"
    # the same data as the plain env stored it: reward = the env's, no env_reward
    stored = online.clone()
    stored["next", keys.REWARD] = stored["next", keys.ENV_REWARD]
    del stored["next", keys.ENV_REWARD]
    assert not torch.equal(stored["next", keys.REWARD], online["next", keys.REWARD])
    offline = make()(stored)
    assert torch.equal(offline["next", keys.REWARD], online["next", keys.REWARD])
    assert torch.equal(offline["next", keys.ENV_REWARD], online["next", keys.ENV_REWARD])
    # applied again, it reads env_reward and gives the same result
    again = make()(online.clone())
    assert torch.equal(again["next", keys.REWARD], online["next", keys.REWARD])


def test_offline_rejects_data_without_a_trailing_time_dimension():
    data = _step_data([1.0, 2.0])
    with pytest.raises(ValueError, match="time"):
        FeedbackFusion("linear")(data[0])
    data = TensorDict({"next": _step_data([1.0, 2.0])["next"].unsqueeze(0)}, [1, 2], names=["time", None])
    with pytest.raises(ValueError, match="time as the last"):
        FeedbackFusion("linear")(data)


def test_on_a_serial_env_with_two_batch_dimensions():
    """Boards [2 workers, 2 boards]: episodes are counted per board over both dimensions.

    ``ActionMask`` does not follow partial resets of a ``SerialEnv`` of masked envs (TorchRL's random
    actions then pick invalid placements, with or without this transform), so the rollout uses a policy
    that reads the mask from the data.
    """

    def make_env(fusion: FeedbackFusion, *transforms: Transform) -> TransformedEnv:
        serial = SerialEnv(2, lambda: TetrisEnv(batch=2, rules=RULES, seed=4))
        return TransformedEnv(serial, Compose(*transforms, fusion))

    def make() -> FeedbackFusion:
        return FeedbackFusion("reward_shaping", AnnealedWeight(1.0, factor=0.5))

    check_env_specs(make_env(make(), ActionMask()), seed=0)
    fusion = make()
    td = make_env(fusion).rollout(40, _random_policy(3), break_when_any_done=False)
    ended = td["next", keys.DONE].squeeze(-1).sum(-1)
    assert fusion.episodes.shape == (2, 2) and torch.equal(fusion.episodes, ended)
    assert (ended > 0).all()
    offline = make()(td.clone())
    assert torch.equal(offline["next", keys.REWARD], td["next", keys.REWARD])
    assert not torch.equal(td["next", keys.REWARD], td["next", keys.ENV_REWARD])
