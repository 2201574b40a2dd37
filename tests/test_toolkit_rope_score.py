"""The linear log-odds score (monodbh.toolkit.rope.score)."""
from monodbh.toolkit.rope.config import BandConfig, StemSearchConfig
from monodbh.toolkit.rope.score import linear_score


def test_linear_score_sums_in_the_order_asked():
    f = {"a": 0.1, "b": 0.2, "c": 1e16, "d": 7.0}
    w = {"bias": 0.3, "c": 1.0, "a": 1.0, "b": 1.0}
    assert linear_score(f, w) == 0.3 + (((0 + 0.1) + 0.2) + 1e16)               # features' order
    assert linear_score(f, w, [k for k in w if k != "bias"]) == 0.3 + (((0 + 1e16) + 0.1) + 0.2)
    assert linear_score({"a": 2.0}, {"a": 0.5}) == 1.0                            # no bias


def test_the_shipped_weights_score_like_the_former_formulas():
    """The band detector summed over its features, the stem search over its weights."""
    bw = BandConfig().score_weights
    bf = {k: 0.1 * (i + 1) for i, k in enumerate(reversed([k for k in bw if k != "bias"]))}
    assert linear_score(bf, bw) == float(bw.get("bias", 0.0) + sum(bw[k] * bf[k] for k in bf if k in bw))
    sw = StemSearchConfig().weights
    sf = {k: 0.3 * (i - 2) for i, k in enumerate(sorted(sw))}
    assert (linear_score(sf, sw, [k for k in sw if k != "bias"])
            == float(sw.get("bias", 0.0) + sum(sw[k] * sf[k] for k in sw if k != "bias")))
