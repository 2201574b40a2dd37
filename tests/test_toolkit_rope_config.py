"""The rope detectors' configurations (monodbh.toolkit.rope.config)."""
import dataclasses

import pytest

from monodbh.toolkit.rope.config import BandConfig, FinderConfig, StemSearchConfig


@pytest.mark.parametrize("cls", [BandConfig, StemSearchConfig, FinderConfig])
def test_configs_are_frozen_and_documented(cls):
    import inspect
    cfg = cls()
    name = dataclasses.fields(cls)[0].name
    with pytest.raises(dataclasses.FrozenInstanceError):
        setattr(cfg, name, None)
    src = inspect.getsource(cls)
    for f in dataclasses.fields(cls):                      # each field: a "#:" line linking its record
        block = src[:src.index(f"    {f.name}:")].rstrip().splitlines()
        doc = []
        while block and block[-1].strip().startswith("#:"):
            doc.append(block.pop())
        assert doc and "docs/decisions/" in " ".join(doc), f.name


def test_weights_are_fresh_per_instance():
    a, b = BandConfig(), BandConfig()
    assert a.score_weights == b.score_weights and a.score_weights is not b.score_weights
    assert StemSearchConfig().weights is not StemSearchConfig().weights
