"""Every tensordict key the project uses, named once.

Environments write observations, rewards and done flags under these keys; the
feedback channel, fusion transforms and agents read them from here too.
"""

from __future__ import annotations

# TorchRL's own
ACTION = "action"
REWARD = "reward"
DONE = "done"
TERMINATED = "terminated"
TRUNCATED = "truncated"
RESET = "_reset"

# observations
ACTION_MASK = "action_mask"
AFTERSTATE_FEATURES = "afterstate_features"  # [B, A, F] features of every placement's afterstate
AFTERSTATE_TERMINAL = "afterstate_terminal"  # [B, A] the placement would end the game
STATE_FEATURES = "state_features"  # [B, F] features of the board before the placement
BOARD = "board"
PIECE = "piece"
NEXT_PIECE = "next_piece"
LINES = "lines"  # lines cleared so far in the current game
PIECES_PLACED = "pieces_placed"
GAME_SEED = "game_seed"  # observation: the seed of each board's current game
RESET_GAME_SEED = "reset_game_seed"  # reset input: play these seeds (replay given games)

# keepaway
OBSERVATION = "observation"  # deciding keeper's state variables
KEEPER = "keeper"  # index of the deciding keeper
EPISODE_CYCLES = "episode_cycles"
END_CAUSE = "end_cause"  # 0 = running, 1 = out of bounds, 2 = taken
EPISODE_END_REWARDS = "episode_end_rewards"  # [B, n] each keeper's cycles since its last decision at the end
STEP_CYCLES = "step_cycles"  # [B] cycles simulated during this step
DECIDING = "deciding"  # [B] the field's observation/keeper/action_mask are a real decision now

# human feedback channel (issue 3)
FEEDBACK = "human_feedback"
FEEDBACK_TIME = "human_feedback_time"
FEEDBACK_SOURCE = "human_feedback_source"
ENV_REWARD = "env_reward"
HUMAN_REWARD_ESTIMATE = "human_reward_estimate"  # H^(s, a) of the action taken, for reward-level fusion
