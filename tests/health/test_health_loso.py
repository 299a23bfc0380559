"""Leave-one-subject-out for health (issue 22, part 3): eval.subjects validation, held-out evaluation envs (trained
policies, reference policies, the oracle's ceiling table), subjects with their own activity plans, the default
subjects' numbers pinned, the LOSO suite's folds and a tiny fold trained end to end."""

import json
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from torchrl.envs.utils import step_mdp

from freamer_rl.data import ACTIVITY_MET, PROTOCOL_SUBJECTS, subject_profiles, synthetic_recording
from freamer_rl.data.subject_profiles import (
    SUBJECT_PROFILES,
    plan_statistics,
    profile_recording,
    profile_timeline,
)
from freamer_rl.errors import ConfigError
from freamer_rl.experiments.suite import plan_suite
from freamer_rl.health import evaluation
from freamer_rl.health.agent import make_health_env as cfg_env
from freamer_rl.health.config import HealthConfig, health_config_from_dict, load_health_config
from freamer_rl.health.evaluation import eval_subjects, make_eval_env
from freamer_rl.health.reference import ceiling_table, reference_rollout
from freamer_rl.run import env_registry
from freamer_rl.trainers.health import train as train_health
from freamer_rl.trainers.registry import load_recipe

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_health_pipeline import TINY as PIPELINE_TINY  # noqa: E402

from freamer_rl_envs.health import VARIED_ENV_ID, make_health_env

ROOT = Path(__file__).resolve().parents[2]
LOSO = ROOT / "recipes" / "suites" / "health_loso.yaml"
VARIED = {"env": {"id": VARIED_ENV_ID, "synthetic_duration_s": 600.0, "episode_length": 48}}
LEVELS = ("low", "moderate", "high")
SMALL_EVAL = {"num_envs": 2, "horizon_context": 4, "horizon_max": 8}


@pytest.fixture(autouse=True)
def health_adapter(monkeypatch):
    """Use the registered ``health`` entry point; until the project is reinstalled with it, register it here."""
    if "health" not in env_registry.available_adapters():
        orig = env_registry.get_env_factory
        monkeypatch.setattr(env_registry, "get_env_factory", lambda a: make_health_env if a == "health" else orig(a))


def _cfg(train, held_out, **env) -> HealthConfig:
    return health_config_from_dict(
        {
            "env": {**VARIED["env"], "subjects": train, **env},
            "eval": {**SMALL_EVAL, "subjects": held_out},
            "world_model": {"seq_len": 12},
        }
    )


# -- config ----------------------------------------------------------------------------------------------------------
def test_held_out_subject_in_training_list_is_refused_in_one_line_naming_both_fields():
    with pytest.raises(ConfigError) as err:
        _cfg([101, 102, 103], [103])
    msg = str(err.value)
    assert "\n" not in msg and "eval.subjects" in msg and "env.subjects" in msg and "[103]" in msg and "leak" in msg


@pytest.mark.parametrize(
    ("train", "held_out", "field", "words"),
    [
        ([101, 110], None, "env.subjects", "101..109"),
        ([101, 102], [100], "eval.subjects", "[100]"),
        ([101, 101], None, "env.subjects", "twice"),
        ([101, 102], [], "eval.subjects", "empty"),
        (None, [104], "eval.subjects", "env.subjects listed"),
    ],
)
def test_bad_subject_lists_are_refused_naming_the_field(train, held_out, field, words):
    with pytest.raises(ConfigError, match=re.escape(field)) as err:
        _cfg(train, held_out)
    assert words in str(err.value)


def test_varied_subjects_with_real_data_are_refused(tmp_path):
    with pytest.raises(ConfigError, match="env.data_dir"):
        _cfg([101, 102], None, data_dir=str(tmp_path))
    with pytest.raises(ValueError, match="data_dir"):
        make_health_env(VARIED_ENV_ID, data_dir=str(tmp_path))


def test_eval_subjects_default_to_the_training_subjects():
    assert eval_subjects(HealthConfig()) is None  # the env's default set, as before
    cfg = _cfg([101, 102], None)
    assert eval_subjects(cfg) == [101, 102]
    assert eval_subjects(_cfg([101, 102], [105])) == [105]


# -- held-out evaluation ---------------------------------------------------------------------------------------------
def test_eval_env_draws_only_the_held_out_subject():
    cfg = _cfg([101, 102, 104], [109])
    env = make_eval_env(cfg, num_envs=6, seed=0)
    env.reset()
    assert env.base_env.subjects == (109,) and env.base_env.subject_index.tolist() == [0] * 6
    train = cfg_env(cfg, num_envs=64, seed=0)  # the training env draws among its three
    train.reset()
    assert train.base_env.subjects == (101, 102, 104) and set(train.base_env.subject_index.tolist()) == {0, 1, 2}


def _spy_eval_envs(monkeypatch) -> list:
    """The envs built by make_eval_env from now on (in order)."""
    built = []

    def spy(cfg, **kwargs):
        env = cfg_env(cfg, **kwargs)
        built.append(env)
        return env

    monkeypatch.setattr(evaluation, "make_health_env", spy)
    return built


def test_reference_policies_and_the_oracle_run_on_the_held_out_subject(monkeypatch):
    """Subject 109's plan has no activity above 3.5 MET, the training subjects run, cycle and play soccer: an
    always-Continue evaluation shows only 109's activities; the ceiling table's policies all roll on 109."""
    built = _spy_eval_envs(monkeypatch)
    cfg = _cfg([104, 106, 108], [109])
    traj = reference_rollout(cfg, "continue", num_envs=8)
    assert [e.base_env.subjects for e in built] == [(109,)]
    seen = set(traj.get(("next", "activity")).unique().tolist())
    allowed = {a for a, _ in SUBJECT_PROFILES[109].plan} | {0}
    assert seen <= allowed and seen & {a for a, _ in SUBJECT_PROFILES[109].plan}
    rows = ceiling_table(cfg, ("oracle", "continue"), num_envs=2, resamples=50, horizon=4, depth=1)
    assert [e.base_env.subjects for e in built[1:]] == [(109,), (109,)] and len(rows) == 2
    assert rows[0]["fraction_of_oracle"] == pytest.approx(1.0)


# -- subjects with their own plans -----------------------------------------------------------------------------------
def test_plan_statistics_match_the_documented_table():
    table = re.findall(r"^(1\d\d)\s+(low|moderate|high)\s+.*?\s+(\d\.\d)\s+(\d\.\d\d)$", subject_profiles.__doc__, re.M)
    assert [int(r[0]) for r in table] == list(PROTOCOL_SUBJECTS)
    for subject, level, mean_met, share in table:
        stats = plan_statistics(int(subject))
        assert SUBJECT_PROFILES[int(subject)].level == level
        assert f"{stats['mean_met']:.1f}" == mean_met and f"{stats['vigorous_share']:.2f}" == share
    # the levels order the plans: every high plan is more intense than every low one
    met = {
        lvl: [plan_statistics(s)["mean_met"] for s, p in SUBJECT_PROFILES.items() if p.level == lvl] for lvl in LEVELS
    }
    assert max(met["low"]) < min(met["moderate"]) and max(met["moderate"]) < min(met["high"])


def test_profile_recording_follows_the_plan_with_the_subjects_own_physiology():
    rec = profile_recording(106, duration_s=300.0, seed=2)
    protocol = synthetic_recording(106, duration_s=300.0, seed=2)
    for key in ("hr_rest", "hr_gain", "tau_hr", "fatigue_drift"):
        assert rec.info[key] == protocol.info[key]  # drawn before the timeline: the same heart under any mix
    assert set(np.unique(rec.activity).tolist()) <= {a for a, _ in SUBJECT_PROFILES[106].plan} | {0}
    assert 20 in rec.activity and 20 not in protocol.activity  # 106 plays soccer; the protocol has none
    segs = profile_timeline(106, 300.0, seed=2)
    assert segs == rec.info["segments"] and sum(d for _, d in segs) >= 300.0
    assert [a for a, _ in segs[1::2]][:3] == [a for a, _ in SUBJECT_PROFILES[106].plan][:3]
    assert profile_timeline(106, 300.0, seed=3) != segs and rec.info["activity_level"] == "high"


def test_varied_env_gives_subjects_their_own_activity_mix():
    env = make_health_env(VARIED_ENV_ID, subjects=[103, 104], synthetic_duration_s=600.0, rate_hz=0.2, seed=0)
    tables = env._tables
    met = np.array([ACTIVITY_MET.get(a, ACTIVITY_MET[0]) for a in range(25)])
    mean_met = [met[tables.activity[i, : tables.length[i]]].mean() for i in range(2)]
    assert mean_met[1] > mean_met[0] + 1.5  # the runner (104, high) vs the sedentary subject (103, low)
    protocol = make_health_env(subjects=[103, 104], synthetic_duration_s=600.0, rate_hz=0.2, seed=0)._tables
    np.testing.assert_array_equal(protocol.hr_rest, tables.hr_rest)  # same physiology, other activities
    assert not np.array_equal(protocol.activity, tables.activity)


#: (episode reward sums after 40 steps, last heart rates) per env, recorded before this change
PINNED_DIRECT = (
    [14.940195083618164, 26.645126342773438, 4.888749122619629, 1.1309263706207275],
    [82.80845642089844, 74.52371215820312, 74.60470581054688, 84.59513092041016],
)
PINNED_EVAL = (
    [22.25740623474121, 19.019691467285156, 15.049233436584473, 16.244483947753906],
    [67.71849822998047, 68.28753662109375, 65.22570037841797, 93.8586196899414],
)


def _pinned_rollout(env, steps=40):
    g = torch.Generator().manual_seed(7)
    td = env.reset()
    subject_index = env.base_env.subject_index if hasattr(env, "base_env") else env.subject_index
    rewards, hr = [], []
    for _ in range(steps):
        td.set("action", torch.randint(0, 5, (env.batch_size[0],), generator=g))
        td = env.step(td)
        rewards.append(td["next", "reward"].squeeze(-1))
        hr.append(td["next", "heart_rate"].squeeze(-1))
        td = step_mdp(td)
    return subject_index.tolist(), torch.stack(rewards, 1).sum(1).tolist(), torch.stack(hr, 1)[:, -1].tolist()


def test_default_subjects_give_the_numbers_recorded_before_loso():
    """Recorded on the code before eval.subjects and the subject plans (fixed seeds, random actions seed 7)."""
    idx, ret, hr = _pinned_rollout(make_health_env(batch_size=4, seed=3, rate_hz=0.2, episode_length=120))
    assert idx == [1, 2, 1, 0]
    np.testing.assert_allclose(ret, PINNED_DIRECT[0], rtol=1e-5)
    np.testing.assert_allclose(hr, PINNED_DIRECT[1], rtol=1e-6)
    cfg = HealthConfig()  # the config path: the evaluation env of a default config
    idx, ret, hr = _pinned_rollout(make_eval_env(cfg, num_envs=4))
    assert idx == [0, 0, 0, 0]
    np.testing.assert_allclose(ret, PINNED_EVAL[0], rtol=1e-5)
    np.testing.assert_allclose(hr, PINNED_EVAL[1], rtol=1e-6)


# -- the suite -------------------------------------------------------------------------------------------------------
def test_loso_suite_plans_nine_folds_per_encoder(tmp_path):
    suite, _, runs = plan_suite(LOSO, tmp_path / "out")
    assert [r.error for r in runs if r.error] == [] and len(runs) == 9 * 2 * 5 and suite.seeds == [0, 1, 2, 3, 4]
    folds: dict[str, set[int]] = {}
    for run in runs[:: len(suite.seeds)]:  # one config per entry
        _, cfg = load_recipe(run.recipe, run.overrides)
        (held_out,) = cfg.eval.subjects
        assert sorted([*cfg.env.subjects, held_out]) == list(PROTOCOL_SUBJECTS)
        assert cfg.env.id == VARIED_ENV_ID and cfg.env.data_dir is None
        assert run.label == f"{cfg.encoder.kind}_fold{held_out}"
        folds.setdefault(cfg.encoder.kind, set()).add(held_out)
    assert folds == {"mlp": set(PROTOCOL_SUBJECTS), "foundation": set(PROTOCOL_SUBJECTS)}


# the pipeline tests' tiny sizes, on the varied subjects, one iteration
TINY = [*PIPELINE_TINY, f"env.id={VARIED_ENV_ID}", "env.synthetic_duration_s=600", "collect.iterations=1"]


def test_tiny_loso_fold_trains_evaluates_on_the_held_out_subject_and_records_it(tmp_path, monkeypatch):
    cfg = load_health_config(
        ROOT / "recipes" / "health" / "health_mlp.yaml", [*TINY, "env.subjects=[102, 104]", "eval.subjects=[101]"]
    )
    built = _spy_eval_envs(monkeypatch)
    summary = train_health(cfg, tmp_path / "run")
    # the final evaluation, the action-ranking diagnostic and each eval.references policy, all on the held-out subject
    assert len(built) == 2 + len(cfg.eval.references) and all(env.base_env.subjects == (101,) for env in built)
    on_disk = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert on_disk["train_subjects"] == [102, 104] and on_disk["eval_subjects"] == [101]
    assert np.isfinite(summary["eval_return_mean"]) and summary["eval_episodes"] == 2
