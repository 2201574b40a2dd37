"""Segmenter data path on real synthetic scenes (generator), tiny sizes."""
import numpy as np
import pytest

synth = pytest.importorskip("monodbh.models.synthetic")

from monodbh.models.modeling import build  # noqa: E402
from monodbh.models.training.common import (AugmentConfig, GeneratorSource, augment,  # noqa: E402
                                            sample_rng)
from monodbh.models.training.segmenter import (build_targets, calibration_inputs,  # noqa: E402
                                               eval_hook, make_batch, torch_predictor)


def test_generator_samples_to_targets_batches_and_metrics():
    src = GeneratorSource(seed=3, size=(96, 72), opts={"distortion": False}, pool=2)
    s = src.get(0)
    assert s is src.get(2)                                   # pool wraps, cache hit
    a = augment(s, sample_rng(0, 0, 0), AugmentConfig(crop=1.0, hflip=1.0), (64, 64))
    assert a["rgb"].shape == (64, 64, 3) and a["instance"].shape == (64, 64)
    assert a["K"].shape == (3, 3) and a["aug"]["flip"]
    t = build_targets(a["semantic"], a["instance"], (16, 16), min_thing_area=4)
    assert len(t["labels"]) == len(t["masks"]) > 0
    model = build("segmenter", "tiny")
    imgs, tgts = make_batch(src, 0, 2, 0, model.spec, AugmentConfig())
    assert imgs.shape == (2, 3, 64, 64) and len(tgts) == 2
    feeds = calibration_inputs(2, 0, model.spec, src)
    assert feeds[0]["image"].shape == (1, 3, 64, 64) and feeds[0]["image"].dtype == np.float32
    met = eval_hook(torch_predictor(model), 2, 0, model.spec, src)
    assert {"roped_iou", "pq", "pq_things", "pq_stuff"} <= set(met)
