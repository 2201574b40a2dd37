"""EfficientNet-Lite0 trunk (size ``effl0`` segmenter) and the loader of its pretrained weights.

The ImageNet weights themselves (the ``pretrained`` extra) are not needed: a saved state dict
stands in for the file.
"""
import pytest
import torch

from monodbh.models.modeling import build, get_spec
from monodbh.models.modeling.efficientnet_lite import FEATURE_CHANNELS, EfficientNetLite0
from monodbh.models.training.pretrained import load_efficientnet_lite0


def test_features_channels_and_strides():
    net = EfficientNetLite0().eval()
    with torch.no_grad():
        feats = net(torch.zeros(1, 3, 64, 96))
    assert [f.shape[1] for f in feats] == list(FEATURE_CHANNELS)
    assert [tuple(f.shape[2:]) for f in feats] == [(16, 24), (8, 12), (4, 6), (2, 3)]


def test_load_round_trips_a_state_dict_and_ignores_classifier(tmp_path):
    src = EfficientNetLite0()
    for p in src.parameters():
        torch.nn.init.normal_(p)
    sd = dict(src.state_dict())
    sd["fc.weight"] = torch.zeros(1000, 1280)          # a classifier head the trunk does not use
    torch.save(sd, tmp_path / "w.pth")
    dst = EfficientNetLite0()
    n = load_efficientnet_lite0(dst, tmp_path / "w.pth")
    assert n == len(dst.state_dict())
    for k, v in dst.state_dict().items():
        assert torch.equal(v, src.state_dict()[k]), k


def test_load_refuses_a_file_of_other_shapes(tmp_path):
    sd = dict(EfficientNetLite0().state_dict())
    key = next(k for k in sd if k.endswith("weight") and sd[k].ndim == 4)
    sd[key] = torch.zeros(1, 1, 1, 1)
    torch.save(sd, tmp_path / "w.pth")
    with pytest.raises(ValueError, match="w.pth: 1 backbone tensors"):
        load_efficientnet_lite0(EfficientNetLite0(), tmp_path / "w.pth")


def test_effl0_segmenter_forward_shapes():
    model = build("segmenter", "effl0").eval()
    spec = get_spec("segmenter", "effl0")
    assert model.cfg.backbone == "effl0" and spec.inputs[0].shape == (1, 3, 256, 256)
    with torch.no_grad():
        c, k = model(torch.zeros(spec.inputs[0].shape))
    assert tuple(c.shape) == spec.outputs[0].shape and tuple(k.shape) == spec.outputs[1].shape
