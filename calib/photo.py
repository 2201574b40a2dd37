"""Photo loading for the whole toolkit.

Phones store most photos as landscape sensor data plus an EXIF ``Orientation`` tag; every
module of monodbh must see the photo the way a viewer shows it, so all photos go through
:func:`load_photo`, which applies the EXIF orientation (``PIL.ImageOps.exif_transpose``) and
converts every pixel format to 8-bit RGB (or 8-bit gray on request).

Errors are :class:`~monodbh.calib.errors.PhotoError` with a one-line message naming the file.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Union

import numpy as np

from .errors import PhotoError

__all__ = ["load_photo", "read_image_size", "PathLike"]

PathLike = Union[str, "os.PathLike[str]"]

# EXIF orientations that swap width and height (transpose, rotate 90 CW, transverse, rotate 90 CCW).
_SWAPPING_ORIENTATIONS = (5, 6, 7, 8)
_EXIF_ORIENTATION_TAG = 0x0112


def _check_file(path: PathLike) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    if not p.exists():
        raise PhotoError(f"{p}: no such file")
    if p.is_dir():
        raise PhotoError(f"{p}: is a directory, not a photo")
    try:
        size = p.stat().st_size
    except OSError as exc:  # pragma: no cover - permission races
        raise PhotoError(f"{p}: cannot read ({exc.strerror or exc})") from None
    if size == 0:
        raise PhotoError(f"{p}: file is empty")
    return p


def _open(p: Path):
    from PIL import Image, UnidentifiedImageError

    try:
        return Image.open(p)
    except UnidentifiedImageError:
        return None  # let the caller try OpenCV's decoders, then report "not an image"
    except Image.DecompressionBombError as exc:
        raise PhotoError(f"{p}: image too large to decode safely ({exc})") from None
    except PermissionError:
        raise PhotoError(f"{p}: permission denied") from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is bad input
        raise PhotoError(f"{p}: cannot read image ({_short(exc)})") from None


def _short(exc: BaseException) -> str:
    msg = " ".join(str(exc).split()) or type(exc).__name__
    return msg if len(msg) <= 120 else msg[:117] + "..."


def _pil_to_array(im, p: Path, gray: bool) -> np.ndarray:
    """Convert a loaded PIL image of any mode to uint8 ``(H, W)`` gray or ``(H, W, 3)`` RGB."""
    mode = im.mode
    if mode.startswith("I") or mode == "F":
        # 16-bit (``I;16*``), 32-bit integer or float single-channel images.
        a = np.asarray(im)
        if a.dtype.kind == "f":
            a = a.astype(np.float64)
            finite = np.isfinite(a)
            peak = float(a[finite].max()) if finite.any() else 0.0
            a = np.where(finite, a, 0.0)
            a = a * 255.0 if peak <= 1.0 else a
        else:
            a = a.astype(np.float64)
            peak = float(a.max()) if a.size else 0.0
            if mode.startswith("I;16") or 255.0 < peak <= 65535.0:
                a = a / 257.0  # 65535 -> 255
            elif peak > 65535.0:
                a = a * (255.0 / peak)
        g = np.clip(np.rint(a), 0, 255).astype(np.uint8)
        return g if gray else np.repeat(g[:, :, None], 3, axis=2)
    if mode in ("1", "LA", "La"):
        im = im.convert("L")
    elif mode not in ("L", "RGB"):
        try:
            im = im.convert("RGB")  # P, PA, RGBA, RGBa, RGBX, CMYK, YCbCr, LAB, HSV, ...
        except Exception as exc:  # noqa: BLE001
            raise PhotoError(f"{p}: unsupported pixel format {mode!r} ({_short(exc)})") from None
    a = np.asarray(im)
    if a.ndim == 2:
        return np.ascontiguousarray(a) if gray else np.repeat(a[:, :, None], 3, axis=2)
    a = np.ascontiguousarray(a[:, :, :3])
    if gray:
        import cv2

        return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    return a


def _cv2_fallback(p: Path, gray: bool) -> np.ndarray | None:
    """Decode formats PIL does not know (e.g. 16-bit colour TIFF) with OpenCV, or None."""
    import cv2

    try:
        buf = np.fromfile(str(p), dtype=np.uint8)
        img = cv2.imdecode(buf, cv2.IMREAD_UNCHANGED)
    except Exception:  # noqa: BLE001
        return None
    if img is None or img.size == 0:
        return None
    if img.dtype == np.uint16:
        img = np.clip(np.rint(img / 257.0), 0, 255).astype(np.uint8)
    elif img.dtype.kind == "f":
        img = np.nan_to_num(img.astype(np.float64))
        img = np.clip(np.rint(img * 255.0 if img.max() <= 1.0 else img), 0, 255).astype(np.uint8)
    elif img.dtype != np.uint8:
        return None
    if img.ndim == 2:
        return img if gray else cv2.cvtColor(img, cv2.COLOR_GRAY2RGB)
    if img.shape[2] == 4:
        img = img[:, :, :3]
    img = np.ascontiguousarray(img)
    return cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if gray else cv2.COLOR_BGR2RGB)


def _jpeg_complete(data: bytes) -> bool:
    """Does the JPEG in ``data`` reach its end-of-image marker?

    The marker segments before the first scan are walked by their lengths (an EXIF thumbnail,
    itself a JPEG with its own end marker, is skipped that way); after the scan header, ``FF D9``
    cannot occur inside entropy-coded data (an ``FF`` there is followed by ``00`` or a restart
    marker), so its first occurrence is the image's end. Data after it (a phone's motion-photo
    video, a maker trailer) does not matter.

    Examples
    --------
    >>> b = bytes.fromhex("ffd8 ffe0 0004 0000 ffda 0002 1234 ffd9 0000")
    >>> _jpeg_complete(b), _jpeg_complete(b[:-4])
    (True, False)
    """
    n = len(data)
    if n < 4 or data[0] != 0xFF or data[1] != 0xD8:
        return False
    i = 2
    while i + 4 <= n:
        if data[i] != 0xFF:
            return False
        marker = data[i + 1]
        if marker == 0xFF:                      # fill byte
            i += 1
            continue
        if marker == 0xD9:                      # end of image before any scan
            return False
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:
            i += 2
            continue
        seg_len = (data[i + 2] << 8) | data[i + 3]
        if marker == 0xDA:                      # start of scan: the rest is image data
            return data.find(b"\xff\xd9", i + 2 + seg_len) != -1
        i += 2 + seg_len
    return False


def _fast_jpeg(im, p: Path) -> np.ndarray | None:
    """A plain RGB JPEG decoded by OpenCV straight into an upright array, or None.

    ``PIL``'s decode, ``exif_transpose`` copy and array conversion take 250 ms for a 12 MP photo
    on the project's machine, ``cv2.imdecode`` 80-90 ms with the same pixels (both libjpeg-turbo,
    tested). A complete (:func:`_jpeg_complete`) 8-bit RGB JPEG takes this path, its EXIF
    orientation applied by the same exact array operation as ``exif_transpose`` (a portrait
    phone photo is stored as landscape with orientation 6); everything else (truncated files,
    which OpenCV would decode silently, gray, CMYK) goes through PIL as before.
    """
    if im.format != "JPEG" or im.mode != "RGB":
        return None
    try:
        orient = im.getexif().get(_EXIF_ORIENTATION_TAG, 1)
    except Exception:  # noqa: BLE001 - malformed EXIF: PIL's path decides
        return None
    if orient not in (None, 0, 1) and orient not in _ORIENT_OPS:
        return None
    import cv2

    try:
        data = p.read_bytes()
    except OSError:
        return None
    if not _jpeg_complete(data):
        return None
    rgb_flag = getattr(cv2, "IMREAD_COLOR_RGB", None)       # OpenCV >= 4.10; else BGR, converted
    flags = (cv2.IMREAD_COLOR if rgb_flag is None else rgb_flag) | cv2.IMREAD_IGNORE_ORIENTATION
    try:
        a = cv2.imdecode(np.frombuffer(data, np.uint8), flags)      # (no copy of the file's bytes)
    except cv2.error:
        return None
    if a is None or a.ndim != 3 or a.shape[:2] != (im.size[1], im.size[0]):
        return None
    if rgb_flag is None:
        cv2.cvtColor(a, cv2.COLOR_BGR2RGB, dst=a)
    if orient in _ORIENT_OPS:
        a = np.ascontiguousarray(_ORIENT_OPS[orient](a))
    return a


def _rot_cw(a):
    import cv2
    return cv2.rotate(a, cv2.ROTATE_90_CLOCKWISE)


def _rot_ccw(a):
    import cv2
    return cv2.rotate(a, cv2.ROTATE_90_COUNTERCLOCKWISE)


#: EXIF orientation -> the array operation ``PIL.ImageOps.exif_transpose`` performs (the photo
#: as a viewer shows it): 2 mirror, 3 rotate 180, 4 flip, 5 transpose, 6 rotate 90 clockwise,
#: 7 transverse, 8 rotate 90 counter-clockwise (same pixels, tested for all of them)
_ORIENT_OPS = {
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.transpose(1, 0, 2),
    6: _rot_cw,
    7: lambda a: a.transpose(1, 0, 2)[::-1, ::-1],
    8: _rot_ccw,
}


def load_photo(path: PathLike, *, gray: bool = False) -> np.ndarray:
    """Read a photo as 8-bit RGB, upright as a viewer shows it.

    The EXIF ``Orientation`` tag is applied (``PIL.ImageOps.exif_transpose``), so a portrait
    phone photo stored as rotated landscape JPEG comes back portrait. Gray, gray+alpha, RGBA
    (alpha dropped), palette, CMYK, 1-bit, 16-bit and float images are converted.

    Parameters
    ----------
    path : str or os.PathLike
        Image file (JPEG, PNG, TIFF, BMP, WebP, ... anything PIL or OpenCV decodes).
    gray : bool, optional
        Return a single-channel gray image instead of RGB (JPEGs are then decoded straight to
        gray, which is faster).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` uint8 RGB, or ``(H, W)`` uint8 when ``gray=True``. C-contiguous.

    Raises
    ------
    PhotoError
        The file is missing, empty, truncated, corrupt, not an image or in an unsupported
        pixel format. The message is one line and names the file.
    """
    p = _check_file(path)
    im = _open(p)
    if im is not None and not gray:
        arr = _fast_jpeg(im, p)
        if arr is not None:
            im.close()
            return arr
    if im is None:
        arr = _cv2_fallback(p, gray)
        if arr is None:
            raise PhotoError(f"{p}: not an image (unrecognised file format)")
        return arr
    from PIL import Image, ImageOps

    try:
        with im:
            if gray and im.format == "JPEG" and im.mode in ("RGB", "YCbCr"):
                im.draft("L", None)  # libjpeg converts to gray while decoding
            im.load()
            try:
                up = ImageOps.exif_transpose(im)
            except Exception:  # noqa: BLE001 - a malformed EXIF block must not lose the photo
                up = im
            if up is None:  # pragma: no cover - old Pillow in_place semantics
                up = im
            return _pil_to_array(up, p, gray)
    except PhotoError:
        raise
    except Image.DecompressionBombError as exc:
        raise PhotoError(f"{p}: image too large to decode safely ({_short(exc)})") from None
    except MemoryError:
        raise PhotoError(f"{p}: not enough memory to decode the image") from None
    except Exception as exc:  # noqa: BLE001 - truncated/corrupt data raises OSError, SyntaxError, ...
        msg = _short(exc)
        if "truncated" in msg.lower():
            raise PhotoError(f"{p}: truncated image file ({msg})") from None
        raise PhotoError(f"{p}: corrupt or unreadable image ({msg})") from None


def read_image_size(path: PathLike) -> tuple[int, int]:
    """Size of a photo as :func:`load_photo` would return it, without decoding the pixels.

    Only the header is read, so this is cheap even for 50 MP photos; a file whose pixel data
    is truncated is only detected by :func:`load_photo`.

    Parameters
    ----------
    path : str or os.PathLike
        Image file.

    Returns
    -------
    tuple of int
        ``(width, height)`` in pixels after the EXIF orientation is applied.

    Raises
    ------
    PhotoError
        Missing, empty or unrecognised file.
    """
    p = _check_file(path)
    im = _open(p)
    if im is None:
        arr = _cv2_fallback(p, gray=True)
        if arr is None:
            raise PhotoError(f"{p}: not an image (unrecognised file format)")
        return int(arr.shape[1]), int(arr.shape[0])
    with im:
        w, h = im.size
        try:
            orientation = int(im.getexif().get(_EXIF_ORIENTATION_TAG, 1))
        except Exception:  # noqa: BLE001
            orientation = 1
    if orientation in _SWAPPING_ORIENTATIONS:
        w, h = h, w
    return int(w), int(h)
