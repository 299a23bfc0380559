"""Health observation encoders (Table 15 rows, Appendix J.2): shapes, step API, sequence == step-by-step for the
foundation encoder's DNC, and each one inside WorldModel.loss."""

import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.modules import set_recurrent_mode

from freamer_rl.health.encoders import (
    ENCODER_KINDS,
    FoundationHealthEncoder,
    make_health_encoder,
)
from freamer_rl.world_model import WorldModel

BATCH_SHAPES = [(), (2,), (3, 2)]
WM_LOSSES = {"loss_rec", "loss_kl", "loss_rew", "loss_con"}
E = 12


def tiny(kind: str):
    if kind == "mlp":
        return make_health_encoder(kind, E, hidden=16)
    if kind == "cnn":
        return make_health_encoder(kind, E, channels=4, hidden=16)
    if kind == "slotattn":
        return make_health_encoder(kind, E, dim=8, heads=2, hr_tokens=2, hidden=16)
    return make_health_encoder(
        kind,
        E,
        dim=8,
        heads=2,
        hr_tokens=2,
        hidden=16,
        fm_hidden=16,
        fm_steps=2,
        fno_modes=4,
        memory_slots=4,
        memory_width=6,
    )


def obs(shape):
    return {"imu": torch.randn(*shape, 36) * 3, "hr_features": torch.rand(*shape, 16)}


@pytest.mark.parametrize("kind", ENCODER_KINDS)
@pytest.mark.parametrize("shape", BATCH_SHAPES)
def test_shapes_and_step_api(kind, shape):
    enc = tiny(kind)
    o = obs(shape)
    state = enc.initial_state(shape)
    out, new_state = enc.step(o, state, torch.zeros(shape, dtype=torch.bool))
    assert out.shape == (*shape, E)
    assert torch.isfinite(out).all()
    assert set(new_state) == set(enc.state_shapes())
    for name, s in enc.state_shapes().items():
        assert new_state[name].shape == (*shape, *s)
    if kind != "foundation":
        torch.testing.assert_close(enc(o), out)
        assert enc.make_aux_loss() is None


@pytest.mark.parametrize("kind", ["mlp", "cnn", "slotattn"])
def test_plain_encoders_batch_consistent(kind):
    enc = tiny(kind).eval()
    o = obs((3, 2))
    full = enc(o)
    one = enc({k: v[1, 0] for k, v in o.items()})
    torch.testing.assert_close(full[1, 0], one, atol=1e-5, rtol=1e-5)


def test_bad_inputs_name_the_key():
    enc = tiny("mlp")
    with pytest.raises(ValueError, match="imu"):
        enc({"imu": torch.randn(2, 35), "hr_features": torch.randn(2, 16)})
    with pytest.raises(KeyError, match="hr_features"):
        enc({"imu": torch.randn(2, 36)})
    with pytest.raises(ValueError, match="batch dims"):
        enc({"imu": torch.randn(2, 36), "hr_features": torch.randn(3, 16)})
    with pytest.raises(ValueError, match="encoder kind"):
        make_health_encoder("transformer")
    with pytest.raises(ValueError, match="gate_init"):
        FoundationHealthEncoder(E, dim=8, heads=2, gate_init={"vision": 0.0})


def test_foundation_gate_init():
    enc = FoundationHealthEncoder(E, dim=8, heads=2, memory_slots=4, memory_width=6)
    assert enc.gates == pytest.approx({"imu": 1 / (1 + math.e), "heart_rate": 1 / (1 + math.e)})
    enc = FoundationHealthEncoder(E, dim=8, heads=2, memory_slots=4, memory_width=6, gate_init={"imu": -3.0})
    assert enc.refiners["imu"].alpha.item() == -3.0 and enc.refiners["heart_rate"].alpha.item() == -1.0


def _is_init(lead, T):
    first = torch.zeros(*lead, T, dtype=torch.bool)
    first[..., 0] = True
    flat = first.reshape(-1, T)
    for i in range(flat.shape[0]):  # a reset somewhere in the middle, at a different step per sequence
        flat[i, 1 + (2 * i) % (T - 1)] = True
    return flat.reshape(*lead, T)


@pytest.mark.parametrize("lead", [(2,), (3, 2)])
def test_foundation_sequence_equals_steps(lead):
    torch.manual_seed(0)
    enc = tiny("foundation")
    T = 6
    o = obs((*lead, T))
    is_init = _is_init(lead, T)
    with torch.no_grad():
        seq, mems = enc.encode_sequence(o, is_init)
        state = enc.initial_state(lead)
        outs = []
        for t in range(T):
            out, state = enc.step({k: v[..., t, :] for k, v in o.items()}, state, is_init[..., t])
            outs.append(out)
            torch.testing.assert_close(mems[..., t, :, :], state["memory"], atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(seq, torch.stack(outs, dim=-2), atol=1e-5, rtol=1e-5)
        # the TensorDict path (what WorldModel.embed calls): recurrent mode without a memory key
        td = TensorDict({**o, "is_init": is_init.unsqueeze(-1)}, batch_size=(*lead, T))
        with set_recurrent_mode(True):
            enc(td)
        torch.testing.assert_close(td["obs_embed"], seq, atol=1e-5, rtol=1e-5)
        assert td["next", "dnc", "memory"].shape == (*lead, T, 4, 6)
    # a reset really forgets: changing the steps before a reset does not change the output after it
    o2 = {k: v.clone() for k, v in o.items()}
    o2["imu"][..., 0, :] += 5.0
    flat_init = is_init.reshape(-1, T)
    r = int(flat_init[0, 1:].nonzero()[0]) + 1  # first reset after t=0 of sequence 0
    with torch.no_grad():
        seq2, _ = enc.encode_sequence(o2, is_init)
    torch.testing.assert_close(seq2.reshape(-1, T, E)[0, r:], seq.reshape(-1, T, E)[0, r:])
    assert not torch.allclose(seq2.reshape(-1, T, E)[0, :r], seq.reshape(-1, T, E)[0, :r])


def test_foundation_td_step_mode_and_errors():
    enc = tiny("foundation")
    o = obs((3,))
    mem = torch.randn(3, 4, 6) * 0.1
    td = TensorDict({**o, "is_init": torch.tensor([[True], [False], [False]]), ("dnc", "memory"): mem}, [3])
    with torch.no_grad():
        enc(td)
        ref, st = enc.step(o, {"memory": mem}, torch.tensor([True, False, False]))
    torch.testing.assert_close(td["obs_embed"], ref)
    torch.testing.assert_close(td["next", "dnc", "memory"], st["memory"])
    # explicit recurrent mode: [B, T] starting from the stored memory at t = 0
    tdseq = TensorDict(
        {
            **obs((3, 4)),
            "is_init": torch.zeros(3, 4, 1, dtype=torch.bool),
            ("dnc", "memory"): mem.unsqueeze(1).expand(3, 4, 4, 6).clone(),
        },
        [3, 4],
    )
    with torch.no_grad(), set_recurrent_mode(True):
        enc(tdseq)
        ref_seq, _ = enc.encode_sequence(
            {k: tdseq[k] for k in ("imu", "hr_features")}, torch.zeros(3, 4, dtype=torch.bool), mem
        )
    torch.testing.assert_close(tdseq["obs_embed"], ref_seq)
    with pytest.raises(KeyError, match="is_init"):
        enc(TensorDict(obs((3,)), [3]))
    with pytest.raises(KeyError, match="embed"):  # no hidden cache: the loss reads a tensordict the trunk wrote
        tiny("foundation").make_aux_loss()(TensorDict(obs((3,)), [3]))


@pytest.mark.parametrize("kind", ENCODER_KINDS)
def test_plugs_into_world_model_loss(kind):
    torch.manual_seed(0)
    enc = tiny(kind)
    wm = WorldModel({"imu": 36, "hr_features": 16}, 5, encoder=enc, embed_dim=E, deter_dim=16, stoch_dim=4, hidden=16)
    B, T = 3, 5
    batch = TensorDict(
        {
            **obs((B, T)),
            "action": torch.randint(0, 5, (B, T)),
            "next": {
                **obs((B, T)),
                "reward": torch.randn(B, T, 1),
                "done": torch.zeros(B, T, 1, dtype=torch.bool),
                "terminated": torch.zeros(B, T, 1, dtype=torch.bool),
            },
        },
        [B, T],
    )
    aux_loss = enc.make_aux_loss(lambda_fm=0.1, lambda_smooth=1e-3)  # FreamerAuxLoss on the encoder's tensordict
    losses, latents = wm.loss(batch, return_latents=True, aux_loss=aux_loss)
    total = losses["total"]  # includes 0.1 * L_FM + 1e-3 * L_smooth
    if kind == "foundation":
        aux = {k: v for k, v in losses.items() if k.startswith("loss_") and k not in WM_LOSSES}
        assert set(aux) == {"loss_fm", "loss_smooth"}
        assert all(torch.isfinite(v) for v in aux.values())
    total.backward()
    assert torch.isfinite(total)
    assert latents.batch_size == (B * (T + 1),)
    grads = [p.grad for p in enc.parameters() if p.requires_grad]
    assert any(g is not None and g.abs().sum() > 0 for g in grads)
    if kind == "foundation":  # the FM velocity fields learn from L_FM
        vel = enc.refiners["imu"].net[-1].weight.grad
        assert vel is not None and vel.abs().sum() > 0


def test_foundation_loads_checkpoints_of_the_former_hand_wired_encoder():
    """State dicts written before the shared trunk (names stage1.*, refiners.<m>.*, fuser.*, dnc.*) still load."""
    enc = tiny("foundation")
    legacy = {
        "stage1.site_embed": torch.full((3, 8), 0.5),
        "refiners.heart_rate.alpha": torch.tensor(2.0),
        "fuser.residual_scale": torch.tensor(0.7),
        "dnc.out.bias": torch.full((E,), 0.25),
    }
    result = enc.load_state_dict(legacy, strict=False)
    assert not result.unexpected_keys
    assert torch.equal(enc.stage1.site_embed, legacy["stage1.site_embed"])
    assert enc.refiners["heart_rate"].alpha.item() == 2.0
    assert enc.fuser.residual_scale.item() == pytest.approx(0.7)
    assert torch.equal(enc.dnc.dnc.out.bias, legacy["dnc.out.bias"])
