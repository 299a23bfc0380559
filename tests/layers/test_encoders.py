"""Layer 1 encoders (Section 3.2, Appendix E): reward, language, CNN/CLIP vision, cross-modal attention, pooling."""

import sys

import pytest
import torch
from tensordict import TensorDict
from tensordict.nn import TensorDictModule

from freamer_rl.layers.encoders import (
    CNNBackbone,
    CrossModalAttention,
    LanguageEncoder,
    RewardEncoder,
    SlotPool,
    VisionEncoder,
)

BATCH_SHAPES = [(), (2,), (3, 2)]
D = 32


def require_open_clip():
    """open_clip through the library's importer (which copes with a CUDA torchvision beside CPU torch), or skip."""
    from freamer_rl.layers.clip_backbone import ClipNotInstalledError, import_open_clip

    try:
        return import_open_clip()
    except ClipNotInstalledError as err:
        pytest.skip(f"CLIP unavailable here: {err}")


def _assert_all_grads(module, skip=()):
    for name, p in module.named_parameters():
        if not p.requires_grad or any(name.startswith(s) for s in skip):
            continue
        assert p.grad is not None, name
        assert torch.isfinite(p.grad).all(), name
        assert p.grad.abs().sum() > 0, name


# ---------------------------------------------------------------------------------------------------- reward
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_reward_encoder_shapes_and_grads(batch):
    enc = RewardEncoder(history=8, out_dim=D, channels=4, kernel=3)
    out = enc(torch.randn(*batch, 8))
    assert out.shape == (*batch, D) and enc.out_dim == D
    out.square().sum().backward()
    _assert_all_grads(enc)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_reward_encoder_symlog_squashes_the_rewards_before_the_conv(batch):
    torch.manual_seed(0)
    plain = RewardEncoder(history=8, out_dim=D, channels=4)
    squashed = RewardEncoder(history=8, out_dim=D, channels=4, symlog=True)
    squashed.load_state_dict(plain.state_dict())  # no new parameters: the same weights fit both
    r = -16 * torch.rand(*batch, 8)  # Pendulum's reward range
    torch.testing.assert_close(squashed(r), plain(torch.sign(r) * torch.log1p(r.abs())))
    torch.testing.assert_close(squashed(torch.zeros(*batch, 8)), plain(torch.zeros(*batch, 8)))  # symlog(0) = 0
    assert squashed(r).abs().max() < plain(r).abs().max()  # 16 -> 2.8: the embedding no longer grows with |r|
    torch.testing.assert_close(torch.vmap(squashed)(r.reshape(-1, 8)), squashed(r).reshape(-1, D))


def test_reward_encoder_checks_history():
    with pytest.raises(ValueError, match=r"\[\*B, 8\]"):
        RewardEncoder(history=8, out_dim=D)(torch.randn(2, 5))


def test_reward_encoder_rejects_non_finite_except_under_vmap():
    enc = RewardEncoder(history=8, out_dim=D, channels=4)
    r = torch.randn(3, 8)
    r[0, 1], r[2, 0], r[2, 7] = float("nan"), float("inf"), -float("inf")
    with pytest.raises(ValueError, match=r"RewardEncoder reward_history: 3 non-finite values \(NaN/Inf\)") as err:
        enc(r)
    assert "\n" not in str(err.value) and "nan_to_num" in str(err.value)
    out = torch.vmap(enc)(r)  # maths only: the row with the NaN is NaN, the check is not run
    assert torch.isnan(out[0]).all() and torch.isfinite(out[1]).all()


# -------------------------------------------------------------------------------------------------- language
def _tokens(batch, length=8, vocab=20):
    t = torch.randint(1, vocab, (*batch, length))
    t[..., 5:] = 0  # trailing padding
    return t


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_language_encoder_shapes_and_grads(batch):
    enc = LanguageEncoder(vocab_size=20, out_dim=D, num_slots=3, layers=1, heads=4, max_len=8)
    out = enc(_tokens(batch))
    assert out.shape == (*batch, 3, D)
    assert (enc.num_slots, enc.slot_dim, enc.out_dim) == (3, D, D)
    out.square().mean().backward()
    # the padding row of the embedding gets no gradient by construction (padding_idx=0)
    _assert_all_grads(enc)


@pytest.mark.parametrize("training", [True, False])
def test_language_encoder_all_padding_rows_are_finite(training):
    enc = LanguageEncoder(vocab_size=20, out_dim=D, num_slots=3, max_len=8).train(training)
    tokens = _tokens((4,))
    tokens[1] = 0
    tokens[3] = 0
    out = enc(tokens)
    assert torch.isfinite(out).all()
    out.sum().backward()
    for name, p in enc.named_parameters():
        assert p.grad is None or torch.isfinite(p.grad).all(), name
    assert enc.slot_attention.nan_fallbacks == 0


def test_language_encoder_ignores_trailing_padding():
    enc = LanguageEncoder(vocab_size=20, out_dim=D, num_slots=3, max_len=12).eval()
    short = torch.randint(1, 20, (3, 5))
    padded = torch.cat([short, torch.zeros(3, 7, dtype=torch.long)], dim=-1)
    torch.testing.assert_close(enc(padded), enc(short), rtol=1e-5, atol=1e-5)


def test_language_encoder_errors():
    enc = LanguageEncoder(vocab_size=20, out_dim=D, max_len=8)
    with pytest.raises(ValueError, match="max_len=8"):
        enc(torch.ones(2, 9, dtype=torch.long))
    with pytest.raises(ValueError, match=r"\[0, 20\)"):
        enc(torch.full((2, 4), 20))
    with pytest.raises(TypeError, match="integer"):
        enc(torch.ones(2, 4))


# ------------------------------------------------------------------------------------------------ CNN / vision
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_cnn_backbone_accepts_uint8(batch):
    bb = CNNBackbone(in_channels=3, out_dim=16)
    px = torch.randint(0, 256, (*batch, 56, 56, 3), dtype=torch.uint8)
    tokens = bb(px)
    assert tokens.shape == (*batch, 49, 16) and bb.token_dim == 16
    torch.testing.assert_close(bb(px.float()), tokens)  # float pixels use the same 0-255 scale


def test_cnn_backbone_other_sizes_and_errors():
    bb = CNNBackbone(out_dim=16)
    assert bb(torch.zeros(2, 64, 48, 3, dtype=torch.uint8)).shape == (2, 8 * 6, 16)
    with pytest.raises(ValueError, match="channels-last"):
        bb(torch.zeros(2, 3, 56, 56, dtype=torch.uint8))


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_vision_encoder_cnn_shapes_and_grads(batch):
    enc = VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, num_slots=5, slot_iters=2)
    out = enc(torch.randint(0, 256, (*batch, 56, 56, 3), dtype=torch.uint8))
    assert out.shape == (*batch, 5, D)
    assert (enc.num_slots, enc.slot_dim, enc.out_dim) == (5, D, D)
    assert torch.isfinite(out).all()
    out.square().mean().backward()
    _assert_all_grads(enc)


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_vision_encoder_flatten_keeps_every_token_in_place(batch):
    """``pooling="flatten"``: one slot, a Linear of the flattened 7x7 token grid; moving one token's content to another
    cell changes the output (Slot Attention with the same tokens is only as position-aware as its embedding)."""
    enc = VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, pooling="flatten", num_tokens=49)
    assert not hasattr(enc, "slot_attention") and enc.num_slots == 1
    assert enc.flat.in_features == 49 * 16
    out = enc(torch.randint(0, 256, (*batch, 56, 56, 3), dtype=torch.uint8))
    assert out.shape == (*batch, 1, D)
    out.square().mean().backward()
    _assert_all_grads(enc)
    tokens = torch.randn(1, 49, 16)
    swapped = tokens[:, torch.arange(49).roll(1)]
    assert not torch.allclose(enc.flat(tokens.flatten(1)), enc.flat(swapped.flatten(1)))


def test_vision_encoder_flatten_needs_its_token_count():
    with pytest.raises(ValueError, match="pooling 'flatten' needs the backbone's token count"):
        VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, pooling="flatten")
    with pytest.raises(ValueError, match="expected one of slots, flatten, got 'max'"):
        VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, pooling="max")
    enc = VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, pooling="flatten", num_tokens=49)
    with pytest.raises(ValueError, match=r"built for 49 tokens, the backbone gave 64 \(pixels \(64, 64, 3\)\)"):
        enc(torch.zeros(2, 64, 64, 3, dtype=torch.uint8))


def test_vision_encoder_needs_token_dim():
    with pytest.raises(TypeError, match="token_dim"):
        VisionEncoder(torch.nn.Identity(), out_dim=D)


def test_vision_encoder_rejects_non_finite_pixels_and_tokens():
    torch.manual_seed(0)
    enc = VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, num_slots=4).eval()  # eval: no random slot init
    px = torch.rand(2, 16, 16, 3) * 255
    px[1, 3, 4, 0] = float("nan")
    with pytest.raises(ValueError, match="CNNBackbone pixels: 1 non-finite values"):
        enc(px)
    with pytest.raises(ValueError, match="CNNBackbone pixels: 1 non-finite values"):
        enc.backbone(px)
    out = torch.vmap(enc)(px)  # no check under vmap; the NaN stays in its own sample
    assert torch.isfinite(out[0]).all() and torch.isnan(out[1]).any()

    class NaNTokens(torch.nn.Module):  # a backbone whose features are non-finite for one token
        token_dim = 8

        def forward(self, pixels):
            tokens = torch.ones(pixels.shape[0], 5, 8)
            tokens[-1, 2, 0] = float("nan")
            return tokens

    enc2 = VisionEncoder(NaNTokens(), out_dim=D, num_slots=3)
    with pytest.raises(ValueError, match=r"VisionEncoder tokens \(from NaNTokens\): 1 non-finite"):
        enc2(torch.zeros(2, 4, 4, 3, dtype=torch.uint8))


def test_vision_encoder_blank_frames_are_finite():
    enc = VisionEncoder(CNNBackbone(out_dim=16), out_dim=D, num_slots=4)
    for px in (torch.zeros(2, 56, 56, 3, dtype=torch.uint8), torch.full((2, 56, 56, 3), 255, dtype=torch.uint8)):
        assert torch.isfinite(enc(px)).all()


# ------------------------------------------------------------------------------------------- cross-modal, pool
@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_cross_modal_attention_shapes_and_grads(batch):
    xattn = CrossModalAttention(D, heads=4)
    vis = torch.randn(*batch, 6, D, requires_grad=True)
    lang = torch.randn(*batch, 3, D, requires_grad=True)
    v2, l2 = xattn(vis, lang)
    assert v2.shape == vis.shape and l2.shape == lang.shape
    (v2.square().sum() + l2.square().sum()).backward()
    _assert_all_grads(xattn)


def test_cross_modal_attention_is_residual_and_bidirectional():
    xattn = CrossModalAttention(D, heads=4)
    vis, lang = torch.randn(2, 6, D), torch.randn(2, 3, D)
    v2, l2 = xattn(vis, lang)
    # Eq. A21 / A22, both computed from the *input* slots
    torch.testing.assert_close(v2, vis + xattn.vis_from_lang(vis, lang, lang)[0])
    torch.testing.assert_close(l2, lang + xattn.lang_from_vis(lang, vis, vis)[0])
    with torch.no_grad():
        xattn.vis_from_lang.out_proj.weight.zero_()
        xattn.vis_from_lang.out_proj.bias.zero_()
    v3, l3 = xattn(vis, lang)
    torch.testing.assert_close(v3, vis)  # MHA == 0 leaves only the residual
    torch.testing.assert_close(l3, l2)


def test_cross_modal_attention_batch_mismatch():
    with pytest.raises(ValueError, match="batch dims differ"):
        CrossModalAttention(D)(torch.randn(2, 6, D), torch.randn(3, 3, D))


@pytest.mark.parametrize("batch", BATCH_SHAPES)
def test_slot_pool(batch):
    slots = torch.randn(*batch, 5, D)
    out = SlotPool()(slots)
    assert out.shape == (*batch, D)
    torch.testing.assert_close(out, slots.mean(-2))


def test_tensordict_wrapping_like_the_factory():
    """The modules drop into TensorDictModule with a [3, 2] batch, as the factory wires them."""
    td = TensorDict(
        {
            "pixels": torch.randint(0, 256, (3, 2, 56, 56, 3), dtype=torch.uint8),
            "mission_tokens": _tokens((3, 2)),
            "reward_history": torch.randn(3, 2, 8),
        },
        batch_size=[3, 2],
    )
    steps = [
        TensorDictModule(RewardEncoder(8, D), in_keys=["reward_history"], out_keys=[("embed", "reward")]),
        TensorDictModule(
            LanguageEncoder(20, D, num_slots=3, max_len=8), in_keys=["mission_tokens"], out_keys=[("slots", "language")]
        ),
        TensorDictModule(
            VisionEncoder(CNNBackbone(out_dim=16), D, num_slots=4), in_keys=["pixels"], out_keys=[("slots", "vision")]
        ),
        TensorDictModule(
            CrossModalAttention(D),
            in_keys=[("slots", "vision"), ("slots", "language")],
            out_keys=[("slots", "vision"), ("slots", "language")],
        ),
        TensorDictModule(SlotPool(), in_keys=[("slots", "vision")], out_keys=[("embed", "vision")]),
        TensorDictModule(SlotPool(), in_keys=[("slots", "language")], out_keys=[("embed", "language")]),
    ]
    for step in steps:
        td = step(td)
    assert td["slots", "vision"].shape == (3, 2, 4, D)
    assert td["slots", "language"].shape == (3, 2, 3, D)
    for m in ("reward", "vision", "language"):
        assert td["embed", m].shape == (3, 2, D)


def test_default_sizes_parameter_counts():
    """Paper sizes (d=128, K=8): the trainable parameter counts reported to the lead."""

    def n(m):
        return sum(p.numel() for p in m.parameters() if p.requires_grad)

    from freamer_rl.layers.slot_attention import SlotAttention

    assert n(SlotAttention(8, 128)) == 182_272
    assert n(CrossModalAttention(128, heads=4)) == 132_096
    assert n(RewardEncoder(8, 128)) == 16_576


# ----------------------------------------------------------------------------------------------------- CLIP
def test_clip_backbone_without_open_clip(monkeypatch):
    from freamer_rl.errors import FreamerError
    from freamer_rl.layers.clip_backbone import ClipBackbone, ClipNotInstalledError, ClipWeightsError

    monkeypatch.setitem(sys.modules, "open_clip", None)  # makes `import open_clip` fail
    with pytest.raises(ClipNotInstalledError) as info:
        ClipBackbone(pretrained=None, allow_random_weights=True)
    assert str(info.value) == "open_clip is not installed: pip install 'freamer_rl[clip]'"
    assert isinstance(info.value, ImportError) and isinstance(info.value, ClipWeightsError)
    assert isinstance(info.value, FreamerError)


@pytest.fixture(scope="module")
def random_clip():
    require_open_clip()
    from freamer_rl.layers.clip_backbone import ClipBackbone

    torch.manual_seed(0)
    return ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=None, allow_random_weights=True)


@pytest.mark.parametrize("batch", [(), (2,), (1, 2)])
def test_clip_backbone_tokens(random_clip, batch):
    px = torch.randint(0, 256, (*batch, 56, 56, 3), dtype=torch.uint8)
    tokens = random_clip(px)
    assert tokens.shape == (*batch, 49, 768) and tokens.dtype == torch.float32
    assert not tokens.requires_grad and torch.isfinite(tokens).all()
    assert random_clip.token_dim == 768 and random_clip.num_tokens == 49


def test_clip_backbone_rejects_non_finite_pixels(random_clip):
    px = torch.full((2, 32, 32, 3), 100.0)
    px[0, 1, 1, 1] = float("nan")
    with pytest.raises(ValueError, match="ClipBackbone pixels: 1 non-finite values"):
        random_clip(px)


def test_clip_backbone_is_frozen(random_clip):
    assert not any(p.requires_grad for p in random_clip.parameters())
    random_clip.train()
    assert not random_clip.visual.training
    enc = VisionEncoder(random_clip, out_dim=D, num_slots=4)
    out = enc(torch.randint(0, 256, (2, 56, 56, 3), dtype=torch.uint8))
    assert out.shape == (2, 4, D)
    out.sum().backward()
    _assert_all_grads(enc)
    assert all(p.grad is None for p in random_clip.parameters())


def test_clip_checkpoint_roundtrip(random_clip, tmp_path):
    from freamer_rl.layers.clip_backbone import ClipBackbone

    path = tmp_path / "clip_visual.pt"
    torch.save(random_clip.state_dict(), path)
    loaded = ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=str(path))
    px = torch.randint(0, 256, (2, 60, 80, 3), dtype=torch.uint8)  # non-square: resize + centre crop
    a, b = random_clip(px), loaded(px)
    assert a.shape == (2, 49, 768)
    torch.testing.assert_close(b, a, rtol=0, atol=0)


def test_clip_tag_from_local_hub_cache(random_clip, tmp_path, monkeypatch):
    """A pre-filled Hugging Face cache resolves the tag without any network call (image-tower-only state dict)."""
    open_clip = require_open_clip()

    from freamer_rl.layers.clip_backbone import ClipBackbone

    def no_network(*args, **kwargs):
        raise AssertionError("download attempted although the file is cached")

    monkeypatch.setattr(open_clip.pretrained, "download_pretrained", no_network)
    snap = tmp_path / "models--timm--vit_base_patch32_clip_224.openai"
    (snap / "refs").mkdir(parents=True)
    (snap / "refs" / "main").write_text("abc123")
    (snap / "snapshots" / "abc123").mkdir(parents=True)
    torch.save(random_clip.visual.state_dict(), snap / "snapshots" / "abc123" / "open_clip_pytorch_model.bin")
    loaded = ClipBackbone("ViT-B-32", pretrained="openai", cache_dir=str(tmp_path), quick_gelu=False)
    px = torch.randint(0, 256, (1, 56, 56, 3), dtype=torch.uint8)
    torch.testing.assert_close(loaded(px), random_clip(px), rtol=0, atol=0)


def test_clip_missing_checkpoint_file(tmp_path):
    require_open_clip()
    from freamer_rl.layers.clip_backbone import ClipBackbone, ClipWeightsError

    missing = tmp_path / "nope" / "clip.pt"
    with pytest.raises(ClipWeightsError) as info:
        ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=str(missing))
    msg = str(info.value)
    assert str(missing) in msg and "\n" not in msg


def test_clip_offline_download_failure(tmp_path, monkeypatch):
    open_clip = require_open_clip()
    from freamer_rl.layers.clip_backbone import ClipBackbone, ClipWeightsError

    def offline(*args, **kwargs):
        raise FileNotFoundError(
            "Failed to download file (open_clip_pytorch_model.bin). Last error: [Errno -2] Name or service not known\n"
            "second line of a long traceback-ish message"
        )

    monkeypatch.setattr(open_clip.pretrained, "download_pretrained", offline)
    with pytest.raises(ClipWeightsError) as info:
        ClipBackbone("ViT-B-32", pretrained="openai", cache_dir=str(tmp_path))
    msg = str(info.value)
    assert "\n" not in msg
    assert "checkpoint_path" in msg and "cache" in msg and "openai" in msg


def test_clip_unknown_tag_and_no_weights():
    require_open_clip()
    from freamer_rl.layers.clip_backbone import ClipBackbone, ClipWeightsError

    with pytest.raises(ClipWeightsError, match="unknown pretrained tag 'no-such-tag'"):
        ClipBackbone("ViT-B-32", pretrained="no-such-tag")
    with pytest.raises(ClipWeightsError, match="allow_random_weights=True"):
        ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=None)


def test_clip_checkpoint_that_does_not_fit(tmp_path):
    require_open_clip()
    from freamer_rl.layers.clip_backbone import ClipBackbone, ClipWeightsError

    bad = tmp_path / "bad.pt"
    torch.save({"foo": torch.zeros(3)}, bad)
    with pytest.raises(ClipWeightsError, match="does not fit"):
        ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=str(bad))
    garbage = tmp_path / "garbage.pt"
    garbage.write_text("not a checkpoint")
    with pytest.raises(ClipWeightsError, match="cannot read CLIP checkpoint"):
        ClipBackbone("ViT-B-32", pretrained=None, checkpoint_path=str(garbage))


def test_language_deduplication_matches_plain_encoding():
    """Encoding distinct rows once and gathering gives the same slots and gradients as encoding every row."""
    torch.manual_seed(0)
    enc = LanguageEncoder(vocab_size=20, out_dim=32, num_slots=2, heads=2, max_len=6).eval()
    rows = torch.tensor([[2, 3, 4, 0, 0, 0], [5, 6, 0, 0, 0, 0]])
    tokens = rows[torch.tensor([0, 1, 0, 0, 1, 0])].reshape(3, 2, 6)
    enc.deduplicate = True
    a = enc(tokens)
    a.square().sum().backward()
    grad_a = enc.embed.weight.grad.clone()
    enc.zero_grad()
    enc.deduplicate = False
    b = enc(tokens)
    b.square().sum().backward()
    assert torch.allclose(a, b, atol=1e-5)
    assert torch.allclose(grad_a, enc.embed.weight.grad, atol=1e-5)


def test_language_inference_cache_is_invalidated_by_parameter_updates():
    torch.manual_seed(0)
    enc = LanguageEncoder(vocab_size=20, out_dim=32, num_slots=2, heads=2, max_len=6).eval()
    tokens = torch.tensor([[2, 3, 4, 0, 0, 0], [5, 6, 0, 0, 0, 0]])
    embedded = []  # rows that went through the encoder (a cache hit embeds none)
    enc.embed.register_forward_hook(lambda module, args, out: embedded.append(args[0].shape[0]))
    with torch.no_grad():
        first = enc(tokens)
        assert embedded == [2]
        assert torch.equal(enc(tokens), first)
        assert embedded == [2]  # the second call was served from the cache
        # an optimiser step is an in-place update: the cache must not serve stale slots. (A uniform shift would be
        # invisible: the LayerNorms remove it, so perturb each weight differently.)
        enc.embed.weight.add_(0.5 * torch.randn_like(enc.embed.weight))
        updated = enc(tokens)
        assert embedded == [2, 2]
    enc.cache_inference = False
    with torch.no_grad():
        assert torch.allclose(updated, enc(tokens), atol=1e-6)
    assert not torch.allclose(updated, first)


def test_torchvision_ops_without_kernels_still_fail_loudly():
    """The schemas declared so that torchvision imports beside a CPU torch must not pose as working operators."""
    require_open_clip()
    import torchvision
    from torchvision.extension import _has_ops

    boxes = torch.tensor([[0.0, 0.0, 1.0, 1.0], [0.0, 0.0, 1.0, 1.0]])
    scores = torch.tensor([1.0, 0.5])
    if _has_ops():  # a torchvision build whose C++ operators load: real non-maximum suppression
        assert torchvision.ops.nms(boxes, scores, 0.5).tolist() == [0]
    else:
        with pytest.raises((RuntimeError, NotImplementedError)):
            torchvision.ops.nms(boxes, scores, 0.5)
