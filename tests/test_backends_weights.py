"""RAFT and MiDaS backends: architecture, safe weight loading, inference wrappers.

No real checkpoint is available offline: every test builds a randomly initialised model of the
same architecture (torch.manual_seed(0)), saves it and loads it back through load_raft /
load_midas.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import save_file

from gcvd_flow.io.weights import open_model
from gcvd_flow.stages.models.midas import MidasNet, midas_prior, network_size
from gcvd_flow.stages.models.raft import RAFT, CorrPyramid, coords_grid, raft_flow, upsample_flow_convex


def _save_safetensors(model: torch.nn.Module, path: Path) -> Path:
    # raft-things stores the strided blocks' norm under two names (norm3 and downsample.1):
    # safetensors refuses shared storage, so write independent copies.
    save_file({k: v.detach().clone().contiguous() for k, v in model.state_dict().items()}, str(path))
    return path


def _images(h: int, w: int, shift: int = 3, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    base = rng.integers(0, 256, (h + 8, w + 8, 3), dtype=np.uint8)
    return base[:h, :w].copy(), base[:h, shift:shift + w].copy()


def _assert_same_weights(a: torch.nn.Module, b: torch.nn.Module) -> None:
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    for k in sa:
        assert torch.equal(sa[k], sb[k]), k


# ------------------------------------------------------------------------------------------
# RAFT
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def raft_files(tmp_path_factory):
    torch.manual_seed(0)
    model = RAFT()
    d = tmp_path_factory.mktemp("raft")
    st = _save_safetensors(model, d / "raft.safetensors")
    pth = d / "raft-things.pth"
    # the official file is a DataParallel state dict: keys prefixed with "module."
    torch.save({"module." + k: v for k, v in model.state_dict().items()}, str(pth))
    return model, st, pth


def test_raft_parameter_count_matches_paper():
    n = sum(p.numel() for p in RAFT().parameters())
    assert n == 5_257_536
    assert abs(n - 5.26e6) / 5.26e6 < 0.01


def test_raft_key_names_match_official_checkpoint():
    keys = set(RAFT().state_dict())
    assert len(keys) == 179  # raft-things.pth holds 179 tensors
    for k in ("fnet.conv1.weight", "fnet.layer1.0.conv1.weight", "fnet.layer2.0.downsample.0.weight",
              "cnet.norm1.weight", "cnet.layer3.0.norm3.running_var", "cnet.layer3.0.downsample.1.weight",
              "update_block.encoder.convc1.weight", "update_block.gru.convz1.weight",
              "update_block.gru.convq2.bias", "update_block.flow_head.conv1.weight",
              "update_block.mask.0.weight", "update_block.mask.2.bias"):
        assert k in keys, k
    assert not any(k.startswith("fnet.norm") for k in keys)  # instance norm: no parameters
    m = RAFT()
    assert tuple(m.update_block.encoder.convc1.weight.shape) == (256, 324, 1, 1)
    assert tuple(m.update_block.gru.convz1.weight.shape) == (128, 384, 1, 5)
    assert tuple(m.update_block.mask[2].weight.shape) == (576, 256, 1, 1)


def test_raft_safetensors_roundtrip_and_determinism(raft_files):
    model, st, _ = raft_files
    loaded = open_model("raft", st)
    assert not loaded.training
    _assert_same_weights(model, loaded)
    a, b = _images(48, 64)
    f1 = raft_flow(loaded, a, b, iters=2)
    f2 = raft_flow(loaded, a, b, iters=2)
    assert f1.shape == (48, 64, 2) and f1.dtype == np.float32
    assert np.isfinite(f1).all()
    assert np.array_equal(f1, f2)
    assert np.abs(f1).max() > 0
    f3 = raft_flow(open_model("raft", st), a, b, iters=2)
    assert np.array_equal(f1, f3)


def test_raft_pth_weights_only_and_padding(raft_files):
    _, st, pth = raft_files
    a, b = _images(48, 64)
    np.testing.assert_array_equal(raft_flow(open_model("raft", pth), a, b, iters=2),
                                  raft_flow(open_model("raft", st), a, b, iters=2))
    # sides not multiples of 8: padded (replicate) then cropped back
    a2, b2 = _images(45, 61, seed=1)
    f = raft_flow(open_model("raft", st), a2, b2, iters=1)
    assert f.shape == (45, 61, 2) and f.dtype == np.float32 and np.isfinite(f).all()


def test_raft_missing_key_is_a_clear_error(raft_files, tmp_path):
    model, _, _ = raft_files
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    del state["update_block.mask.0.weight"]
    bad = tmp_path / "broken.safetensors"
    save_file(state, str(bad))
    with pytest.raises(ValueError, match=r"update_block\.mask\.0\.weight") as e:
        open_model("raft", bad)
    assert "broken.safetensors" in str(e.value)
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    state["extra.weight"] = torch.zeros(1)
    bad2 = tmp_path / "extra.pth"
    torch.save(state, str(bad2))
    with pytest.raises(ValueError, match=r"extra\.weight"):
        open_model("raft", bad2)


def test_raft_inputs_validated():
    m = RAFT().eval()
    a, b = _images(48, 64)
    with pytest.raises(ValueError):
        raft_flow(m, a.astype(np.float32), b)
    with pytest.raises(ValueError):
        raft_flow(m, a, b[:40])


def test_corr_lookup_channel_order_and_values():
    torch.manual_seed(0)
    f1, f2 = torch.randn(1, 8, 6, 7), torch.randn(1, 8, 6, 7)
    corr = CorrPyramid(f1, f2, levels=2, radius=1)(coords_grid(1, 6, 7))
    assert corr.shape == (1, 2 * 9, 6, 7)
    y, x = 2, 3
    direct = lambda yy, xx: float((f1[0, :, y, x] * f2[0, :, yy, xx]).sum() / 8**0.5)  # noqa: E731
    # window index a * 3 + b <-> offset (dx = a - 1, dy = b - 1)
    assert corr[0, 4, y, x].item() == pytest.approx(direct(y, x), abs=1e-5)
    assert corr[0, 7, y, x].item() == pytest.approx(direct(y, x + 1), abs=1e-5)  # a=2, b=1
    assert corr[0, 5, y, x].item() == pytest.approx(direct(y + 1, x), abs=1e-5)  # a=1, b=2
    assert corr[0, 0, 0, 0].item() == 0.0  # outside the image: zero padding


def test_convex_upsampling_of_constant_flow():
    flow = torch.zeros(1, 2, 3, 4)
    flow[:, 0], flow[:, 1] = 1.5, -0.5
    up = upsample_flow_convex(flow, torch.randn(1, 576, 3, 4))
    assert up.shape == (1, 2, 24, 32)
    # interior pixels (all 3x3 neighbours inside) reproduce 8 x flow exactly
    assert torch.allclose(up[0, 0, 8:16, 8:24], torch.full((8, 16), 12.0), atol=1e-5)
    assert torch.allclose(up[0, 1, 8:16, 8:24], torch.full((8, 16), -4.0), atol=1e-5)


# ------------------------------------------------------------------------------------------
# MiDaS v2.1 small
# ------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def midas_files(tmp_path_factory):
    torch.manual_seed(0)
    model = MidasNet()
    d = tmp_path_factory.mktemp("midas")
    st = _save_safetensors(model, d / "midas.safetensors")
    pth = d / "midas_v21_small_256.pt"
    torch.save(model.state_dict(), str(pth))
    return model, st, pth


def test_midas_architecture_keys_and_size():
    m = MidasNet()
    keys = set(m.state_dict())
    for k in ("pretrained.layer1.0.weight", "pretrained.layer1.3.0.conv_dw.weight",
              "pretrained.layer1.4.2.conv_pwl.weight", "pretrained.layer4.1.0.bn3.running_mean",
              "scratch.layer4_rn.weight", "scratch.refinenet4.resConfUnit1.conv1.weight",
              "scratch.refinenet1.out_conv.bias", "scratch.output_conv.0.weight",
              "scratch.output_conv.4.bias"):
        assert k in keys, k
    n = sum(p.numel() for p in m.parameters())
    assert n == 21_320_545
    with torch.no_grad():
        feats = []
        x = torch.zeros(1, 3, 64, 96)
        for layer in (m.pretrained.layer1, m.pretrained.layer2, m.pretrained.layer3, m.pretrained.layer4):
            x = layer(x)
            feats.append(tuple(x.shape[1:]))
    assert feats == [(32, 16, 24), (48, 8, 12), (136, 4, 6), (384, 2, 3)]
    assert network_size(48, 64) == (192, 256)
    assert network_size(480, 640) == (192, 256)
    assert network_size(100, 1000) == (32, 256)


def test_midas_safetensors_roundtrip_prior_contract(midas_files):
    model, st, _ = midas_files
    loaded = open_model("midas", st)
    assert not loaded.training
    _assert_same_weights(model, loaded)
    img, _ = _images(48, 64)
    p1 = midas_prior(loaded, img)
    p2 = midas_prior(open_model("midas", st), img)
    assert p1.shape == (48, 64) and p1.dtype == np.float32
    assert np.isfinite(p1).all() and (p1 > 0).all()
    assert np.median(p1) == pytest.approx(1.0, rel=1e-5)
    assert np.array_equal(p1, p2)
    with torch.no_grad():
        raw = loaded(torch.randn(1, 3, 64, 96))
    assert raw.shape == (1, 64, 96) and (raw >= 0).all()


def test_midas_pth_weights_only(midas_files):
    model, st, pth = midas_files
    loaded = open_model("midas", pth)
    _assert_same_weights(model, loaded)
    img, _ = _images(48, 64, seed=2)
    np.testing.assert_array_equal(midas_prior(loaded, img), midas_prior(open_model("midas", st), img))


def test_midas_missing_key_is_a_clear_error(midas_files, tmp_path):
    model, _, _ = midas_files
    state = {k: v.detach().clone() for k, v in model.state_dict().items()}
    del state["scratch.output_conv.4.weight"]
    bad = tmp_path / "broken_midas.pt"
    torch.save(state, str(bad))
    with pytest.raises(ValueError, match=r"scratch\.output_conv\.4\.weight") as e:
        open_model("midas", bad)
    assert "broken_midas.pt" in str(e.value)
    # a RAFT file is not a MiDaS file
    torch.manual_seed(0)
    raft = tmp_path / "raft.safetensors"
    _save_safetensors(RAFT(), raft)
    with pytest.raises(ValueError, match="pretrained.layer1.0.weight"):
        open_model("midas", raft)
