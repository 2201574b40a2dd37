"""The geometry's configuration (toolkit.geometry.config)."""
import dataclasses

import pytest

from monodbh.toolkit.geometry import GeometryConfig, ScaleConfig


def test_configs_are_frozen_and_replaced_per_stage():
    cfg = GeometryConfig()
    with pytest.raises(dataclasses.FrozenInstanceError):
        cfg.scale.agree_sigmas = 1.0
    c2 = dataclasses.replace(cfg, scale=ScaleConfig(agree_sigmas=1.0))
    assert c2.scale.agree_sigmas == 1.0 and cfg.scale.agree_sigmas == 2.5 and c2.edges == cfg.edges
    # each instance has its own sigma tables (no shared mutable default)
    assert GeometryConfig().sigma.model is not cfg.sigma.model and GeometryConfig().sigma == cfg.sigma
