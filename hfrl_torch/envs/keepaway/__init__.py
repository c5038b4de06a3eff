"""RoboCup keepaway (Stone, Sutton & Kuhlmann 2005) as a batched torch simulator, a TorchRL
environment and a Gymnasium environment ("hfrl_torch/Keepaway-v0")."""

from hfrl_torch.envs.keepaway.benchmark_policies import (
    KeeperChooser,
    play_benchmark_policy,
    play_keeper_policy,
    record_keeper_gif,
)
from hfrl_torch.envs.keepaway.env import EPISODE_END_REWARDS, STEP_CYCLES, KeepawayEnv
from hfrl_torch.envs.keepaway.gym_env import ENV_ID, KeepawayGymEnv, register_keepaway
from hfrl_torch.envs.keepaway.params import (
    PRESETS,
    TASKS,
    KeepawayConfig,
    PhysicsParams,
    physics_preset,
    saved_config,
)
from hfrl_torch.envs.keepaway.policies import (
    POLICIES,
    hand_coded_actions,
    hold_actions,
    make_benchmark_policy,
    random_actions,
)
from hfrl_torch.envs.keepaway.render import record_episode_gif, render_rgb, write_gif
from hfrl_torch.envs.keepaway.simulator import CycleOutcome, Decision, KeepawaySimulator, KeepawayState
from hfrl_torch.envs.keepaway.state_vars import keeper_state_variables
from hfrl_torch.envs.keepaway.transitions import keeper_transitions

__all__ = [
    "ENV_ID",
    "EPISODE_END_REWARDS",
    "POLICIES",
    "PRESETS",
    "STEP_CYCLES",
    "TASKS",
    "CycleOutcome",
    "Decision",
    "KeepawayConfig",
    "KeepawayEnv",
    "KeepawayGymEnv",
    "KeepawaySimulator",
    "KeepawayState",
    "KeeperChooser",
    "PhysicsParams",
    "hand_coded_actions",
    "hold_actions",
    "keeper_state_variables",
    "keeper_transitions",
    "make_benchmark_policy",
    "physics_preset",
    "play_benchmark_policy",
    "play_keeper_policy",
    "random_actions",
    "record_episode_gif",
    "record_keeper_gif",
    "register_keepaway",
    "render_rgb",
    "saved_config",
    "write_gif",
]
