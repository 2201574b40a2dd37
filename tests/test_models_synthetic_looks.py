"""The held-out look (issue 26): the same scenes with another appearance, refused by training."""
import json

import numpy as np
import pytest

pytest.importorskip("embreex")

from monodbh.models.synthetic import generate_sample  # noqa: E402
from monodbh.models.synthetic.io import write_sample  # noqa: E402
from monodbh.models.synthetic.looks import photo_textures  # noqa: E402
from monodbh.models.training.common import FolderSource, GeneratorSource, make_source  # noqa: E402

SIZE = (160, 120)


@pytest.fixture(scope="module")
def textures(shared_data):
    folder = shared_data / "real_trees"
    if not folder.is_dir():
        pytest.skip(f"{folder}: real photos not found")
    return photo_textures(str(folder))


@pytest.fixture(scope="module")
def pair(textures, shared_data, monkeypatch_module):
    monkeypatch_module.setenv("MONODBH_REAL_TREES", str(shared_data / "real_trees"))
    return generate_sample(5, 1, SIZE), generate_sample(5, 1, SIZE, look="heldout")


@pytest.fixture(scope="module")
def monkeypatch_module():
    mp = pytest.MonkeyPatch()
    yield mp
    mp.undo()


def test_photo_textures_cut_from_every_kind_of_region(textures):
    for k in ("bark", "foliage", "ground", "sky"):
        patches = getattr(textures, k)
        assert len(patches) >= 20, k
        assert all(p.ndim == 3 and p.shape[2] == 3 and p.dtype == np.float32 for p in patches)
    # bark comes from the outlined trunks only, with each photo's credit kept
    assert len(textures.sources) == 24
    assert all(s["credit"] and s["licence"] for s in textures.sources)


def test_heldout_look_keeps_scene_and_labels_changes_appearance(pair):
    a, b = pair
    for k in ("depth", "semantic", "instance", "rope", "z1", "z2"):
        assert np.array_equal(a[k], b[k]), k
    assert a["meta"]["trees"] == b["meta"]["trees"] and a["meta"]["rope"] == b["meta"]["rope"]
    assert a["meta"]["look"] == "default" and b["meta"]["look"] == "heldout"
    diff = np.abs(a["rgb"].astype(int) - b["rgb"].astype(int)).mean()
    assert diff > 10, diff


def test_randomized_look_keeps_labels_and_is_trainable(pair, tmp_path):
    a = pair[0]
    r = generate_sample(5, 1, SIZE, look="randomized")
    for k in ("depth", "semantic", "instance", "rope"):
        assert np.array_equal(a[k], r[k]), k
    assert r["meta"]["look"] == "randomized"
    assert np.abs(a["rgb"].astype(int) - r["rgb"].astype(int)).mean() > 5
    # two draws of the same scene are the same picture (its appearance is seeded by the scene)
    assert np.array_equal(r["rgb"], generate_sample(5, 1, SIZE, look="randomized")["rgb"])
    write_sample(tmp_path / "rand", 0, r)
    assert len(FolderSource(tmp_path / "rand")) == 1


def test_unknown_look_is_refused():
    with pytest.raises(ValueError, match="unknown look"):
        generate_sample(5, 0, (32, 32), look="sepia")


def test_training_sources_refuse_the_heldout_look(pair, tmp_path):
    a, b = pair
    write_sample(tmp_path / "plain", 0, a)
    write_sample(tmp_path / "held", 0, b)
    assert len(FolderSource(tmp_path / "plain")) == 1
    with pytest.raises(ValueError, match="held-out look"):
        FolderSource(tmp_path / "held")
    with pytest.raises(ValueError, match="held-out look"):
        make_source([str(tmp_path / "plain"), str(tmp_path / "held")])
    with pytest.raises(ValueError, match="held-out look"):
        make_source([b])
    with pytest.raises(ValueError, match="held-out look"):
        GeneratorSource(0, SIZE, {"look": "heldout"})
    # evaluation may read it
    assert len(make_source(tmp_path / "held", allow_heldout=True)) == 1
    assert json.loads((tmp_path / "held" / "000000.json").read_text())["look"] == "heldout"


def test_rope_finder_bank_refuses_the_heldout_look(pair, tmp_path):
    from monodbh.models.training.rope_finder_bank import cut_folder
    write_sample(tmp_path / "held", 0, pair[1])
    with pytest.raises(ValueError, match="held-out look"):
        cut_folder(tmp_path / "held", tmp_path / "bank.npz")
