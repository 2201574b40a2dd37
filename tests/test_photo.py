"""monodbh.calib.photo: EXIF orientation, pixel formats, one-line errors."""
import numpy as np
import pytest
from PIL import Image

from monodbh.calib import PhotoError, load_photo, read_image_size


def _marked(w=40, h=20):
    """RGB image with a red block at the top-left corner and a blue one at the bottom-right."""
    a = np.full((h, w, 3), 128, np.uint8)
    a[:6, :6] = (255, 0, 0)
    a[-6:, -6:] = (0, 0, 255)
    return a


def test_rgb_jpeg(tmp_path):
    p = tmp_path / "a.jpg"
    Image.fromarray(_marked()).save(p, quality=95)
    img = load_photo(p)
    assert img.shape == (20, 40, 3) and img.dtype == np.uint8 and img.flags.c_contiguous
    assert img[2, 2, 0] > 200 and img[2, 2, 2] < 60
    g = load_photo(p, gray=True)
    assert g.shape == (20, 40) and g.dtype == np.uint8
    assert read_image_size(p) == (40, 20)


def test_fast_jpeg_path_same_pixels_as_pil(tmp_path):
    """Upright RGB JPEGs are decoded by OpenCV (3x faster at 12 MP); the pixels must be PIL's."""
    from monodbh.calib import photo

    rng = np.random.default_rng(0)
    a = np.clip(rng.normal(128, 60, (90, 130, 3)), 0, 255).astype(np.uint8)
    p = tmp_path / "n.jpg"
    Image.fromarray(a).save(p, quality=90)
    with Image.open(p) as im:
        fast = photo._fast_jpeg(im, p)
        im.load()
        ref = np.asarray(im)
    assert fast is not None and fast.shape == ref.shape and fast.flags.c_contiguous
    assert np.array_equal(fast, ref) and np.array_equal(load_photo(p), ref)
    # an OpenCV without IMREAD_COLOR_RGB (< 4.10) decodes BGR and converts: the same pixels
    import cv2
    with pytest.MonkeyPatch.context() as mp:
        mp.delattr(cv2, "IMREAD_COLOR_RGB", raising=False)
        with Image.open(p) as im:
            assert np.array_equal(photo._fast_jpeg(im, p), ref)
    # data after the image (a phone's motion-photo video) is fine
    (tmp_path / "x.jpg").write_bytes(p.read_bytes() + b"\x00\x00ftypmp42" + bytes(300))
    with Image.open(tmp_path / "x.jpg") as im:
        assert np.array_equal(photo._fast_jpeg(im, tmp_path / "x.jpg"), ref)
    # every EXIF orientation: the pixels of PIL's exif_transpose
    from PIL import ImageOps
    for o in range(1, 9):
        exif = Image.Exif()
        exif[0x0112] = o
        q = tmp_path / f"o{o}.jpg"
        Image.fromarray(a).save(q, quality=90, exif=exif)
        with Image.open(q) as im:
            fast = photo._fast_jpeg(im, q)
            want = np.asarray(ImageOps.exif_transpose(im))
        assert fast is not None and fast.flags.c_contiguous and np.array_equal(fast, want), o
    # truncated JPEGs are left to PIL, also when an APP segment (an EXIF thumbnail) holds an
    # end-of-image marker of its own
    raw = p.read_bytes()
    (tmp_path / "t.jpg").write_bytes(raw[:-200])
    app = b"\xff\xe1\x00\x0aExif\xff\xd8\xff\xd9"
    (tmp_path / "u.jpg").write_bytes(raw[:2] + app + raw[2:-200])
    (tmp_path / "v.jpg").write_bytes(raw[:2] + app + raw[2:])
    for name in ("t.jpg", "u.jpg"):
        with Image.open(tmp_path / name) as im:
            assert photo._fast_jpeg(im, tmp_path / name) is None, name
    with Image.open(tmp_path / "v.jpg") as im:
        assert photo._fast_jpeg(im, tmp_path / "v.jpg") is not None
    assert "truncated" in pytest.raises(PhotoError, load_photo, tmp_path / "u.jpg").value.args[0]


@pytest.mark.parametrize("orientation, corner", [(6, (0, -1)), (8, (-1, 0)), (3, (-1, -1))])
def test_exif_orientation_applied(tmp_path, orientation, corner):
    """Orientation 6 = rotate 90 CW to display: stored top-left lands at the top-right."""
    p = tmp_path / "rot.jpg"
    exif = Image.Exif()
    exif[0x0112] = orientation
    Image.fromarray(_marked()).save(p, quality=95, exif=exif)
    img = load_photo(p)
    swapped = orientation in (6, 8)
    assert img.shape[:2] == ((40, 20) if swapped else (20, 40))
    assert read_image_size(p) == ((20, 40) if swapped else (40, 20))
    r, c = corner
    y = 2 if r == 0 else img.shape[0] - 3
    x = 2 if c == 0 else img.shape[1] - 3
    assert img[y, x, 0] > 200 and img[y, x, 2] < 60  # the red block moved there
    assert load_photo(p, gray=True).shape == img.shape[:2]


def test_gray_rgba_palette_la_1bit_cmyk(tmp_path):
    rgb = _marked()
    Image.fromarray(rgb[:, :, 1]).save(tmp_path / "l.png")
    out = load_photo(tmp_path / "l.png")
    assert out.shape == (20, 40, 3) and np.array_equal(out[..., 0], out[..., 2])
    rgba = np.dstack([rgb, np.zeros(rgb.shape[:2], np.uint8)])  # fully transparent
    Image.fromarray(rgba, "RGBA").save(tmp_path / "rgba.png")
    assert np.array_equal(load_photo(tmp_path / "rgba.png"), rgb)  # alpha dropped
    Image.fromarray(rgb).convert("P", palette=Image.Palette.ADAPTIVE, colors=8).save(
        tmp_path / "p.png")
    out = load_photo(tmp_path / "p.png")
    assert out.shape == (20, 40, 3) and out[2, 2, 0] > 200
    Image.fromarray(rgb).convert("LA").save(tmp_path / "la.png")
    assert load_photo(tmp_path / "la.png").shape == (20, 40, 3)
    Image.fromarray(rgb).convert("1").save(tmp_path / "b.png")
    assert set(np.unique(load_photo(tmp_path / "b.png"))) <= {0, 255}
    Image.fromarray(rgb).convert("CMYK").save(tmp_path / "c.jpg", quality=95)
    out = load_photo(tmp_path / "c.jpg")
    assert out.shape == (20, 40, 3) and out[2, 2, 0] > 180


def test_16bit_gray_scaled(tmp_path):
    a = np.zeros((10, 12), np.uint16)
    a[:, 6:] = 65535
    a[0, 0] = 257 * 100
    Image.fromarray(a).save(tmp_path / "g16.png")
    out = load_photo(tmp_path / "g16.png")
    assert out.dtype == np.uint8 and out.shape == (10, 12, 3)
    assert out[0, 0, 0] == 100 and out[5, 11, 1] == 255 and out[5, 1, 2] == 0


def test_16bit_colour_via_fallbacks(tmp_path):
    import cv2

    a = np.zeros((10, 12, 3), np.uint16)
    a[..., 2] = 65535  # red in BGR order
    cv2.imwrite(str(tmp_path / "c16.tif"), a)
    out = load_photo(tmp_path / "c16.tif")
    assert out.shape == (10, 12, 3) and out[0, 0, 0] == 255 and out[0, 0, 2] == 0


def _one_line_error(path, match):
    with pytest.raises(PhotoError) as ei:
        load_photo(path)
    msg = str(ei.value)
    assert "\n" not in msg and str(path) in msg and match in msg, msg
    return msg


def test_errors(tmp_path):
    empty = tmp_path / "empty.jpg"
    empty.write_bytes(b"")
    _one_line_error(empty, "empty")
    good = tmp_path / "good.jpg"
    Image.fromarray(np.random.default_rng(0).integers(0, 255, (200, 300, 3), np.uint8)).save(good)
    trunc = tmp_path / "trunc.jpg"
    trunc.write_bytes(good.read_bytes()[: len(good.read_bytes()) // 2])
    _one_line_error(trunc, "truncated")
    text = tmp_path / "notes.jpg"
    text.write_text("this is not a photo\n" * 20)
    _one_line_error(text, "not an image")
    _one_line_error(tmp_path / "missing.jpg", "no such file")
    _one_line_error(tmp_path, "directory")
    with pytest.raises(PhotoError, match="not an image"):
        read_image_size(text)
    with pytest.raises(PhotoError, match="empty"):
        read_image_size(empty)
    with pytest.raises(TypeError):
        load_photo(123)


def test_tiny_image_loads(tmp_path):
    Image.fromarray(np.zeros((1, 1, 3), np.uint8)).save(tmp_path / "px.png")
    assert load_photo(tmp_path / "px.png").shape == (1, 1, 3)
