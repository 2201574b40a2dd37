"""Reading the depth map at the stem (toolkit.geometry.depth_read)."""
import numpy as np
import pytest


def test_stem_depth_is_the_nearest_across_the_stem():
    import cv2

    from monodbh.toolkit.geometry.depth_read import depth_nearest_across

    # the photo's edges say the stem spans x 34-45; the network's map (coarse, upsampled) has
    # the stem narrower and shifted: its middle reads the background, the nearest depth the stem
    d = np.full((60, 80), 10.0, np.float32)
    d[:, 31:39] = 5.0
    blurred = cv2.GaussianBlur(d, (0, 0), 1.5)
    assert blurred[30, 40] > 8.0
    z = depth_nearest_across(blurred, (34.0, 30.0), (45.0, 30.0))
    assert z == pytest.approx(float(blurred[30, 35:39].min()), abs=1e-6) and z < 5.1
    # the cross-section may lean: the segment between the edges is followed, +-2 px across
    assert depth_nearest_across(d, (34.0, 28.0), (45.0, 32.0)) == pytest.approx(5.0)
    # nothing positive there (or off the map): nan, not a number that looks like a depth
    assert np.isnan(depth_nearest_across(np.zeros_like(d), (34.0, 30.0), (45.0, 30.0)))
    assert np.isnan(depth_nearest_across(d, (200.0, 300.0), (210.0, 300.0)))


def _stem_cross_section():
    """A stem between x 34 and 45 at row 30 whose depth map reads 5 m on its left part (x 31-38)
    and 10 m (background bleeding in) on the rest."""
    from monodbh.toolkit.geometry import TrunkEdges
    d = np.full((60, 80), 10.0, np.float32)
    d[:, 31:39] = 5.0
    tree = np.zeros(d.shape, bool)
    tree[:, 34:46] = True
    edges = TrunkEdges(left_xy=np.array([34.0, 30.0]), right_xy=np.array([45.0, 30.0]), width_px=11.0,
                       along=np.array([0.0, 1.0]), across=np.array([1.0, 0.0]))
    return d, tree, edges


def test_network_depth_reads_the_nearest_and_ground_truth_the_centre():
    from types import SimpleNamespace

    from monodbh.toolkit.geometry.depth_read import depth_at_stem_centre, stem_front_depth
    d, tree, edges = _stem_cross_section()
    perc = SimpleNamespace(depth=d, tree_mask=tree, edge_mask=None, rope_half_px=1.0, depth_is_metric=False)
    assert stem_front_depth(perc, edges) == 5.0
    perc.depth_is_metric = True                         # an exact map: the stem's centre (38-41 px)
    assert stem_front_depth(perc, edges) == 10.0
    assert depth_at_stem_centre(perc, edges, np.zeros(2)) == 10.0
    # the tree mask misses the stem there: the edge mask's pixels are read
    perc.tree_mask = np.zeros_like(tree)
    assert np.isnan(depth_at_stem_centre(perc, edges, np.zeros(2)))
    perc.edge_mask = tree
    assert depth_at_stem_centre(perc, edges, np.zeros(2)) == 10.0
