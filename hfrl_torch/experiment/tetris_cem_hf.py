"""CE + human feedback on Tetris (thesis Figure 4.1): ``train.py agent=cem fusion=<scheme> trainer=<t>``.

One CE iteration is one episode of the fusion, in four parts:

1. **Watch.** The fused mean policy plays one game (at most ``agent.watch_pieces`` placements) on a
   ``TetrisEnv`` wrapped in ``FeedbackFusion``; the trainer judges each placement, every event is logged and
   written into the tensordict, and H^ (TAMER) learns from it: the thesis's "H^ keeps learning during
   testing". One trainer watches one board, as a person would.
2. **CE step.** Every candidate plays its games acting on its own R fused with H^ at this iteration's weight,
   so the elite are the weights that work best together with what the trainer taught.
3. **Test.** The fused mean policy plays ``agent.eval_games`` fresh games: their lines are the learning
   curve, and the share of their placements where argmax H^ = argmax R is the match rate m.
4. **Weight.** The schedule ends the episode: eq. 4.4 folds in (lines, m) for the trust factor; the
   annealed weight decays by its factor; a fixed weight stays.

Every random draw of iteration t (CE, games, trainer, control-sharing coins) is seeded from (seed, t) or
restored from the checkpoint, so a resumed run continues as if never stopped; feedback events are appended to
``feedback.jsonl`` as they are given, so a crash loses none of them.
"""

from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch
from omegaconf import DictConfig, OmegaConf
from tensordict import TensorDictBase
from torchrl.envs import TransformedEnv
from tqdm import tqdm

from hfrl_torch import keys
from hfrl_torch.agents.cem import CrossEntropyMethod
from hfrl_torch.agents.cem.cem import _derived_seed
from hfrl_torch.agents.cem.fused_rollout import FusedRollout
from hfrl_torch.agents.tamer import TamerAgent
from hfrl_torch.agents.tamer.tamer import placement_deltas
from hfrl_torch.common.checkpoint import LAST, save_checkpoint
from hfrl_torch.common.errors import CheckpointError
from hfrl_torch.common.logger import flatten_config, markdown_table
from hfrl_torch.common.stats import summarize
from hfrl_torch.envs.tetris import TetrisEnv, TetrisRules
from hfrl_torch.envs.tetris.features import feature_id, feature_names
from hfrl_torch.envs.tetris.pieces import PIECE_NAMES, placement_table
from hfrl_torch.feedback.events import feedback_tensors
from hfrl_torch.feedback.log import FeedbackLog
from hfrl_torch.fusion.schedules import ConstantWeight, TrustWeight, WeightSchedule
from hfrl_torch.fusion.schemes import FusedActionSelector
from hfrl_torch.fusion.transform import FeedbackFusion
from hfrl_torch.interactive.session import TeachingSession

if TYPE_CHECKING:
    from hfrl_torch.interactive.live import LiveTeaching
from hfrl_torch.trainers.base import Trainer

LATE_FEEDBACK_S = 0.8  # how long a live game waits after its last placement for feedback on it

# The reward-level rule the watched game's FeedbackFusion applies for each scheme: decision-level schemes
# leave the reward as it is, the annealed baseline is the linear rule.
REWARD_RULE = {
    "none": "none",
    "human_only": "human_only",
    "linear": "linear",
    "exponential": "exponential",
    "annealed": "linear",
    "reward_shaping": "reward_shaping",
    "action_biasing": "none",
    "control_sharing": "none",
}
# The rule the fused mean policy chooses placements by (reward shaping acts on R alone).
DECISION_RULE = {**{k: k for k in REWARD_RULE}, "annealed": "linear", "reward_shaping": "none"}


def watch_game(
    env: TransformedEnv,
    selector: FusedActionSelector,
    env_weights: torch.Tensor,
    agent: TamerAgent,
    trainer: Trainer,
    game_seed: int,
    episode: int,
    clock: float,
    seconds_per_placement: float,
    live: TeachingSession | None = None,
) -> dict[str, float]:
    """The trainer watches the fused policy play one game; H^ learns from every event. Returns its totals.

    ``clock`` is the simulated time of the first placement; the game's last events, which arrive after its
    last placement, are learned too (they credit its last placements). With ``live`` (a person in the
    browser) the game runs on the wall clock at the page's speed, every placement is shown on the page,
    and the game stops early if the person leaves.
    """
    n_env = env_weights.numel()
    env.set_seed(game_seed)  # a TransformedEnv passes no reset_game_seed down: seed the env's own draw
    td = env.reset()
    totals = {"env_return": 0.0, "fused_return": 0.0, "placements": 0.0, "given": 0.0, "positive": 0.0}
    now = clock
    episode_t = torch.tensor([episode])
    while True:
        if live is not None:
            if not live.teaching():
                totals["lines"] = float(td[keys.LINES].sum())
                break
            now = live.wait_turn()
        agent.learn(now)
        deltas = placement_deltas(td)
        human = agent.model(deltas)
        env_values = (td[keys.AFTERSTATE_FEATURES][..., :n_env].to(torch.float64) * env_weights).sum(-1)
        action = selector(env_values, human, td[keys.ACTION_MASK], td[keys.AFTERSTATE_TERMINAL])
        events = trainer.give(td, action, now, episode_t)
        agent.record(td, action, now)
        agent.give_feedback(events)
        td[keys.ACTION] = action
        td[keys.HUMAN_REWARD_ESTIMATE] = human.gather(1, action.view(1, 1)).to(torch.float32)
        td.update(feedback_tensors(events))
        td = env.step(td)
        nxt = td["next"]
        if live is not None:
            live.publish(tetris_frame(td, episode, weight=selector.weight().reshape(-1)[0].item()))
        totals["env_return"] += float(nxt[keys.ENV_REWARD].sum())
        totals["fused_return"] += float(nxt[keys.REWARD].sum())
        totals["placements"] += 1
        totals["given"] += float(sum(len(e) for e in events))
        totals["positive"] += float(sum(ev.value > 0 for e in events for ev in e))
        now += seconds_per_placement
        if bool(nxt[keys.DONE].any()):
            trainer.end_games(nxt[keys.DONE].view(-1), nxt[keys.LINES].view(-1))
            totals["lines"] = float(nxt[keys.LINES].sum())
            break
        td = td["next"]
    if live is not None and totals["placements"] > 0:  # feedback on the last placements is on its way
        live.sleep(LATE_FEEDBACK_S)
        late = trainer.give(td, torch.zeros(1, dtype=torch.int64), live.clock(), episode_t)
        agent.give_feedback(late)
        totals["given"] += float(sum(len(e) for e in late))
        totals["positive"] += float(sum(ev.value > 0 for e in late for ev in e))
    agent.learn(math.inf)
    totals["clock"] = now
    return totals


def tetris_frame(td: TensorDictBase, episode: int, weight: float) -> dict[str, Any]:
    """What the page draws after a placement: the board, the cells just placed, lines, the action."""
    before = td[keys.BOARD][0]
    after = td["next", keys.BOARD][0]
    placed = (
        (after & ~before).nonzero().tolist()
        if int(td["next", keys.LINES].sum()) == int(td[keys.LINES].sum())
        else []
    )
    p, a = int(td[keys.PIECE][0]), int(td[keys.ACTION][0])
    table = placement_table(before.shape[1])
    column, orient = int(table.column[p, a]), int(table.orient[p, a])
    return {
        "type": "tetris",
        "board": after.to(torch.int64).tolist(),
        "placed": placed,
        "lines": int(td["next", keys.LINES].sum()),
        "pieces": int(td["next", keys.PIECES_PLACED].sum()),
        "episode": episode,
        "action": f"{PIECE_NAMES[p]} at column {column + 1}, rotation {orient}",
        "text": f"watching you (trust in your feedback: {weight:.2f})",
    }


def games_match_rate(games_matches: torch.Tensor, pieces: torch.Tensor) -> float | None:
    """m over a set of games: placements where argmax H^ = argmax R / placements (None: no placement)."""
    total = int(pieces.sum())
    return int(games_matches.sum()) / total if total else None


def train_cem_hf(cfg: DictConfig, run_dir: Path, checkpoint: dict | None) -> dict[str, float]:
    """Run CE + human feedback up to ``agent.iterations``, continuing from ``checkpoint`` if given."""
    from hfrl_torch.experiment.factories import (
        fusion_normalises,
        make_cem_config,
        make_credit,
        make_rules,
        make_run_logger,
        make_trainer,
        make_weight_schedule,
        warm_up,
    )

    rules: TetrisRules = make_rules(cfg)
    scheme = cfg.fusion.name
    hm = cfg.human
    normalise = fusion_normalises(cfg)
    env_names = feature_names(feature_id(cfg.domain.features), rules.width)
    human_names = feature_names(feature_id(hm.features), rules.width)
    rollout = FusedRollout(rules, cfg.domain.features, hm.features, scheme, normalise, cfg.domain.max_pieces)
    cem = CrossEntropyMethod(len(env_names), make_cem_config(cfg), rollout, seed=cfg.seed)
    agent = TamerAgent(len(human_names), 1, hm.alpha, make_credit(cfg), hm.window, hm.renormalise)
    schedule: WeightSchedule = make_weight_schedule(cfg)
    log = FeedbackLog(run_dir / "feedback.jsonl", session=run_dir.name)
    teaching: LiveTeaching | None = None
    live: TeachingSession | None = None
    if cfg.trainer.name == "interactive":
        from hfrl_torch.interactive.live import start_live_teaching

        teaching = start_live_teaching(cfg, log, view="tetris")
        trainer, live = teaching.trainer, teaching.session
        who = "a person in the browser (human:browser)"
    else:
        trainer = make_trainer(cfg, log)
        source = trainer.source if trainer.source != "trainer" else f"simulated:{cfg.trainer.name}"
        who = f"{source} (trainer={cfg.trainer.name}; a simulated or replayed trainer, not a person)"
    history: list[dict[str, float]] = []
    clock = 0.0
    if checkpoint is not None:
        state = checkpoint["state"]
        try:
            cem.load_state_dict(state["cem"])
            agent.model.weight.copy_(torch.as_tensor(state["human_weights"], dtype=torch.float64))
            agent.applied.copy_(torch.as_tensor(state["applied"], dtype=torch.int64))
            schedule.load_state_dict(state["schedule"])
            trainer.load_state_dict(state["trainer"])
            clock = float(state["clock"])
        except (KeyError, RuntimeError, TypeError, ValueError) as e:
            raise CheckpointError(f"checkpoint of {run_dir} is not a CE + feedback run ({e!r})") from None
        history = list(checkpoint["history"])

    env = TransformedEnv(
        TetrisEnv(batch=1, rules=rules, features=hm.features, max_pieces=cfg.agent.watch_pieces),
        FeedbackFusion(REWARD_RULE[scheme], 0.0),
    )
    start = cem.iteration
    warm_up(cfg)
    logger = make_run_logger(cfg, str(run_dir / "tensorboard"), purge_step=start + 1 if start > 0 else None)
    if start == 0:
        logger.text("hyperparameters", markdown_table(flatten_config(cfg)))
        logger.text("trainer", f"{who}, fusion={scheme}")
    if teaching is not None:
        wait = float(cfg.trainer.wait_for_page_s)
        tqdm.write(f"Teach the agent in your browser: {teaching.url}", file=sys.stderr)
        if wait > 0 and start == 0:
            tqdm.write(f"Waiting up to {wait:g} s for the page to open...", file=sys.stderr)
            if not teaching.session.wait_for_page(wait):
                tqdm.write("No page opened: learning from the game alone until one does.", file=sys.stderr)
    ckpt_path = run_dir / "checkpoints" / LAST
    config_yaml = OmegaConf.to_yaml(cfg, resolve=True)
    bar = tqdm(
        total=cfg.agent.iterations,
        initial=start,
        desc=f"CE+{scheme} {rules.width}x{rules.height}",
        unit="it",
        dynamic_ncols=True,
    )
    try:
        while cem.iteration < cfg.agent.iterations:
            t = cem.iteration
            t0 = time.perf_counter()
            weight = float(schedule.value(t).reshape(-1)[0])  # 0 for none and human_only

            # 1. the trainer watches the fused mean policy; H^ learns
            env.transform.schedule = ConstantWeight(weight)
            selector = FusedActionSelector(
                DECISION_RULE[scheme],
                weight,
                generator=torch.Generator().manual_seed(_derived_seed(cfg.seed, t, 4)),
                normalise=normalise,
            )
            watched = watch_game(
                env,
                selector,
                cem.mean,
                agent,
                trainer,
                _derived_seed(cfg.seed, t, 3),
                t,
                clock,
                hm.seconds_per_placement,
                live,
            )
            clock = watched["clock"]
            if live is not None:
                live.publish({"type": "status", "text": f"practising on its own (CE iteration {t + 1})"})

            # 2. CE step, candidates acting on R fused with H^
            rollout.human_weights = agent.model.weight[0].detach().clone()
            rollout.weight = weight
            metrics = cem.step()

            # 3. test the fused mean policy; m from its placements
            eval_lines = cem.evaluate_mean()
            assert rollout.last is not None
            m = games_match_rate(rollout.last.matches, rollout.last.pieces)
            ev = summarize(eval_lines, floor=0.0)

            # 4. the weight's episode ends: eq. 4.4, annealing
            if isinstance(schedule, TrustWeight):
                schedule.end_episode(performance=ev["mean"], match_rate=m)
            else:
                schedule.end_episode()
            elapsed = time.perf_counter() - t0
            metrics.update(
                {
                    "eval/mean_policy_lines_mean": ev["mean"],
                    "eval/mean_policy_lines_median": ev["median"],
                    "eval/mean_policy_lines_ci95_low": ev["ci95_low"],
                    "eval/mean_policy_lines_ci95_high": ev["ci95_high"],
                    "eval/capped_games": cem.last_eval_capped,
                    "episode/env_return": watched["env_return"],
                    "episode/fused_return": watched["fused_return"],
                    "episode/placements": watched["placements"],
                    "feedback/given": watched["given"],
                    "feedback/positive_share": watched["positive"] / watched["given"]
                    if watched["given"]
                    else 0.0,
                    "feedback/trainer_present": float(watched["given"] > 0),
                    "feedback/learned_total": float(agent.applied.sum()),
                    "fusion/weight": weight,
                    "fusion/weight_next": float(schedule.value(t + 1).reshape(-1)[0]),
                    "fusion/match_rate": math.nan if m is None else m,
                    "time/iteration_s": elapsed,
                }
            )
            step = cem.iteration
            logger.scalars(metrics, step)
            logger.flush()
            history.append({"iteration": step, **metrics})
            human_weights = agent.model.weight[0].detach().clone()
            save_checkpoint(
                ckpt_path,
                domain="tetris",
                agent="cem",
                config_yaml=config_yaml,
                payload={
                    "state": {
                        "cem": cem.state_dict(),
                        "human_weights": agent.model.weight.detach().clone(),
                        "applied": agent.applied.clone(),
                        "schedule": schedule.state_dict(),
                        "trainer": trainer.state_dict(),
                        "clock": clock,
                    },
                    "history": history,
                    "policy": {
                        "kind": "fused",
                        "scheme": DECISION_RULE[scheme],
                        "weight": metrics["fusion/weight_next"],
                        "normalise": normalise,
                        "features": cfg.domain.features,
                        "feature_names": env_names,
                        "weights": cem.mean.clone(),
                        "human_features": hm.features,
                        "human_weights": human_weights,
                    },
                    "rules": rules.as_dict(),
                },
            )
            with (run_dir / "metrics.jsonl").open("a") as f:
                f.write(json.dumps({"iteration": step, **metrics}) + "\n")
            if live is not None:
                live.add_point(step, ev["mean"])
            bar.update(1)
            bar.set_postfix(
                eval_lines=f"{ev['mean']:.1f}",
                w=f"{weight:.2f}",
                m="-" if m is None else f"{m:.2f}",
                fb=f"{watched['given']:.0f}",
            )
    finally:
        bar.close()
        if teaching is not None:
            teaching.stop()
        log.close()
        final = history[-1] if history else {}
        if history and cem.iteration >= cfg.agent.iterations and cem.iteration > start:
            logger.hparams(
                flatten_config(cfg), {"hparam/eval_lines_mean": final["eval/mean_policy_lines_mean"]}
            )
        logger.close()
    return final
