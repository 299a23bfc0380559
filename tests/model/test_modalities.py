"""The modality registry: every entry builds, encodes any batch shape, and bad specs give one clear error line."""

from __future__ import annotations

import pytest
import torch
from torchrl.data import Bounded, Categorical, Composite, OneHot, Unbounded

from freamer_rl.errors import EnvSetupError
from freamer_rl.model.config import ModelConfig
from freamer_rl.model.factory import build_freamer
from freamer_rl.model.modalities import MODALITIES, EncoderContext, check_observation_keys, modality_keys

D = 16


def tiny_model(modalities, **kw) -> ModelConfig:
    cfg = ModelConfig(modalities=list(modalities), embed_dim=D, head_hidden=16, **kw)
    cfg.language.num_slots, cfg.language.heads = 2, 2
    cfg.vision.num_slots = 2
    cfg.state.channels, cfg.state.modes = 4, 4
    cfg.vector.hidden = 8
    cfg.flow.hidden, cfg.flow.steps = 8, 2
    cfg.fno.modes = 4
    cfg.dnc.memory_slots, cfg.dnc.memory_width = 4, 8
    return cfg


#: One valid unbatched spec per default key of every registry entry.
SPECS = {
    "grid": Bounded(low=0, high=torch.tensor([10, 5, 2]).expand(7, 7, 3).clone(), shape=(7, 7, 3), dtype=torch.int64),
    "direction": Categorical(4, shape=(), dtype=torch.int64),
    "pixels": Bounded(low=0, high=255, shape=(16, 16, 3), dtype=torch.uint8),
    "mission_tokens": Bounded(low=0, high=9, shape=(5,), dtype=torch.int64),
    "reward_history": Unbounded(shape=(4,), dtype=torch.float32),
    "observation": Unbounded(shape=(6,), dtype=torch.float32),
    "imu": Unbounded(shape=(36,), dtype=torch.float32),
    "hr_features": Unbounded(shape=(16,), dtype=torch.float32),
}


def test_registry_entries_are_complete():
    assert set(MODALITIES) >= {"state", "vision", "language", "reward", "vector"}
    for name, entry in MODALITIES.items():
        assert entry.kind in ("vector", "slots"), name
        assert all(k in SPECS for k in entry.default_keys), f"add a spec for {name}'s keys to SPECS"


@pytest.mark.parametrize("name", sorted(MODALITIES))
@pytest.mark.parametrize("batch", [(), (3,), (2, 3)])
def test_every_registry_entry_encodes(name, batch):
    entry = MODALITIES[name]
    cfg = tiny_model([name])
    keys = entry.default_keys
    obs_spec = Composite({k: SPECS[k] for k in keys}, shape=())
    check_observation_keys(obs_spec, cfg)
    enc = entry.build_encoder(EncoderContext(name, keys, tuple(SPECS[k] for k in keys), cfg))
    inputs = [SPECS[k].rand(batch) for k in keys]
    out = enc(*inputs)
    expected = (
        (*batch, cfg.language.num_slots if name == "language" else cfg.vision.num_slots, D)
        if entry.kind == "slots"
        else (*batch, D)
    )
    assert out.shape == expected
    assert torch.isfinite(out).all()


@pytest.mark.parametrize("name", sorted(MODALITIES))
def test_every_registry_entry_builds_a_policy(name):
    keys = MODALITIES[name].default_keys
    obs_spec = Composite({k: SPECS[k] for k in keys}, shape=())
    m = build_freamer(obs_spec, Categorical(3, shape=(), dtype=torch.int64), tiny_model([name]))
    td = obs_spec.rand((2,))
    td["is_init"] = torch.ones(2, 1, dtype=torch.bool)
    td["dnc", "memory"] = torch.zeros(2, 4, 8)
    out = m.policy(td)
    assert out["action"].shape == (2,)
    assert set(m.gates()) == {name}
    assert m.gates()[name] == pytest.approx(torch.sigmoid(torch.tensor(MODALITIES[name].gate_init)).item(), abs=1e-6)


def test_vector_modality_concatenates_several_keys():
    obs_spec = Composite(pos=Unbounded(shape=(3,)), vel=Unbounded(shape=(2, 2)), shape=())
    cfg = tiny_model(["vector"], observation_keys={"vector": ["pos", "vel"]})
    m = build_freamer(obs_spec, Categorical(2, shape=(), dtype=torch.int64), cfg)
    assert m.trunk[0].in_keys == ["pos", "vel"]
    td = obs_spec.rand((4,))
    assert m.trunk[0](td)["embed", "vector"].shape == (4, D)
    assert modality_keys("vector", cfg.observation_keys) == ("pos", "vel")


@pytest.mark.parametrize(
    "spec, keys, fragment",
    [
        (
            Composite(obs=Unbounded(shape=(3,)), shape=()),
            None,
            r"'vector' but .* no \['observation'\].*observation_keys",
        ),
        (
            Composite(observation=Categorical(2, shape=(), dtype=torch.bool), shape=()),
            None,
            r"'observation' with spec .*dtype=torch.bool.*expected a float or integer",
        ),
        (
            Composite(reward_history=Unbounded(shape=(2, 2)), shape=()),
            None,
            r"'reward_history'.*expected a float reward history",
        ),
        (
            Composite(pixels=Bounded(low=0, high=255, shape=(3, 8, 8), dtype=torch.uint8), shape=()),
            None,
            r"'pixels'.*shape=\(3, 8, 8\).*channels-last",
        ),
        (
            Composite(grid=Unbounded(shape=(7, 7, 3)), direction=Categorical(4, shape=()), shape=()),
            None,
            r"'grid'.*float32.*integer symbolic view",
        ),
        (Composite(a=Unbounded(shape=(3,)), shape=()), {"state": ["a"]}, r"observation_keys.state.*exactly 2 key"),
    ],
)
def test_bad_observation_specs_are_one_line(spec, keys, fragment):
    mods = (
        list(keys)
        if keys
        else [
            {"observation": "vector", "obs": "vector", "reward_history": "reward", "pixels": "vision", "grid": "state"}[
                next(iter(spec.keys()))
            ]
        ]
    )
    cfg = tiny_model(mods, observation_keys=keys or {})
    with pytest.raises(EnvSetupError, match=fragment) as err:
        build_freamer(spec, Categorical(2, shape=(), dtype=torch.int64), cfg)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "action_spec",
    [
        Categorical(3, shape=(2,), dtype=torch.int64),
        Composite(a=Categorical(2, shape=())),
        Bounded(low=0, high=3, shape=(2,), dtype=torch.int64),
        Categorical(3, shape=(1,), dtype=torch.int64),
        Bounded(low=-1.0, high=1.0, shape=()),
    ],
    ids=["multi-discrete", "composite", "integer-box", "categorical-[1]", "scalar-box"],
)
def test_action_spec_without_a_head_is_one_line(action_spec):
    obs_spec = Composite(observation=Unbounded(shape=(3,)), shape=())
    with pytest.raises(EnvSetupError, match="has no head: expected Categorical") as err:
        build_freamer(obs_spec, action_spec, tiny_model(["vector"]))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "action_spec, dist",
    [
        (Categorical(3, shape=(), dtype=torch.int64), "Categorical"),
        (OneHot(3), "OneHotCategorical"),
        (Bounded(low=-2.0, high=2.0, shape=(2,)), "TanhNormal"),
        (Unbounded(shape=(2,)), "IndependentNormal"),
        (Bounded(low=-1.0, high=1.0, shape=(2, 3)), "TanhNormal"),
    ],
)
@pytest.mark.parametrize("batch", [(), (4,)])
def test_heads_follow_the_action_spec(action_spec, dist, batch):
    obs_spec = Composite(observation=Unbounded(shape=(3,)), shape=())
    m = build_freamer(obs_spec, action_spec, tiny_model(["vector"]))
    td = obs_spec.rand(batch)
    td["is_init"] = torch.ones(*batch, 1, dtype=torch.bool)
    td["dnc", "memory"] = torch.zeros(*batch, 4, 8)
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    with set_exploration_type(ExplorationType.RANDOM):
        out = m.policy(td)
    assert type(m.actor.get_dist(out)).__name__ == dist
    assert out["action"].shape == (*batch, *action_spec.shape)
    assert action_spec.is_in(out["action"].to(action_spec.dtype))
    assert torch.isfinite(out["action_log_prob"]).all()
    assert out["action_log_prob"].shape == batch  # one log-prob per action, summed over its dims
    assert m.value(td)["state_value"].shape == (*batch, 1)


def test_vector_encoder_rejects_non_finite_input_but_not_under_vmap():
    from freamer_rl.layers.vector import VectorEncoder

    enc = VectorEncoder(3, D, hidden=8)
    x = torch.randn(4, 3)
    x[1, 2] = float("nan")
    with pytest.raises(ValueError, match="VectorEncoder input 0: 1 non-finite"):
        enc(x)
    clean = torch.randn(5, 4, 3)
    torch.testing.assert_close(torch.vmap(enc)(clean), enc(clean))
