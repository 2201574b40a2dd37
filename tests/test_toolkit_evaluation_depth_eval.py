"""toolkit.evaluation.depth_eval: depth maps written whole, beside nothing else."""
import numpy as np

from monodbh.toolkit.evaluation.depth_eval import write_depth


def test_write_depth_float32_atomically(tmp_path):
    d = np.linspace(1.0, 9.0, 12, dtype=np.float64).reshape(3, 4)
    p = write_depth(tmp_path / "out", "/photos/IMG_7.jpg", d)
    assert p == tmp_path / "out" / "IMG_7_depth.npy" and [q.name for q in p.parent.iterdir()] == [p.name]
    back = np.load(p)
    assert back.dtype == np.float32 and back.shape == (3, 4) and np.array_equal(back, d.astype(np.float32))
