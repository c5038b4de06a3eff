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
STEP_COUNT = "step_count"  # TorchRL's ``StepCounter``: steps taken in the episode so far
EPISODE_REWARD = "episode_reward"  # TorchRL's ``RewardSum``: the environment's return of the episode so far

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

# the run's clock
CLOCK = "clock"  # [B] float64 seconds: when each board's current decision is made (simulated or wall clock)
LEARNER = "learner"  # [B] int64: the learner (seed) each row belongs to, for per-learner fusion weights

# human feedback: what the trainer's events put into a tensordict (``feedback.channel.FeedbackChannel``), K
# slots per board: the events that arrived on the board's clock since its previous decision, oldest first
FEEDBACK = "human_feedback"  # [B, K] float64: the person's reward h of each event (0 in empty slots)
FEEDBACK_TIME = (
    "human_feedback_time"  # [B, K] float64: when it was given, on the run's clock (credit uses it)
)
FEEDBACK_MASK = "human_feedback_mask"  # [B, K] bool: the slot holds an event
FEEDBACK_SOURCE = "human_feedback_source"  # [B, K] int64: ``feedback.events.SOURCE_KINDS`` code (0: none)

# fusion: what the one fusion component (``hfrl_torch.fusion``) reads and writes
ENV_VALUES = (
    "env_values"  # [B, A] the environment-trained estimate of every action: CE's R, Sarsa's Q, PG's logits
)
HUMAN_VALUES = "human_values"  # [B, A] H^(s, a) of every action
FUSED_VALUES = "fused_values"  # [B, A] f(R, H^): the values the action is chosen by
FUSION_WEIGHT = "fusion_weight"  # [B] the weight on H^ each row was fused with (trust, annealed, fixed)
ENV_REWARD = "env_reward"  # [B, 1] the environment's own reward, kept next to the fused one
HUMAN_REWARD_ESTIMATE = (
    "human_reward_estimate"  # [B, 1] H^(s, a) of the action taken, for reward-level fusion
)
