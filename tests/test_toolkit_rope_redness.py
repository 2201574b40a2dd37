"""Red-ness maps and the thin-line contrast (monodbh.toolkit.rope.redness)."""
import cv2
import numpy as np

from monodbh.toolkit.rope.redness import line_contrast, red_shift_map, redness_map


def test_maps_computed_in_place_equal_the_plain_steps():
    """red_shift_map / line_contrast reuse their buffers (speed): the values must be those of the
    plain, step-by-step versions."""
    rng = np.random.default_rng(3)
    rgb = rng.integers(0, 256, (61, 83, 3), dtype=np.uint8)
    R, G, B = cv2.split(rgb)
    num = cv2.addWeighted(cv2.subtract(R, cv2.max(G, B), dtype=cv2.CV_32F), 1.0, cv2.subtract(G, B), -0.5, 0.0,
                          dtype=cv2.CV_32F)
    den = cv2.add(cv2.addWeighted(R, 1.0, G, 1.0, 30.0, dtype=cv2.CV_32F), B, dtype=cv2.CV_32F)
    ref = cv2.divide(num, den)
    assert np.array_equal(red_shift_map(rgb), ref) and np.array_equal(redness_map(rgb), np.maximum(ref, 0.0))
    F = np.maximum(ref, 0.0)
    Gb = cv2.GaussianBlur(F, (0, 0), sigmaX=2.0, sigmaY=0.7)
    want = np.zeros_like(Gb)
    for d in (2, 3):
        c = Gb[d:-d]
        want[d:-d] = np.maximum(want[d:-d], np.minimum(c - Gb[:-2 * d], c - Gb[2 * d:]))
    assert np.allclose(line_contrast(F), want, atol=1e-7)


def test_line_contrast_answers_to_thin_lines_not_to_blob_edges():
    F = np.zeros((60, 80), np.float32)
    F[30, 10:70] = 0.2                         # a thin line
    F[:, :5] = 0.2                             # the edge of a wide red area
    R = line_contrast(F)
    assert R[30, 40] > 0.05
    assert R[10:50, 5:8].max() < 0.2 * R[30, 40]
