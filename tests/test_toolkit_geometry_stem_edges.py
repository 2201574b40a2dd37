"""The edge pair checked against the rope band (toolkit.geometry.stem_edges)."""
import dataclasses

import numpy as np
import pytest

from geometry_scenes import arced_rope_scene, rope_perception, roped_pair
from monodbh.toolkit.geometry.stem_edges import edges_checked_by_rope, edges_two_pass, stem_edges


def test_merged_neighbour_is_cut_at_the_rope_end():
    # the mask took in the neighbouring trunk on the right: the rope ends at the roped stem's
    # edge, so that side's edge is searched there; the left side stays
    rgb, mask = roped_pair(rope_to=260)
    perc = rope_perception(rgb, mask, 201, 259)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    assert e1 and e1.right_xy[0] > 320          # the mask-guided pair spans both trunks
    e, n = edges_checked_by_rope(gray, perc, e1)
    assert n == 1
    assert abs(e.left_xy[0] - 199.5) < 1.0 and abs(e.right_xy[0] - 259.5) < 1.0
    assert abs(e.width_px - 60.0) < 1.5


def test_merged_neighbour_is_cut_with_the_rope_centre_line_given():
    # the same check reading the rope's row along its (straight) centre line
    rgb, mask = roped_pair(rope_to=260)
    perc = dataclasses.replace(rope_perception(rgb, mask, 201, 259),
                               rope_polyline=np.c_[np.arange(201.0, 260.0, 4.0), np.full(15, 200.0)])
    gray = rgb.astype(np.float32).mean(2)
    e, n = edges_checked_by_rope(gray, perc, edges_two_pass(gray, mask, perc))
    assert n == 1
    assert abs(e.left_xy[0] - 199.5) < 1.0 and abs(e.right_xy[0] - 259.5) < 1.0


def test_arced_rope_is_read_along_its_curve_and_the_mask_edges_stay():
    # a close wide stem seen from above: the rope's ends rise 40 px at the flanks, and the rope
    # band was found over the middle 70 % only. Read along the rope's centre line, the rope goes
    # on to the mask's edges, which stay; a straight row along the chord misses the rising ends
    # and would cut both sides at the band's ends (196 px for 280)
    rgb, mask, perc = arced_rope_scene(depth=40.0, found=0.7)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    assert abs(e1.width_px - 280.0) < 1.5
    e, n = edges_checked_by_rope(gray, perc, e1)
    assert n == 0 and abs(e.width_px - 280.0) < 1.5
    e_straight, n_straight = edges_checked_by_rope(gray, dataclasses.replace(perc, rope_polyline=None), e1)
    assert n_straight == 2 and e_straight.width_px < 0.75 * 280


def test_mask_and_band_inside_the_stem_move_out_to_the_rope_end():
    # a close stem seen from above (x 100..380): the mask and the rope band both stop 50 px
    # inside each flank, where the rope still runs on: both edges move out to the silhouette
    rgb, _, perc = arced_rope_scene(depth=40.0, found=0.65)
    inner = np.zeros(perc.tree_mask.shape, bool)
    inner[:, 149:331] = True
    perc = dataclasses.replace(perc, tree_mask=inner, edge_mask=inner)
    edges, flags, _ = stem_edges(perc, rgb.astype(np.float32).mean(2))
    assert "edges_out_to_rope_end" in flags
    assert abs(edges.left_xy[0] - 100.0) < 1.5 and abs(edges.right_xy[0] - 380.0) < 1.5


def test_rope_end_hanging_past_the_stem_does_not_move_its_edge():
    # the rope's loose end runs on 50 px past the stem's right side over the background: the
    # silhouette there is the stem's own, stronger than any edge at the rope's end
    rgb, _, perc = arced_rope_scene(depth=40.0, found=0.65)
    rgb[178:183, 380:430] = (170, 30, 25)
    perc = dataclasses.replace(perc, rgb=rgb)
    edges, flags, _ = stem_edges(perc, rgb.astype(np.float32).mean(2))
    assert "edges_out_to_rope_end" not in flags
    assert abs(edges.width_px - 280.0) < 1.5


def test_rope_seen_on_part_of_the_stem_keeps_the_mask_edge():
    # the rope goes on, darker, into the stem's shade beyond where the rope band was found:
    # the mask's edge is the stem's
    rgb, mask = roped_pair(rope_to=260, shade_from=235)
    mask[:, 262:] = False                       # the mask is the roped stem's only
    perc = rope_perception(rgb, mask, 201, 235)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    e, n = edges_checked_by_rope(gray, perc, e1)
    assert n == 0
    assert abs(e.right_xy[0] - 259.5) < 1.0


def test_mask_edge_inside_the_roped_stem_is_moved_to_the_rope_end():
    # the coarse mask stops at a bark-tone edge inside the stem (x 215) while the rope runs on
    # to the stem's silhouette (x 200): that side's edge is the rope's end
    rgb, mask = roped_pair(rope_to=260)
    rgb[:, 200:215] = (rgb[:, 200:215] * 0.6).astype(np.uint8)
    rgb[198:203, 200:215] = (170, 30, 25)
    mask[:] = False
    mask[:, 214:262] = True
    perc = rope_perception(rgb, mask, 201, 259)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    assert e1 and abs(e1.left_xy[0] - 214.5) < 1.5     # the mask-guided edge is the bark's
    e, n = edges_checked_by_rope(gray, perc, e1)
    assert n == 1
    assert abs(e.left_xy[0] - 199.5) < 1.0 and abs(e.right_xy[0] - 259.5) < 1.0
    # a rope that fades where the mask stops is no evidence: the mask's edge stays
    rgb2 = rgb.copy()
    rgb2[198:203, 200:215] = rgb[190:195, 200:215]
    e, n = edges_checked_by_rope(rgb2.astype(np.float32).mean(2), dataclasses.replace(perc, rgb=rgb2), e1)
    assert n == 0 and abs(e.left_xy[0] - 214.5) < 1.5


def test_the_rope_check_thresholds_come_from_the_config():
    from monodbh.toolkit.geometry import StemEdgesConfig
    from monodbh.toolkit.geometry.stem_edges import stem_edges
    rgb, mask = roped_pair(rope_to=260)
    perc = rope_perception(rgb, mask, 201, 259)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    # a rope that must stand out more than it can: the mask's edges stay
    e, n = edges_checked_by_rope(gray, perc, e1, StemEdgesConfig(rope_gap_min_contrast=10.0))
    assert n == 0 and e is e1
    # the checked edges (60 px) against the rope band (58 px): within the default ratio 1.3, not 1.0
    edges, flags, width_vs_rope = stem_edges(perc, gray)
    assert flags == ["edge_at_rope_end"] and width_vs_rope == 0.0
    edges, flags, width_vs_rope = stem_edges(perc, gray, StemEdgesConfig(width_rope_ratio_max=1.0))
    assert flags == ["edge_at_rope_end", "width_disagrees_rope"]
    assert width_vs_rope == pytest.approx(abs(np.log(edges.width_px / 58.0)))
    # edges much narrower than the band across the stem are flagged the same way
    edges, flags, width_vs_rope = stem_edges(perc, gray, StemEdgesConfig(width_rope_ratio_min=1.1))
    assert flags == ["edge_at_rope_end", "width_disagrees_rope"]
    assert width_vs_rope == pytest.approx(abs(np.log(edges.width_px / 58.0)))



def test_knot_and_hanging_end_on_the_flank_are_not_the_stem_edge():
    # the knot sticks out past the right flank and its loose end hangs beside the stem: the edge
    # search finds the loose end's border on the lines below the rope; those points have rope
    # red just inside them and are left out of the right side's line
    from monodbh.toolkit.geometry import StemEdgesConfig
    from geometry_scenes import knotted_rope_scene
    rgb, mask, perc = knotted_rope_scene()
    gray = rgb.astype(np.float32).mean(2)
    e_off, flags_off, _ = stem_edges(perc, gray, StemEdgesConfig(rope_end_red_ratio=0.0))
    assert "edge_points_on_rope_end" not in flags_off
    assert e_off.right_xy[0] > 262.0            # pulled out by the hanging end
    edges, flags, _ = stem_edges(perc, gray)
    assert "edge_points_on_rope_end" in flags
    assert abs(edges.left_xy[0] - 199.5) < 1.0 and abs(edges.right_xy[0] - 259.5) < 1.0


def test_rope_without_knot_leaves_every_edge_point():
    from monodbh.toolkit.geometry.stem_edges import edges_off_rope_ends
    rgb, mask = roped_pair(rope_to=260)
    mask[:, 262:] = False
    perc = rope_perception(rgb, mask, 201, 259)
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    e, n = edges_off_rope_ends(perc, gray.shape, e1)
    assert n == 0 and e is e1


def _edge_finder(left_x, right_x, mass=(0.9, 0.9)):
    """A stand-in for the stem-edge network that answers the given photo columns (a vertical stem)."""
    from monodbh.models.runtime.stem_edge import EdgeEstimate

    def find(rgb, center_xy, along, width_px):
        return EdgeEstimate(offsets_px=np.array([left_x, right_x]) - center_xy[0], across=np.array([1.0, 0.0]),
                            mass=np.array(mass), px_per_col=width_px / 64.0)
    return find


def test_the_edge_network_moves_a_side_the_gradient_took_on_a_neighbour():
    # the mask took in the lighter neighbour on the right and the rope does not tell (it is not
    # there: no rope band): the gradient pair spans both trunks. The network says the stem ends at
    # x 260: that side is searched again there, to a fraction of a pixel; the left side stays
    from monodbh.toolkit.geometry.stem_edges import edges_from_network

    rgb, mask = roped_pair(rope_to=260)
    gray = rgb.astype(np.float32).mean(2)
    perc = dataclasses.replace(rope_perception(rgb, mask, 201, 259), rope_band_mask=None, rope_length_px=None)
    e1 = edges_two_pass(gray, mask, perc)
    assert e1.right_xy[0] > 320
    e, n = edges_from_network(dataclasses.replace(perc, edge_finder=_edge_finder(199.0, 261.0)), gray, e1)
    assert n == 1 and abs(e.left_xy[0] - e1.left_xy[0]) < 1e-9
    assert abs(e.right_xy[0] - 259.5) < 0.75 and abs(e.width_px - 60.0) < 1.0
    # through stem_edges, flagged
    edges, flags, _ = stem_edges(dataclasses.replace(perc, edge_finder=_edge_finder(199.0, 261.0)), gray)
    assert "edges_from_network" in flags and abs(edges.width_px - 60.0) < 1.0
    # an unsure network, or one that agrees within the tolerance, leaves the edges
    unsure = dataclasses.replace(perc, edge_finder=_edge_finder(199.0, 261.0, mass=(0.9, 0.2)))
    assert edges_from_network(unsure, gray, e1)[1] == 0
    agree = dataclasses.replace(perc, edge_finder=_edge_finder(e1.left_xy[0] + 0.5, e1.right_xy[0] - 1.0))
    assert edges_from_network(agree, gray, e1)[1] == 0


def test_leaving_out_knot_points_never_widens_a_side(monkeypatch):
    # the refit without the knot's points moves a side inward or keeps it; a refit that would
    # put a side further out (its remaining points tilt the line) keeps all that side's points
    import importlib
    from monodbh.toolkit.geometry.edges import TrunkEdges
    from geometry_scenes import knotted_rope_scene
    se = importlib.import_module("monodbh.toolkit.geometry.stem_edges")
    rgb, mask, perc = knotted_rope_scene()
    gray = rgb.astype(np.float32).mean(2)
    e1 = edges_two_pass(gray, mask, perc)
    e_ok, n_ok = se.edges_off_rope_ends(perc, gray.shape, e1)
    assert n_ok > 0 and e_ok.right_xy[0] < e1.right_xy[0]

    def outward(edges, keep):          # a refit that pushes the right side 20 px out
        return TrunkEdges(left_xy=edges.left_xy, right_xy=edges.right_xy + 20 * edges.across,
                          width_px=edges.width_px + 20, along=edges.along, across=edges.across,
                          edge_rms_px=edges.edge_rms_px, n_lines=edges.n_lines, points=edges.points)
    monkeypatch.setattr(se, "refit_edges", outward)
    e, n = se.edges_off_rope_ends(perc, gray.shape, e1)
    assert n == 0 and e is e1
