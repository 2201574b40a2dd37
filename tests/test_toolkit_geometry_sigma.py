"""The sigma tables of one measurement (toolkit.geometry.sigma)."""
from types import SimpleNamespace

from monodbh.toolkit.geometry import SigmaConfig
from monodbh.toolkit.geometry.sigma import sigma_tables


def test_measured_sigmas_override_the_default_network_table():
    cfg = SigmaConfig()
    t = sigma_tables(SimpleNamespace(sigma_network={"network": 0.3}, source="network"))
    assert t.net and t.network["network"] == 0.3 and t.network["width"] == cfg.model_network["width"]
    assert t.by_perception is t.network and t.model == cfg.model
    t = sigma_tables(SimpleNamespace(sigma_network=None, source="ground_truth"),
                     SigmaConfig(model={**cfg.model, "pose": 0.5}))
    assert not t.net and t.by_perception["pose"] == 0.5
