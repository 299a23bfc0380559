"""World-model and imagination options of issue 22 part 2: symlog two-hot heads, KL balancing with free bits, the
percentile return scale, ensemble uncertainty penalty, balanced exploration, and the imagined-vs-real per-action
diagnostic (closed-form checks plus one tiny training iteration per option)."""

import copy
import math
import sys
from pathlib import Path

import pytest
import torch
from tensordict import TensorDict
from torch import nn

from freamer_rl.errors import ConfigError
from freamer_rl.health.agent import build_agent, make_health_env
from freamer_rl.health.config import load_health_config
from freamer_rl.health.oracle import (
    action_ranking,
    held_action_returns,
    imagined_held_returns,
    planning_env,
    rank_agreement,
)
from freamer_rl.health.reference import evaluate_reference
from freamer_rl.health.trainer import HealthTrainer
from freamer_rl.trainers.health import STRUCTURAL
from freamer_rl.world_model.functional import free_nats_kl, gaussian_kl, symexp, symlog
from freamer_rl.world_model.heads import (
    HeadEnsemble,
    PercentileReturnScale,
    TwoHotHead,
    make_scalar_head,
    twohot_bins,
    twohot_decode,
    twohot_encode,
)
from freamer_rl.world_model.imagination import RSSMWorldModelEnv
from freamer_rl.world_model.rssm import WorldModel

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import TINY, health_adapter  # noqa: E402, F401  (the fixture registers the health adapter)

MLP_RECIPE = Path(__file__).resolve().parents[2] / "recipes" / "health" / "health_mlp.yaml"
SHAPES = [(), (2,), (3, 2)]


# -- two-hot ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_twohot_encode_decode_round_trip(shape):
    torch.manual_seed(0)
    bins = twohot_bins(255, -20.0, 20.0)
    x = torch.randn(shape) * 50  # up to ~|150|: symlog ~5, inside the range
    t = twohot_encode(x, bins)
    assert t.shape == (*shape, 255)
    torch.testing.assert_close(t.sum(-1), torch.ones(shape))
    nz = t > 0
    assert bool((nz.sum(-1) <= 2).all())
    idx = torch.arange(255).expand_as(t)
    lo = torch.where(nz, idx, 255).min(-1).values
    hi = torch.where(nz, idx, -1).max(-1).values
    assert bool((hi - lo <= 1).all())  # the two weights sit on neighbouring bins
    # symlog(x) lies between those bins and the weights interpolate linearly
    torch.testing.assert_close((t * bins).sum(-1), symlog(x), atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(twohot_decode(t, bins), x, atol=1e-3, rtol=1e-4)


def test_twohot_exact_bin_and_clipping():
    bins = torch.tensor([-2.0, 0.0, 2.0])
    t = twohot_encode(torch.tensor([0.0, symexp(torch.tensor(1.0)), 1e6, -1e6]), bins)
    torch.testing.assert_close(t[0], torch.tensor([0.0, 1.0, 0.0]))
    torch.testing.assert_close(t[1], torch.tensor([0.0, 0.5, 0.5]))
    torch.testing.assert_close(t[2], torch.tensor([0.0, 0.0, 1.0]))  # beyond the range: clipped to the last bin
    torch.testing.assert_close(t[3], torch.tensor([1.0, 0.0, 0.0]))


@pytest.mark.parametrize("shape", SHAPES)
def test_twohot_head_starts_at_zero_and_fits(shape):
    torch.manual_seed(0)
    head = TwoHotHead(4, 16)
    feat = torch.randn(*shape, 4)
    assert head(feat).shape == (*shape, 1)
    torch.testing.assert_close(head(feat), torch.zeros(*shape, 1))
    opt = torch.optim.Adam(head.parameters(), lr=1e-2)
    target = torch.full(shape, 7.0)
    for _ in range(150):
        opt.zero_grad()
        head.loss(feat, target).backward()
        opt.step()
    assert float((head(feat).detach() - 7.0).abs().max()) < 0.5


# -- ensemble ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("shape", SHAPES)
def test_ensemble_penalty_zero_for_identical_members(shape):
    torch.manual_seed(0)
    member = make_scalar_head("mse", 6, 8)
    ens = HeadEnsemble([member, copy.deepcopy(member), copy.deepcopy(member)])
    feat = torch.randn(*shape, 6)
    torch.testing.assert_close(ens.std(feat), torch.zeros(*shape, 1))
    torch.testing.assert_close(ens(feat), member(feat))
    a, b = make_scalar_head("mse", 6, 8), make_scalar_head("mse", 6, 8)
    ens2 = HeadEnsemble([a, b])
    torch.testing.assert_close(ens2.std(feat), (a(feat) - b(feat)).abs() / 2)  # population std of two values


def _wm(**kw):
    torch.manual_seed(0)
    return WorldModel({"x": 3}, 2, embed_dim=8, deter_dim=6, stoch_dim=2, hidden=8, **kw)


def test_imagined_reward_is_mean_minus_penalty_times_std():
    wm = _wm(ensemble=2)
    env = RSSMWorldModelEnv(wm, uncertainty_penalty=0.7, sample=False, done_mode="never")
    plain = RSSMWorldModelEnv(wm, sample=False, done_mode="never")
    start = env.reset(_seeds(wm, 4))
    act = torch.tensor([0, 1, 0, 1])
    out = env.step(start.clone().set("action", act))["next"]
    ref = plain.step(start.clone().set("action", act))["next"]
    feat = out["latent"]
    expected = ref["reward"] - 0.7 * wm.reward_head.std(feat)
    torch.testing.assert_close(out["reward"], expected)
    assert float(wm.reward_head.std(feat).detach().abs().sum()) > 0  # independently initialised members disagree


def _seeds(wm, n):
    return TensorDict({"deter": torch.randn(n, wm.deter_dim), "stoch": torch.randn(n, wm.stoch_dim)}, [n])


# -- KL balancing with free bits --------------------------------------------------------------------------------------
def test_kl_balance_with_free_nats_is_dreamerv3_per_term_clip():
    """beta = 0.6, alpha = 5/6 with the per-step free-nats clamp == 0.5 max(1, KL(sg q||p)) + 0.1 max(1, KL(q||sg p))
    in value and in the gradients of both the prior and the posterior parameters."""
    torch.manual_seed(0)
    wm = _wm(kl_balance=5 / 6, beta=0.6, free_nats=1.0)
    pm, qm = torch.randn(8, 5, 2), torch.randn(8, 5, 2) * 1.5  # some steps below, some above 1 nat
    ps, qs = torch.rand(8, 5, 2) + 0.5, torch.rand(8, 5, 2) + 0.5

    def grads(fn):
        leaves = [t.clone().requires_grad_() for t in (pm, ps, qm, qs)]
        loss = fn(*leaves)
        loss.backward()
        return loss.detach(), [t.grad for t in leaves]

    ours = grads(
        lambda a, b, c, d: (
            wm.beta
            * free_nats_kl(wm.kl({"prior_mean": a, "prior_std": b, "post_mean": c, "post_std": d}), wm.free_nats)
        )
    )
    dyn = lambda a, b, c, d: gaussian_kl(c.detach(), d.detach(), a, b).clamp(min=1.0).mean()  # noqa: E731
    rep = lambda a, b, c, d: gaussian_kl(c, d, a.detach(), b.detach()).clamp(min=1.0).mean()  # noqa: E731
    v3 = grads(lambda *t: 0.5 * dyn(*t) + 0.1 * rep(*t))
    kl = gaussian_kl(qm, qs, pm, ps)
    assert bool((kl < 1).any()) and bool((kl > 1).any())
    torch.testing.assert_close(ours[0], v3[0])
    for g1, g2 in zip(ours[1], v3[1]):
        torch.testing.assert_close(g1, g2)


# -- percentile return normalisation ----------------------------------------------------------------------------------
def test_percentile_scale_closed_form():
    s = PercentileReturnScale(decay=0.99)
    r = torch.linspace(0, 100, 101)  # P5 = 5, P95 = 95
    torch.testing.assert_close(s.update(r), torch.tensor(90.0))  # the first batch initialises the EMAs
    r2 = torch.linspace(0, 200, 101)  # P5 = 10, P95 = 190
    torch.testing.assert_close(s.update(r2), torch.tensor(0.99 * 90 + 0.01 * 180))
    small = PercentileReturnScale()
    torch.testing.assert_close(small.update(torch.full((10,), 3.0)), torch.tensor(1.0))  # max(1, 0)


# -- diagnostic pieces ------------------------------------------------------------------------------------------------
def test_rank_agreement_closed_form():
    real = torch.tensor([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0], [5.0, 5.0, 1.0]])
    imag = torch.tensor([[10.0, 20.0, 30.0], [3.0, 2.0, 1.0], [0.0, 1.0, 2.0]])
    rho, top1 = rank_agreement(imag, real)
    torch.testing.assert_close(rho[:2], torch.tensor([1.0, -1.0]))
    # ranks real (1.5, 1.5, 0) vs imag (0, 1, 2): centred (1/2, 1/2, -1) . (-1, 0, 1) / sqrt(1.5 * 2)
    torch.testing.assert_close(rho[2], torch.tensor(-1.5 / 3**0.5))
    assert top1.tolist() == [True, False, False]


def test_imagined_held_returns_closed_form():
    wm = _wm()
    with torch.no_grad():
        wm.reward_head[-1].weight.zero_()
        wm.reward_head[-1].bias.fill_(0.5)
        wm.continue_head[-1].weight.zero_()
        wm.continue_head[-1].bias.fill_(10.0)
    latent = torch.randn(3, wm.latent_dim)
    torch.testing.assert_close(imagined_held_returns(wm, latent, 4, "threshold"), torch.full((3, 2), 2.0))
    with torch.no_grad():
        wm.continue_head[-1].bias.fill_(-10.0)  # terminates at once: only the first step counts
    torch.testing.assert_close(imagined_held_returns(wm, latent, 4, "threshold"), torch.full((3, 2), 0.5))
    torch.testing.assert_close(imagined_held_returns(wm, latent, 4, "never"), torch.full((3, 2), 2.0))


def test_held_action_returns_match_the_real_env():
    """The held-action returns of the planning copy equal the real (TransformedEnv) env stepped with the held action
    from the same state, with zero heart-rate noise draws like the copy."""
    cfg = load_health_config(MLP_RECIPE, TINY)
    env = make_health_env(cfg, num_envs=2, seed=3)
    td = env.reset()
    for _ in range(5):  # leave the reset state
        td = env.step(td.set("action", torch.tensor([0, 2])))["next"]
    sim = planning_env(env)
    ret = held_action_returns(sim, 5, 6)
    state = sim.snapshot()
    for a in range(5):
        sim.restore(state)
        total = torch.zeros(2)
        for _ in range(6):
            # the step's "hr_noise" draws (zeros: the noise-free dynamics of the planning copy)
            step = TensorDict({"action": torch.full((2,), a), "hr_noise": torch.zeros(2)}, batch_size=[2])
            nxt = env.step(step)["next"]
            total += nxt["reward"].reshape(2)
        torch.testing.assert_close(ret[:, a], total)
    assert len({round(float(v), 3) for v in ret[0]}) > 1  # the actions' returns differ


# -- config -----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("overrides", "field"),
    [
        (["world_model.reward_head=l1"], r"world_model\.reward_head"),
        (["imagination.value_head=huber"], r"imagination\.value_head"),
        (["imagination.return_norm=std"], r"imagination\.return_norm"),
        (["imagination.uncertainty_penalty=0.5"], r"imagination\.uncertainty_penalty"),
        (["imagination.uncertainty_penalty=-1", "world_model.ensemble=2"], r"imagination\.uncertainty_penalty"),
        (["world_model.ensemble=0"], r"world_model\.ensemble"),
        (
            ["collect.balance_actions=true", "collect.random_action_prob=0", "collect.prefill_frames=0"],
            r"collect\.balance_actions",
        ),
        (["eval.references=[oracle, mpc]"], r"eval\.references"),
        (["eval.references=[continue, continue]"], r"eval\.references"),
    ],
)
def test_option_errors_name_the_field(overrides, field):
    with pytest.raises(ConfigError, match=field):
        load_health_config(MLP_RECIPE, [*TINY, *overrides])


def test_defaults_are_todays_behaviour():
    agent = build_agent(load_health_config(MLP_RECIPE, TINY))
    assert isinstance(agent.world_model.reward_head, nn.Sequential)  # the MSE MLP (old checkpoints load)
    assert not isinstance(agent.value.module, TwoHotHead)


# -- each option trains one tiny iteration; the diagnostic lands in the summary -----------------------------------------
@pytest.mark.parametrize(
    "options",
    [
        ["world_model.reward_head=twohot", "imagination.value_head=twohot"],
        ["imagination.return_norm=percentile"],
        ["imagination.return_norm=percentile", "imagination.lambda_return_actor_critic=true"],
        [
            "world_model.ensemble=2",
            "imagination.uncertainty_penalty=1.0",
            "imagination.value_head=twohot",
            "imagination.lambda_return_actor_critic=true",
        ],
        ["collect.balance_actions=true", "world_model.kl_balance=0.8333", "world_model.beta=0.6"],
    ],
)
def test_option_trains_one_iteration(options, tmp_path):
    torch.manual_seed(0)
    cfg = load_health_config(MLP_RECIPE, [*TINY, "collect.iterations=1", *options])
    trainer = HealthTrainer(cfg, tmp_path / "run", structural=STRUCTURAL)
    summary = trainer.train()
    assert torch.isfinite(torch.tensor(summary["eval_return_mean"]))
    rank = summary["action_ranking"]
    assert len(rank["imagined_return"]) == len(rank["real_return"]) == 5 and rank["seeds"] > 0
    assert summary["eval_action_rank_top1"] == rank["top1_agreement"]
    row = trainer.rows[-1]
    assert row["wm_loss_rew"] > 0 and row["wm_loss_con"] > 0  # reward and continuation heads are trained
    if "collect.balance_actions=true" in options:
        counts = trainer.action_counts
        assert int(counts.sum()) == cfg.collect.prefill_frames + cfg.collect.frames_per_iter
        inv = 1.0 / (1.0 + counts)
        torch.testing.assert_close(trainer.policy.explore_probs, inv / inv.sum())
    if "imagination.return_norm=percentile" in options:
        assert row["ppo_return_scale"] >= 1.0


def test_action_ranking_of_an_untrained_agent():
    """A constant-reward world model ranks nothing: imagined returns equal over actions, real ones differ."""
    torch.manual_seed(0)
    cfg = load_health_config(MLP_RECIPE, TINY)
    agent = build_agent(cfg)
    with torch.no_grad():
        agent.world_model.reward_head[-1].weight.zero_()
        agent.world_model.reward_head[-1].bias.fill_(0.1)
        agent.world_model.continue_head[-1].weight.zero_()
        agent.world_model.continue_head[-1].bias.fill_(10.0)
    out = action_ranking(agent, lambda primer: make_health_env(cfg, num_envs=2, seed=5, primer=primer), num_times=2)
    H = cfg.imagination.horizon
    assert out["seeds"] == 4 and out["imagined_return"] == [pytest.approx(0.1 * H, rel=1e-4)] * 5
    assert len(set(out["real_return"])) > 1
    assert math.isnan(out["spearman_mean"])  # a constant imagined ranking has no rank correlation


def test_summary_reports_the_run_as_a_fraction_of_the_oracle_and_the_rule(tmp_path):
    """The default eval.references: the oracle planner, the heart-rate rule and always-Continue on the run's own
    evaluation episodes; the fractions are the run's return over theirs."""
    torch.manual_seed(0)
    overrides = [*TINY, "collect.iterations=1", "eval.references=[oracle, hr_threshold, continue]"]
    cfg = load_health_config(MLP_RECIPE, overrides)
    summary = HealthTrainer(cfg, tmp_path / "run", structural=STRUCTURAL).train()
    refs = {name: evaluate_reference(cfg, name)["return_mean"] for name in ("oracle", "hr_threshold", "continue")}
    for name, ret in refs.items():
        assert summary[f"eval_ref_{name}_return"] == pytest.approx(ret)  # the same episodes, recomputed
    assert refs["oracle"] > refs["continue"]  # the planner searches over Continue too: it is not below it here
    agent = summary["eval_return_mean"]
    assert summary["eval_fraction_of_oracle"] == pytest.approx(agent / refs["oracle"])
    assert summary["eval_vs_hr_threshold"] == pytest.approx(agent / refs["hr_threshold"])
