"""Photo loading for the whole toolkit.

Phones store most photos as landscape sensor data plus an EXIF ``Orientation`` tag; every
module of monodbh must see the photo the way a viewer shows it, so all photos go through
:func:`load_photo`, which applies the EXIF orientation (``PIL.ImageOps.exif_transpose``) and
converts every pixel format to 8-bit RGB (or 8-bit gray on request).

Errors are :class:`~monodbh.calib.errors.PhotoError` with a one-line message naming the file.

Hostile photos (see ``docs/decisions/photo-limits.md``): the header is read first and a photo
is refused *before* its pixels are decoded when it has more than :data:`MAX_PHOTO_PIXELS`
pixels, when the file is too small to hold the pixels its header claims (a JPEG needs at
least one bit per 8 x 8 block, a PNG at least 1/1032 of its raw size), when it is an
animation (GIF, APNG, WebP, AVIF with more than one frame; a multi-page TIFF or an MPO loads
its first picture) or when it is smaller than the caller's ``min_side_px``. JPEG data that
libjpeg reports as corrupt (its warnings, which PIL and OpenCV ignore) is an error too.
"""
from __future__ import annotations

import contextlib
import errno
import math
import os
import stat
import sys
import tempfile
import threading
import warnings
from pathlib import Path
from typing import Union

import numpy as np

from .errors import PhotoError

__all__ = ["load_photo", "read_image_size", "PathLike"]

PathLike = Union[str, "os.PathLike[str]"]

#: Most pixels a photo may have, checked on the header before decoding: above the 200 Mpx phone
#: sensors (16320 x 12240), with room for crops of stitched photos (photo-limits.md)
MAX_PHOTO_PIXELS = 250_000_000
#: Largest photo file read (a 200 Mpx phone JPEG is 30-100 MB; the file is read into memory)
MAX_PHOTO_BYTES = 512 * 1024 * 1024
#: Fewest bits a Huffman-coded JPEG spends per 8 x 8 block of its first component (a
#: progressive DC scan's shortest code); real encoders spend 15 or more on a flat gray photo
_JPEG_MIN_BITS_PER_BLOCK = 1
#: Deflate's largest compression ratio (a 258-byte match coded in 2 bits): the floor of a PNG
_DEFLATE_MAX_RATIO = 1032
#: Formats whose further frames are an animation: refused; TIFF pages and MPO pictures are not
_ANIMATED_FORMATS = frozenset({"GIF", "PNG", "WEBP", "AVIF", "FLI"})
#: JPEG markers that start a Huffman-coded frame (SOF0-3, SOF5-7; arithmetic coding has no floor)
_HUFFMAN_SOF = frozenset({0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7})
#: Any start-of-frame marker (SOF0-15 less DHT, JPG and DAC)
_ANY_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
#: Most bytes of a JPEG's start read to find its frame header (APP segments are <= 64 KB each)
_JPEG_HEAD_BYTES = 1 << 20
#: Most bytes of codec messages kept from one decode
_MAX_CODEC_TEXT = 8192

# EXIF orientations that swap width and height (transpose, rotate 90 CW, transverse, rotate 90 CCW).
_SWAPPING_ORIENTATIONS = (5, 6, 7, 8)
_EXIF_ORIENTATION_TAG = 0x0112

# libjpeg's warnings (printed to stderr by OpenCV's decoder, only the first of a decode) that mean
# the pixels are wrong: bad entropy-coded data, missing data, bad scan progression.
_CORRUPT_JPEG_TEXT = ("Corrupt JPEG data", "Premature end of JPEG file",
                      "Inconsistent progression sequence")
# Warnings that leave the pixels right (a broken ICC profile is metadata only).
_HARMLESS_JPEG_TEXT = ("Corrupt JPEG data: bad ICC marker",)
# Lines that codecs (libjpeg, libpng, libtiff, OpenCV's log) write to stderr during a decode:
# swallowed; any other text written there meanwhile (another thread's) is written back.
_CODEC_TEXT = _CORRUPT_JPEG_TEXT + (
    "Invalid SOS parameters", "Warning: unknown JFIF", "Unknown Adobe color transform",
    "Application transferred too many", "libpng", "[ WARN:", "[ERROR:", "[ INFO:", "OpenCV(",
    "TIFF", "JPEGLib", "OJPEG")

# Signatures of formats PIL reads itself: when PIL cannot open such a file, it is corrupt.
_PIL_SIGNATURES = ((b"\xff\xd8\xff", "JPEG"), (b"\x89PNG\r\n\x1a\n", "PNG"), (b"GIF8", "GIF"),
                   (b"BM", "BMP"), (b"RIFF", "WebP"))

_STDERR_LOCK = threading.Lock()   # one fd-2 redirection at a time (it is process-wide)
_PIL_READY = False


def _pil():
    """``PIL.Image``, with its decompression-bomb limit raised to :data:`MAX_PHOTO_PIXELS`.

    PIL warns above ``Image.MAX_IMAGE_PIXELS`` (89 Mpx by default) and refuses above twice
    that, which would refuse a 200 Mpx phone photo; this module checks its own limit on the
    header before decoding, so PIL's is raised to it (never lowered) once.
    """
    global _PIL_READY
    from PIL import Image

    if not _PIL_READY:
        limit = Image.MAX_IMAGE_PIXELS
        if limit is not None and limit < MAX_PHOTO_PIXELS:
            Image.MAX_IMAGE_PIXELS = MAX_PHOTO_PIXELS
        _PIL_READY = True
    return Image


@contextlib.contextmanager
def _quiet():
    """Silence PIL's Python warnings (corrupt EXIF, palette transparency, bomb warnings)."""
    from PIL import Image

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", category=Image.DecompressionBombWarning)
        warnings.filterwarnings("ignore", module=r"PIL(\.|$)")
        warnings.filterwarnings("ignore", module=r"monodbh\.calib\.photo$")
        yield


@contextlib.contextmanager
def _codec_stderr():
    """Collect what C codecs print on file descriptor 2 while the block runs.

    libjpeg reports corrupt data as warnings, which OpenCV's decoder prints on the process's
    stderr (the first of each decode) and does not return. The block runs with fd 2 pointed at
    an anonymous temporary file (``os.dup2``; under a lock, as fd 2 is shared by all threads);
    afterwards the lines of codecs (:data:`_CODEC_TEXT`) are put in the yielded list and any
    other text (another thread's output) is written back to stderr. Where fd 2 cannot be
    redirected the block runs unobserved.

    Yields
    ------
    list of str
        Filled with the codecs' lines when the block ends.
    """
    lines: list[str] = []
    with _STDERR_LOCK:
        saved, tmp = None, None
        try:
            with contextlib.suppress(Exception):
                sys.stderr.flush()
            tmp = tempfile.TemporaryFile()
            saved = os.dup(2)
            os.dup2(tmp.fileno(), 2)
        except OSError:
            if saved is not None:
                os.close(saved)
            if tmp is not None:
                tmp.close()
            saved = tmp = None
        try:
            yield lines
        finally:
            if saved is not None:
                os.dup2(saved, 2)
                os.close(saved)
                tmp.seek(0)
                text = tmp.read(_MAX_CODEC_TEXT).decode("utf-8", "replace")
                tmp.close()
                _sort_codec_text(text, lines)


def _sort_codec_text(text: str, lines: list) -> None:
    """Codec lines of ``text`` into ``lines``; the rest written back to fd 2."""
    other = []
    for line in text.splitlines():
        s = line.strip()
        if not s:
            continue
        if s.startswith(_CODEC_TEXT) or "Warning, " in s:
            lines.append(s)
        else:
            other.append(line)
    if other:
        with contextlib.suppress(OSError):
            os.write(2, ("\n".join(other) + "\n").encode("utf-8", "replace"))


def _corrupt_jpeg_message(lines) -> str | None:
    """The first of libjpeg's ``lines`` that says the pixels are wrong, or None."""
    for s in lines:
        if s.startswith(_CORRUPT_JPEG_TEXT) and not s.startswith(_HARMLESS_JPEG_TEXT):
            return s if len(s) <= 120 else s[:117] + "..."
    return None


def _os_problem(exc: OSError) -> str:
    """The problem an ``OSError`` from opening a photo names, in a few words."""
    if exc.errno in (errno.ENOENT, errno.ENOTDIR):
        return "no such file"
    if exc.errno == errno.ELOOP:
        return "symbolic link loop, not a photo"
    if exc.errno in (errno.EACCES, errno.EPERM):
        return "permission denied"
    return f"cannot read ({exc.strerror or exc})"


def _check_file(path: PathLike) -> tuple[Path, int]:
    """The photo's path and size in bytes: a readable, non-empty regular file within limits."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    try:
        st = os.stat(p)
    except OSError as exc:
        raise PhotoError(f"{p}: {_os_problem(exc)}") from None
    except ValueError:  # an embedded NUL byte
        raise PhotoError(f"{p!r}: not a valid file name") from None
    if stat.S_ISDIR(st.st_mode):
        raise PhotoError(f"{p}: is a directory, not a photo")
    if not stat.S_ISREG(st.st_mode):
        raise PhotoError(f"{p}: not a regular file (a device, pipe or socket), not a photo")
    if st.st_size == 0:
        raise PhotoError(f"{p}: file is empty")
    if st.st_size > MAX_PHOTO_BYTES:
        raise PhotoError(f"{p}: file is {st.st_size / 2**20:.0f} MB, larger than any photo "
                         f"(at most {MAX_PHOTO_BYTES // 2**20} MB)")
    try:
        with open(p, "rb"):
            pass
    except OSError as exc:
        raise PhotoError(f"{p}: {_os_problem(exc)}") from None
    return p, int(st.st_size)


def _open(p: Path):
    """PIL's lazily decoded image (only the header read), or None where PIL does not know it."""
    Image = _pil()
    from PIL import UnidentifiedImageError

    try:
        with _quiet():
            return Image.open(p)
    except UnidentifiedImageError:
        return None  # let the caller try OpenCV's decoders, then report "not an image"
    except Image.DecompressionBombError as exc:
        raise PhotoError(f"{p}: image too large to decode ({_bomb_pixels(exc)}at most "
                         f"{MAX_PHOTO_PIXELS / 1e6:.0f} Mpx)") from None
    except PermissionError:
        raise PhotoError(f"{p}: permission denied") from None
    except MemoryError:
        raise PhotoError(f"{p}: not enough memory to read the image header") from None
    except Exception as exc:  # noqa: BLE001 - any decoder failure is bad input
        raise PhotoError(f"{p}: cannot read image ({_short(exc)})") from None


def _bomb_pixels(exc: BaseException) -> str:
    """``"900 Mpx; "`` from PIL's decompression-bomb message, or ``""``."""
    import re

    m = re.search(r"\((\d+) pixels\)", str(exc))
    return f"{int(m.group(1)) / 1e6:.0f} Mpx; " if m else ""


def _kb(n: int) -> str:
    """A file size in words: bytes, KB or MB."""
    if n < 10 * 1024:
        return f"{n} bytes"
    return f"{n / 1024:.0f} KB" if n < 10 * 2**20 else f"{n / 2**20:.0f} MB"


def _check_size(p: Path, w: int, h: int, orientation: int, min_side_px: int) -> None:
    """Refuse an empty, too large or (below ``min_side_px``) too small picture of ``w x h``."""
    if w < 1 or h < 1:
        raise PhotoError(f"{p}: corrupt image (the header says {w}x{h} px)")
    if w * h > MAX_PHOTO_PIXELS:
        raise PhotoError(f"{p}: image too large to decode ({w}x{h} px = {w * h / 1e6:.0f} Mpx; "
                         f"at most {MAX_PHOTO_PIXELS / 1e6:.0f} Mpx)")
    if min(w, h) < min_side_px:
        if orientation in _SWAPPING_ORIENTATIONS:
            w, h = h, w
        raise PhotoError(f"{p}: photo is {w}x{h} px, too small to measure "
                         f"(at least {min_side_px} px a side)")


def _orientation(im) -> int:
    """The EXIF orientation ``exif_transpose`` applies (2-8), or 1 for none or garbage."""
    try:
        with _quiet():
            o = im.getexif().get(_EXIF_ORIENTATION_TAG, 1)
        return int(o) if o in _ORIENT_OPS else 1
    except Exception:  # noqa: BLE001 - malformed EXIF, unhashable values: not rotated
        return 1


def _jpeg_frame(head: bytes) -> int | None:
    """The start-of-frame marker (``0xC0``-``0xCF``) of the JPEG starting with ``head``, or None.

    Examples
    --------
    >>> hex(_jpeg_frame(bytes.fromhex("ffd8 ffe0 0004 0000 ffc2 0011 08")))
    '0xc2'
    """
    n, i = len(head), 2
    while i + 4 <= n and head[i] == 0xFF:
        marker = head[i + 1]
        if marker == 0xFF:
            i += 1
            continue
        if marker in _ANY_SOF:
            return marker
        if marker in (0xD9, 0xDA):
            return None
        if 0xD0 <= marker <= 0xD7 or marker == 0x01:
            i += 2
            continue
        i += 2 + ((head[i + 2] << 8) | head[i + 3])
    return None


def _min_file_bytes(im, p: Path) -> int:
    """Fewest bytes a valid file of ``im``'s format and size can have (0: no floor known).

    A Huffman-coded JPEG spends at least :data:`_JPEG_MIN_BITS_PER_BLOCK` per 8 x 8 block of
    its first (full-resolution) component; a PNG's deflated data is at least its raw size
    (rows with their filter byte) divided by :data:`_DEFLATE_MAX_RATIO`.
    """
    w, h = im.size
    try:
        with open(p, "rb") as f:
            if im.format in ("JPEG", "MPO"):
                head = f.read(1 << 16)                 # most headers; else up to 1 MiB
                frame = _jpeg_frame(head) or _jpeg_frame(head + f.read(_JPEG_HEAD_BYTES))
                if frame in _HUFFMAN_SOF:
                    blocks = math.ceil(w / 8) * math.ceil(h / 8)
                    return blocks * _JPEG_MIN_BITS_PER_BLOCK // 8
            elif im.format == "PNG":
                head = f.read(26)
                if len(head) == 26 and head[12:16] == b"IHDR":
                    depth, colour = head[24], head[25]
                    channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 1)
                    raw = h * (1 + math.ceil(w * channels * depth / 8))
                    return raw // _DEFLATE_MAX_RATIO
    except OSError:
        return 0
    return 0


def _check_header(im, p: Path, nbytes: int, min_side_px: int) -> int:
    """Refuse a photo on its header (see the module's docstring); its EXIF orientation.

    Raises
    ------
    PhotoError
        Too large, too small, an animation, or a file too small for the pixels it claims.
    """
    w, h = im.size
    orientation = _orientation(im)
    _check_size(p, w, h, orientation, min_side_px)
    if im.format in _ANIMATED_FORMATS:
        try:
            with _quiet():
                frames = int(getattr(im, "n_frames", 1)) if getattr(im, "is_animated", False) else 1
        except Exception as exc:  # noqa: BLE001 - a broken second frame
            raise PhotoError(f"{p}: cannot read image ({_short(exc)})") from None
        if frames > 1:
            raise PhotoError(f"{p}: animated image ({frames} frames); give a single photo")
    floor = _min_file_bytes(im, p)
    if nbytes < floor:
        raise PhotoError(f"{p}: corrupt image (the header says {w}x{h} px but the file holds "
                         f"only {_kb(nbytes)})")
    return orientation


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




def _fallback_size(p: Path) -> tuple[int, int] | None:
    """``(width, height)`` from the header of a file PIL does not open, for OpenCV, or None.

    Only formats whose size is read here are handed to OpenCV (its decoders allocate the
    whole picture a header claims before reading the data): TIFF (classic, first page),
    Netpbm including PAM and PFM, and Radiance HDR.
    """
    try:
        with open(p, "rb") as f:
            head = f.read(4096)
    except OSError:
        return None
    if head[:4] in (b"II*\x00", b"MM\x00*"):
        return _tiff_size(p, head[:2])
    if len(head) > 2 and head[:1] == b"P" and head[1:2] in b"1234567Ff":
        return _netpbm_size(head)
    if head.startswith(b"#?"):
        for line in head.split(b"\n"):
            parts = line.split()
            if len(parts) == 4 and parts[0] in (b"-Y", b"+Y") and parts[2] in (b"+X", b"-X"):
                try:
                    return int(parts[3]), int(parts[1])
                except ValueError:
                    return None
    return None


def _netpbm_size(head: bytes) -> tuple[int, int] | None:
    """Width and height of a PBM/PGM/PPM/PAM/PFM header (comments skipped)."""
    text = b"\n".join(line.split(b"#")[0] for line in head.split(b"\n"))
    tokens = text.split()
    try:
        if head[1:2] == b"7":
            keys = {tokens[i]: tokens[i + 1] for i in range(1, len(tokens) - 1)}
            return int(keys[b"WIDTH"]), int(keys[b"HEIGHT"])
        return int(tokens[1]), int(tokens[2])
    except (KeyError, IndexError, ValueError):
        return None


def _tiff_size(p: Path, order: bytes) -> tuple[int, int] | None:
    """Width and height (tags 256, 257) of a classic TIFF's first directory."""
    import struct

    e = "<" if order == b"II" else ">"
    try:
        with open(p, "rb") as f:
            f.seek(4)
            (ifd,) = struct.unpack(e + "I", f.read(4))
            f.seek(ifd)
            (count,) = struct.unpack(e + "H", f.read(2))
            entries = f.read(12 * min(count, 4096))
    except (OSError, struct.error):
        return None
    size = {}
    for k in range(len(entries) // 12):
        tag, typ, _n = struct.unpack(e + "HHI", entries[12 * k:12 * k + 8])
        if tag in (256, 257):
            fmt = e + ("H" if typ == 3 else "I")
            size[tag] = struct.unpack(fmt, entries[12 * k + 8:12 * k + 8 + struct.calcsize(fmt)])[0]
    return (size[256], size[257]) if len(size) == 2 else None


def _fallback_load(p: Path, gray: bool, min_side_px: int) -> np.ndarray:
    """A photo PIL cannot open, decoded by OpenCV when its header says it is safe to."""
    with open(p, "rb") as f:
        head = f.read(16)
    for sig, name in _PIL_SIGNATURES:
        if head.startswith(sig) and (name != "WebP" or head[8:12] == b"WEBP"):
            raise PhotoError(f"{p}: corrupt {name} file (its header cannot be read)")
    size = _fallback_size(p)
    if size is None:
        raise PhotoError(f"{p}: not an image (unrecognised file format)")
    _check_size(p, size[0], size[1], 1, min_side_px)
    arr = _cv2_fallback(p, gray)
    if arr is None:
        raise PhotoError(f"{p}: corrupt or unreadable image (OpenCV cannot decode it)")
    return arr


def _cv2_fallback(p: Path, gray: bool) -> np.ndarray | None:
    """Decode formats PIL does not know (e.g. PFM, Radiance HDR) with OpenCV, or None."""
    import cv2

    try:
        buf = np.fromfile(str(p), dtype=np.uint8)
        with _codec_stderr():
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




def _decode_jpeg(p: Path, data: bytes, flags: int) -> np.ndarray | None:
    """``cv2.imdecode`` of a JPEG's bytes; corrupt data (libjpeg's warnings) is an error.

    libjpeg-turbo decodes corrupt entropy-coded data (overwritten bytes, a lost stretch)
    into wrong pixels and reports it only as a warning ("Corrupt JPEG data: 37 extraneous
    bytes before marker 0xd9", "... premature end of data segment", "Premature end of JPEG
    file"), which neither PIL nor OpenCV returns; OpenCV's decoder prints the first warning of
    each decode on stderr, so the decode runs with stderr collected (:func:`_codec_stderr`,
    about 0.1 ms). A structural scan of the data for impossible markers was rejected: most
    corruption keeps the markers valid and is found only by decoding the Huffman codes.
    Limit: libjpeg prints only the first warning of a decode, so corrupt data after a
    harmless warning (an unknown JFIF revision) goes unseen.

    Returns
    -------
    numpy.ndarray or None
        The decoded array, or None where OpenCV does not decode the file.

    Raises
    ------
    PhotoError
        ``"PATH: corrupt JPEG data (<libjpeg's warning>)"``.
    """
    import cv2

    with _codec_stderr() as lines:
        try:
            a = cv2.imdecode(np.frombuffer(data, np.uint8), flags)  # (no copy of the bytes)
        except cv2.error:
            a = None
    bad = _corrupt_jpeg_message(lines)
    if bad is not None:
        raise PhotoError(f"{p}: corrupt JPEG data ({bad})")
    return a


def _check_jpeg_data(p: Path) -> None:
    """Check a complete JPEG that PIL decodes (gray, CMYK, MPO) for corrupt data.

    The check decodes at 1/8 scale (libjpeg still reads every Huffman code, skipping most
    of the inverse DCT): about 45 ms for a 12 MP photo. A file without its end marker is left
    to PIL, which reports it as truncated.
    """
    import cv2

    try:
        data = p.read_bytes()
    except OSError:
        return
    if _jpeg_complete(data):
        _decode_jpeg(p, data, cv2.IMREAD_REDUCED_GRAYSCALE_8 | cv2.IMREAD_IGNORE_ORIENTATION)


def _check_png_data(p: Path) -> None:
    """Check the CRC of every critical chunk (IHDR, PLTE, IDAT, IEND, ...) of a PNG.

    PIL checks the CRCs of the chunks before the pixel data but not those of ``IDAT``, and
    deflate's own checksum at the stream's end is not read once all rows are decoded: a PNG
    with overwritten pixel data would load with wrong pixels. ``zlib.crc32`` reads about
    1 GB/s (20 ms for a 12 MP PNG). Ancillary chunks (lower-case first letter) are skipped as
    libpng does; a file that ends before ``IEND`` is left to PIL, which reports it truncated.
    """
    import struct
    import zlib

    try:
        data = memoryview(p.read_bytes())
    except OSError:
        return
    i, n = 8, len(data)
    while i + 12 <= n:
        length, ctype = struct.unpack(">I4s", data[i:i + 8])
        end = i + 8 + length
        if end + 4 > n:
            return
        if not ctype[0] & 0x20:
            (crc,) = struct.unpack(">I", data[end:end + 4])
            if zlib.crc32(data[i + 4:end]) != crc:
                name = ctype.decode("latin-1") if ctype.isalpha() else ctype.hex()
                raise PhotoError(f"{p}: corrupt PNG data (bad CRC in chunk {name} at byte {i})")
        if ctype == b"IEND":
            return
        i = end + 4


def _fast_jpeg(im, p: Path, gray: bool = False, orient: int | None = None) -> np.ndarray | None:
    """A plain RGB (or, with ``gray``, RGB or gray) JPEG decoded by OpenCV, upright, or None.

    ``PIL``'s decode, ``exif_transpose`` copy and array conversion take 250 ms for a 12 MP photo
    on the project's machine, ``cv2.imdecode`` 80-90 ms with the same pixels (both libjpeg-turbo,
    tested; with ``gray`` the same pixels as PIL's ``draft("L")`` decode). A complete
    (:func:`_jpeg_complete`) 8-bit JPEG takes this path, its EXIF orientation applied by the
    same exact array operation as ``exif_transpose`` (a portrait phone photo is stored as
    landscape with orientation 6); everything else (truncated files, which OpenCV would decode
    silently, CMYK) goes through PIL as before. Corrupt data raises (:func:`_decode_jpeg`).
    """
    if im.format != "JPEG" or im.mode not in (("RGB", "L") if gray else ("RGB",)):
        return None
    if orient is None:
        orient = _orientation(im)
    import cv2

    try:
        data = p.read_bytes()
    except OSError:
        return None
    if not _jpeg_complete(data):
        return None
    rgb_flag = getattr(cv2, "IMREAD_COLOR_RGB", None)       # OpenCV >= 4.10; else BGR, converted
    if gray:
        flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
    else:
        flags = (cv2.IMREAD_COLOR if rgb_flag is None else rgb_flag) | cv2.IMREAD_IGNORE_ORIENTATION
    a = _decode_jpeg(p, data, flags)
    if a is None or a.ndim != (2 if gray else 3) or a.shape[:2] != (im.size[1], im.size[0]):
        return None
    if rgb_flag is None and not gray:
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
#: 7 transverse, 8 rotate 90 counter-clockwise (same pixels, tested for all of them; RGB or gray)
_ORIENT_OPS = {
    2: lambda a: a[:, ::-1],
    3: lambda a: a[::-1, ::-1],
    4: lambda a: a[::-1],
    5: lambda a: a.swapaxes(0, 1),
    6: _rot_cw,
    7: lambda a: a.swapaxes(0, 1)[::-1, ::-1],
    8: _rot_ccw,
}


def _pil_decode(im, p: Path, gray: bool) -> np.ndarray:
    """Decode an opened PIL image, apply its EXIF orientation, convert (see :func:`load_photo`)."""
    from PIL import Image, ImageOps

    try:
        if gray and im.format == "JPEG" and im.mode in ("RGB", "YCbCr"):
            im.draft("L", None)  # libjpeg converts to gray while decoding
        with _quiet(), (_codec_stderr() if im.format == "TIFF" else contextlib.nullcontext()):
            im.load()                                   # (libtiff prints its warnings)
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
        raise PhotoError(f"{p}: image too large to decode ({_short(exc)})") from None
    except MemoryError:
        raise PhotoError(f"{p}: not enough memory to decode the image") from None
    except Exception as exc:  # noqa: BLE001 - truncated/corrupt data raises OSError, SyntaxError, ...
        msg = _short(exc)
        if "truncated" in msg.lower():
            raise PhotoError(f"{p}: truncated image file ({msg})") from None
        raise PhotoError(f"{p}: corrupt or unreadable image ({msg})") from None


def load_photo(path: PathLike, *, gray: bool = False, min_side_px: int = 0) -> np.ndarray:
    """Read a photo as 8-bit RGB, upright as a viewer shows it.

    The EXIF ``Orientation`` tag is applied (``PIL.ImageOps.exif_transpose``; a garbage value
    leaves the photo as stored), so a portrait phone photo stored as rotated landscape JPEG
    comes back portrait. Gray, gray+alpha, RGBA (alpha dropped), palette, CMYK, 1-bit, 16-bit
    and float images are converted. A multi-page TIFF or an MPO gives its first picture.

    The header is checked before the pixels are decoded (see the module's docstring and
    ``docs/decisions/photo-limits.md``): at most :data:`MAX_PHOTO_PIXELS` pixels and
    :data:`MAX_PHOTO_BYTES` bytes, a file large enough for its pixels, a single frame.

    Parameters
    ----------
    path : str or os.PathLike
        Image file (JPEG, PNG, TIFF, BMP, WebP, ... anything PIL decodes; PFM, PAM and
        Radiance HDR through OpenCV).
    gray : bool, optional
        Return a single-channel gray image instead of RGB (JPEGs are then decoded straight to
        gray, which is faster).
    min_side_px : int, optional
        Refuse a photo whose shorter side is below this many pixels (default 0: any size).

    Returns
    -------
    numpy.ndarray
        ``(H, W, 3)`` uint8 RGB, or ``(H, W)`` uint8 when ``gray=True``. C-contiguous.

    Raises
    ------
    PhotoError
        The file is missing, unreadable, empty, truncated, corrupt, not an image, too large,
        too small, animated or in an unsupported pixel format. The message is one line and
        names the file.
    """
    p, nbytes = _check_file(path)
    im = _open(p)
    if im is None:
        return _fallback_load(p, gray, min_side_px)
    with im:
        orient = _check_header(im, p, nbytes, min_side_px)
        arr = _fast_jpeg(im, p, gray, orient)
        if arr is not None:
            return arr
        if im.format in ("JPEG", "MPO"):
            _check_jpeg_data(p)
        elif im.format == "PNG":
            _check_png_data(p)
        return _pil_decode(im, p, gray)


def read_image_size(path: PathLike, *, min_side_px: int = 0) -> tuple[int, int]:
    """Size of a photo as :func:`load_photo` would return it, without decoding the pixels.

    Only the header is read, so this is cheap even for 50 MP photos, and the header checks
    of :func:`load_photo` apply (too large, too small, animated, too few bytes); a file whose
    pixel data is truncated or corrupt is only detected by :func:`load_photo`.

    Parameters
    ----------
    path : str or os.PathLike
        Image file.
    min_side_px : int, optional
        Refuse a photo whose shorter side is below this many pixels (default 0: any size).

    Returns
    -------
    tuple of int
        ``(width, height)`` in pixels after the EXIF orientation is applied.

    Raises
    ------
    PhotoError
        Missing, empty, unrecognised file, or refused on its header.
    """
    p, nbytes = _check_file(path)
    im = _open(p)
    if im is None:
        arr = _fallback_load(p, True, min_side_px)
        return int(arr.shape[1]), int(arr.shape[0])
    with im:
        w, h = im.size
        orientation = _check_header(im, p, nbytes, min_side_px)
    if orientation in _SWAPPING_ORIENTATIONS:
        w, h = h, w
    return int(w), int(h)
