"""Every config group composes, and bad values fail with one line naming the value and what is allowed."""

from __future__ import annotations

import pytest
from omegaconf import OmegaConf

from hfrl_torch.common.errors import ConfigError, UserError
from hfrl_torch.experiment.checks import check_kernels
from hfrl_torch.experiment.cli import check_group_choices, compose_config
from hfrl_torch.experiment.config import resume_config, validate_evaluate, validate_train
from hfrl_torch.experiment.factories import make_keepaway_config, make_trainer
from hfrl_torch.experiment.keepaway_evaluation import evaluate_keepaway, format_keepaway_summary
from hfrl_torch.experiment.tetris_evaluation import evaluate_tetris
from hfrl_torch.fusion.weights import make_weight


def test_defaults_are_valid():
    validate_train(compose_config("train"))


@pytest.mark.parametrize(
    ("overrides", "weight"),
    [
        (["fusion=linear"], "adaptive"),  # the default the lifetimes support (docs/feedback.md)
        (["domain=keepaway", "fusion=exponential"], "adaptive"),
        (["fusion=control_sharing"], "adaptive"),
        (["+experiment=fig4_1", "fusion=linear"], "trust"),  # the thesis's figures keep the thesis's rule
        (["+experiment=fig4_2", "fusion=linear"], "trust"),
        (["+experiment=fig5_7", "fusion=exponential"], "trust"),
        (["+experiment=fig5_7", "fusion=linear", "fusion.weight=1.0"], 1.0),
    ],
)
def test_the_default_weight_is_adaptive_and_the_thesis_figures_keep_trust(overrides, weight):
    cfg = compose_config("train", *overrides)
    validate_train(cfg)
    assert cfg.fusion.weight == weight


@pytest.mark.parametrize("experiment", ["fig4_1", "fig4_2", "fig5_7"])
def test_annealed_in_a_figure_sweep_starts_from_its_own_beta(experiment):
    """The figure configs set fusion.weight=trust for every scheme they sweep; annealed leaves it unused."""
    cfg = compose_config("train", f"+experiment={experiment}", "fusion=annealed")
    validate_train(cfg)
    assert cfg.fusion.beta == 1.0 and cfg.fusion.weight == "trust"


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("domain.width=3", "domain.width=3 is invalid: must be an integer in 4..30"),
        ("domain.height=2", "domain.height=2 is invalid: must be an integer in 4..1000"),
        ("domain.features=abc", "domain.features='abc' is invalid; allowed: bt, knox, dellacherie, dt"),
        ("domain.engine=gpu", "domain.engine='gpu' is invalid; allowed: auto, numba, torch"),
        ("domain.max_pieces=-1", "domain.max_pieces=-1 is invalid: must be an integer >= 0"),
        ("domain.bag=maybe", "domain.bag='maybe' is invalid: must be true or false"),
        ("agent.iterations=-1", "agent.iterations=-1 is invalid: must be an integer >= 1"),
        ("agent.population=1", "agent.population=1 is invalid: must be an integer >= 2"),
        (
            "agent.elite_fraction=1.5",
            "agent.elite_fraction=1.5 is invalid: must be a finite number in 0.001..1.0",
        ),
        (
            "agent.initial_variance=-2.0",
            "agent.initial_variance=-2.0 is invalid: must be a finite number >= 0.0",
        ),
        ("agent.noise=wild", "agent.noise='wild' is invalid; allowed: constant, decreasing, none"),
        ("agent.noise_value=-4", "agent.noise_value=-4 is invalid: must be a finite number >= 0.0"),
        ("agent.games_per_candidate=0", "agent.games_per_candidate=0 is invalid: must be an integer >= 1"),
        ("seed=-3", "seed=-3 is invalid: must be an integer in 0.."),
        ("device=tpu", "device='tpu' is invalid; allowed: cpu, cuda, cuda:N"),
        ("threads=0", "threads=0 is invalid: must be auto or an integer in 1..256"),
        ("threads=all", "threads='all' is invalid: must be auto or an integer in 1..256"),
        ("logger.backend=wandb", "logger.backend='wandb' is invalid; allowed: tensorboard, none"),
        (
            "fusion=linear trainer=none",
            "fusion='linear' fuses the trainer's H^ with the environment; choose a trainer",
        ),
        (
            "fusion=linear trainer=oracle fusion.weight=-1",
            "fusion.weight=-1 is invalid: must be a finite number >= 0.0",
        ),
        (
            "fusion=linear trainer=oracle fusion.weight=much",
            "fusion.weight='much' is invalid; allowed: trust, adaptive, bandit, paired, search, or a number",
        ),
        (
            "fusion=linear trainer=oracle fusion.weight=adaptive fusion.adaptive.arms=[1.0]",
            "fusion.adaptive.arms=[1.0] is invalid; allowed: a list of two or more different weights >= 0",
        ),
        (
            "fusion=linear trainer=oracle fusion.weight=bandit fusion.adaptive.arms=[0,-1]",
            "fusion.adaptive.arms=[0, -1] is invalid",
        ),
        (
            "fusion=linear trainer=oracle fusion.weight=adaptive fusion.adaptive.discount=0",
            "fusion.adaptive.discount=0 is invalid: must be a finite number in 1e-06..1.0",
        ),
        (
            "agent=pg fusion=linear trainer=oracle fusion.weight=search",
            "fusion.weight=search with agent=pg fusion=linear is invalid: it needs a learner that searches "
            "the weight as part of its own search (agent=cem)",
        ),
        (
            "fusion=reward_shaping trainer=oracle fusion.weight=search",
            "fusion.weight=search with agent=cem fusion=reward_shaping is invalid",
        ),
        (
            "fusion=linear trainer=oracle trainer.leave_after=-5",
            "trainer.leave_after=-5 is invalid: must be a finite number >= 0.0",
        ),
        (
            "fusion=linear trainer=oracle trainer.leave_unit=hours",
            "trainer.leave_unit='hours' is invalid; allowed: episodes, minutes",
        ),
        (
            "domain=keepaway fusion=linear trainer.leave_unit=days",
            "trainer.leave_unit='days' is invalid; allowed: episodes, minutes",
        ),
        ("fusion=annealed trainer=oracle fusion.factor=1.5", "fusion.factor=1.5 is invalid"),
        ("fusion=annealed trainer=oracle fusion.beta=-1", "fusion.beta=-1 is invalid"),
        (
            "fusion=annealed trainer=oracle fusion.weight=maybe",
            "fusion.weight='maybe' is invalid; allowed: trust",
        ),
        (
            "trainer=interactive trainer.reconnect_wait_s=-1",
            "trainer.reconnect_wait_s=-1 is invalid: must be a finite number >= 0.0",
        ),
        (
            "trainer=interactive trainer.port=70000",
            "trainer.port=70000 is invalid: must be an integer in 0..65535",
        ),
        (
            "trainer=interactive trainer.keys.bad=/",
            "'bad': '/', 'pause': 'p', 'presence': 'h'} must be four different keys",
        ),
        (
            "trainer=interactive trainer.keys.good=ab",
            "trainer.keys.good='ab' is invalid: must be one character",
        ),
        ("trainer=interactive trainer.actions_per_s=100", "trainer.actions_per_s=100 is invalid"),
        (
            "trainer=interactive trainer.blind=maybe",
            "trainer.blind='maybe' is invalid: must be true or false",
        ),
        ("agent.initial_mean=nan", "agent.initial_mean=nan is invalid: must be a finite number"),
        ("agent.initial_variance=inf", "agent.initial_variance=inf is invalid: must be a finite number"),
    ],
)
def test_bad_values(override, message):
    with pytest.raises(ConfigError) as info:
        validate_train(compose_config("train", *override.split()))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_unknown_group_option_names_the_allowed_ones(capsys):
    with pytest.raises(SystemExit) as info:
        check_group_choices(["agent=nosuch"])
    assert info.value.code == 2
    assert (
        capsys.readouterr().err.strip()
        == "error: unknown agent 'nosuch'; allowed: cem, dqn, pg, ppo, qlearning, sarsa, tamer"
    )
    check_group_choices(["domain=tetris", "domain.width=8", "-m"])  # valid ones pass


def test_evaluate_rejects_bad_values_and_plays_random():
    with pytest.raises(ConfigError, match="games=0 is invalid"):
        validate_evaluate(compose_config("evaluate", "games=0"))
    with pytest.raises(UserError, match="neither a checkpoint nor a run directory"):
        evaluate_tetris(compose_config("evaluate", "policy=/no/such/dir"), progress=False)
    res = evaluate_tetris(compose_config("evaluate", "policy=random", "games=20"), progress=False)
    assert res["mean"] < 1.0 and res["games"] == 20 and res["policy"] == "random"


def test_keepaway_is_learned_by_sarsa_only():
    with pytest.raises(ConfigError, match=r"domain=keepaway agent=sarsa"):
        validate_train(compose_config("train", "domain=keepaway", "agent=cem"))
    with pytest.raises(ConfigError, match=r"domain=tetris agent=sarsa"):
        validate_train(compose_config("train", "agent=sarsa"))
    validate_train(compose_config("train", "domain=keepaway"))  # the domain brings its learner: agent=sarsa


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("policy=dellacherie", "policy='dellacherie' is not a keepaway policy; allowed: hand, random, hold"),
        ("domain.preset=1999", "domain.preset='1999' is invalid; allowed: 2005, rcss19"),
        ("domain.keepers=1", "domain.keepers=1 is invalid: must be an integer in 2..11"),
        ("episodes=0", "episodes=0 is invalid: must be an integer >= 1"),
        ("domain.decision_period_cycles=0", "domain.decision_period_cycles=0 is invalid"),
        ("domain.kernels=fast", "domain.kernels='fast' is invalid; allowed: auto, numba, torch"),
        ("max_episode_s=-1", "max_episode_s=-1 is invalid: must be a finite number >= 0.1"),
    ],
)
def test_keepaway_evaluate_bad_values(override, message):
    with pytest.raises(ConfigError) as info:
        cfg = compose_config("evaluate", "domain=keepaway", override)
        validate_evaluate(cfg)
        evaluate_keepaway(cfg, progress=False)
    assert message in str(info.value)


def test_keepaway_evaluate_reports_the_issue_fields(tmp_path):
    gif = tmp_path / "episode.gif"
    cfg = compose_config(
        "evaluate", "domain=keepaway", "policy=hold", "episodes=16", "domain.batch=16", f"gif={gif}"
    )
    res = evaluate_keepaway(cfg, progress=False)
    for key in ("domain", "policy", "preset", "keepers", "takers", "episodes", "mean_s", "sd_s", "median_s"):
        assert key in res
    for key in ("ci95_low", "ci95_high", "taken_share", "out_share", "cycles_per_s"):
        assert key in res
    assert res["episodes"] == 16 and res["policy"] == "hold" and res["keepers"] == 3
    assert abs(res["taken_share"] + res["out_share"] + res["cut_share"] - 1.0) < 1e-9
    assert 0.5 < res["mean_s"] < 10.0  # always holding loses the ball within seconds
    assert gif.is_file() and gif.stat().st_size > 1000


def test_keepaway_evaluate_cuts_episodes_at_max_episode_s():
    """An episode still running at max_episode_s ends there, counted at that length and reported as
    cut, so a policy that never loses the ball cannot stall evaluate.py."""
    cfg = compose_config(
        "evaluate", "domain=keepaway", "policy=hand", "episodes=16", "domain.batch=16", "max_episode_s=1.5"
    )
    res = evaluate_keepaway(cfg, progress=False)
    assert res["mean_s"] <= 1.5 and res["cut_share"] > 0.5
    assert abs(res["taken_share"] + res["out_share"] + res["cut_share"] - 1.0) < 1e-9
    assert "cut at max_episode_s, still running" in format_keepaway_summary(res)


def test_keepaway_preset_given_as_a_number_on_the_command_line_is_accepted():
    cfg = compose_config("evaluate", "domain=keepaway", "domain.preset=2005")
    validate_evaluate(cfg)
    assert make_keepaway_config(cfg).preset == "2005"


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        (
            ["trainer=none"],
            "agent=tamer learns only from feedback; choose a trainer: oracle, value_proxy, replay",
        ),
        (["trainer=oracle", "human.alpha=-1"], "human.alpha=-1 is invalid: must be a finite number >= 1e-12"),
        (["trainer=oracle", "human.credit=soon"], "human.credit='soon' is invalid; allowed: previous_step"),
        (["trainer=oracle", "human.features=dt"], "human.features='dt' is invalid; allowed: knox, bt"),
        (
            ["trainer=oracle", "trainer.frequency=1.5"],
            "trainer.frequency=1.5 is invalid: must be a finite number in 0.0..1.0",
        ),
        (["trainer=oracle", "trainer.consistency=-0.1"], "trainer.consistency=-0.1 is invalid"),
        (
            ["trainer=value_proxy", "trainer.mode=loud"],
            "trainer.mode='loud' is invalid; allowed: sign, scaled",
        ),
        (["trainer=replay"], "trainer=replay needs trainer.log=<feedback log file>"),
        (["trainer=replay", "trainer.log=/no/such.jsonl"], "trainer.log='/no/such.jsonl' is not a file"),
    ],
)
def test_tamer_and_trainer_bad_values(overrides, message):
    cfg = compose_config("train", "agent=tamer", *overrides)
    with pytest.raises(ConfigError) as info:
        validate_train(cfg)
    assert message in str(info.value)


def test_adaptive_weight_is_each_learners_own_estimator():
    from hfrl_torch.experiment.registry import learner_for
    from hfrl_torch.fusion.bandit import BanditWeight
    from hfrl_torch.fusion.paired import PairedWeight
    from hfrl_torch.fusion.schedules import SearchedWeight
    from hfrl_torch.fusion.weights import make_weight, weight_kind

    for overrides, kind, cls in (
        (["fusion=linear"], "paired", PairedWeight),  # CE compares weights on the same test games
        (["fusion=linear", "fusion.weight=search"], "search", SearchedWeight),  # measured, kept as an option
        (["fusion=reward_shaping"], "bandit", BanditWeight),  # a shaped fitness would select a large weight
        (["agent=pg", "fusion=linear"], "bandit", BanditWeight),
        (["domain=keepaway", "fusion=exponential"], "bandit", BanditWeight),
        (["fusion=linear", "fusion.weight=bandit"], "bandit", BanditWeight),
    ):
        weight = [] if any(o.startswith("fusion.weight") for o in overrides) else ["fusion.weight=adaptive"]
        cfg = compose_config("train", *overrides, *weight)
        validate_train(cfg)
        evidence = learner_for(cfg.agent.name, cfg.domain.name).weight_evidence
        assert weight_kind(cfg, evidence) == kind
        assert isinstance(make_weight(cfg, 3, evidence), cls)


def test_trainer_factory_builds_the_simulated_trainers():
    from hfrl_torch.trainers import HumanLikeTiming, OracleTrainer, ValueProxyTrainer

    oracle = make_trainer(compose_config("train", "agent=tamer", "trainer=oracle"), None)
    assert isinstance(oracle, HumanLikeTiming) and isinstance(oracle.trainer, OracleTrainer)
    assert oracle.trainer.frequency == 0.5 and oracle.trainer.consistency == 0.9
    plain = make_trainer(
        compose_config("train", "agent=tamer", "trainer=value_proxy", "trainer.timing.enabled=false"), None
    )
    assert isinstance(plain, ValueProxyTrainer)
    assert make_trainer(compose_config("train"), None) is None


def test_numba_kernels_need_the_cpu():
    cfg = compose_config("train", "domain=keepaway", "agent=sarsa", "domain.kernels=numba", "device=cuda")
    with pytest.raises(ConfigError) as info:
        check_kernels(cfg)
    assert str(info.value) == (
        "domain.kernels='numba' runs on the CPU only, not device=cuda; use domain.kernels=auto or torch"
    )
    assert check_kernels(compose_config("train", "domain=keepaway", "agent=sarsa", "device=cuda")) == "torch"


def test_keepaway_kernels_follow_the_device():
    """Whole cycles compiled on the CPU, the browser's live view included (it steps them one cycle per
    call), torch on a GPU."""
    assert check_kernels(compose_config("train", "domain=keepaway")) == "cycle"
    assert check_kernels(compose_config("train", "domain=keepaway", "trainer=interactive")) == "cycle"
    assert check_kernels(compose_config("evaluate", "domain=keepaway")) == "cycle"
    on_gpu = compose_config("train", "domain=keepaway", "trainer=interactive", "device=cuda")
    assert check_kernels(on_gpu) == "torch"


def test_the_adaptive_priors_strength_follows_the_domain(compose_train):
    """Keepaway's short episodes get a prior worth 20 episodes, Tetris's 4; an override still wins."""
    keepaway = compose_train("domain=keepaway", "fusion=linear", "fusion.weight=adaptive")
    tetris = compose_train("agent=pg", "fusion=linear", "fusion.weight=adaptive")
    assert keepaway.fusion.adaptive.prior_count == 20.0 and tetris.fusion.adaptive.prior_count == 4.0
    assert (
        compose_train(
            "domain=keepaway", "fusion=linear", "fusion.adaptive.prior_count=2"
        ).fusion.adaptive.prior_count
        == 2
    )


def test_a_run_saved_before_trainer_blind_existed_resumes_blind(tmp_path):
    """A study's worker resumes with trainer.blind=true, also a run saved before the setting existed."""
    old = OmegaConf.to_container(compose_config("train", "trainer=interactive"))
    del old["trainer"]["blind"]
    merged = resume_config(OmegaConf.create({}), tmp_path, {"config": old}, ["trainer.blind=true"])
    assert merged.trainer.blind is True
    oracle = OmegaConf.to_container(compose_config("train", "trainer=oracle"))
    with pytest.raises(ConfigError, match="cannot apply overrides"):  # a trainer that has no such setting
        resume_config(OmegaConf.create({}), tmp_path, {"config": oracle}, ["trainer.blind=true"])


def test_the_adaptive_arms_follow_the_domain_and_reach_the_bandit(compose_train):
    """Keepaway's bandit may also put H^ at 256 (H^ decides outright), Tetris's and a gym task's stop at 16;
    an override still wins, and the run's bandit plays the composed arms."""
    keepaway = compose_train("domain=keepaway", "fusion=linear", "fusion.weight=adaptive")
    tetris = compose_train("agent=pg", "fusion=linear", "fusion.weight=adaptive")
    assert list(keepaway.fusion.adaptive.arms) == [0.0, 1.0, 16.0, 256.0]
    assert list(tetris.fusion.adaptive.arms) == [0.0, 1.0, 16.0]
    custom = compose_train("domain=keepaway", "fusion=linear", "fusion.adaptive.arms=[0.0,4.0]")
    assert list(custom.fusion.adaptive.arms) == [0.0, 4.0]
    bandit = make_weight(keepaway, learners=2)
    assert bandit.arms.tolist() == [0.0, 1.0, 16.0, 256.0] and bandit.value().tolist() == [256.0, 256.0]
