"""Every file the suite reads or writes: bounded readers (a size cap, UTF-8, NumPy archives
without pickles, images held to the rig file's pixel bound) that name the file and what was
expected, atomic writers (a temporary file renamed into place, with the usual mode), strict JSON
(no bare NaN: ``strict`` turns non-finite numbers into null) and the names that may become file
names.
"""

from __future__ import annotations

import io
import json
import math
import os
import re
import tempfile
import zlib
from pathlib import Path

import numpy as np


_UMASK = os.umask(0)
os.umask(_UMASK)


NAME_PATTERN = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")


def is_safe_name(name) -> bool:
    """A name that can become a file or folder name: letters, digits, ``_``, ``-``, ``.``; at
    most 64 characters; not ``.`` or ``..``."""
    return isinstance(name, str) and bool(NAME_PATTERN.match(name)) and name not in (".", "..")


class UnreadableFileError(ValueError):
    """A file that exists but cannot be parsed (torn by a kill, edited by hand, not ours)."""


def strict(x):
    """A JSON-ready copy of ``x``: numpy scalars and arrays become Python values, non-finite
    floats become None (with ``<key>_reason`` beside them in a mapping)."""
    if isinstance(x, dict):
        out = {}
        for k, v in x.items():
            k = str(k)
            out[k] = strict(v)
            reason = _non_finite(v)
            if reason:
                out[f"{k}_reason"] = reason
        return out
    if isinstance(x, (list, tuple)):
        return [strict(v) for v in x]
    if isinstance(x, np.ndarray):
        return strict(x.tolist())
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return strict(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, Path):
        return str(x)
    return x


def _non_finite(v) -> str | None:
    if isinstance(v, (float, np.floating)) and not math.isfinite(v):
        return "not a number" if math.isnan(v) else "infinite"
    return None


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same folder, then rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        os.fchmod(fd, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual mode
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def write_text(path, text: str) -> Path:
    return write_bytes(path, text.encode("utf-8"))


def write_json(path, obj) -> Path:
    """Strict JSON (see :func:`strict`), atomically."""
    return write_text(path, json.dumps(strict(obj), indent=2, allow_nan=False) + "\n")


def write_npy(path, array: np.ndarray) -> Path:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=False)
    return write_bytes(path, buf.getvalue())


def write_npz(path, **arrays) -> Path:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return write_bytes(path, buf.getvalue())


#: PNG colour type by channel count, for images in OpenCV's order (grey, BGR, BGRA).
_PNG_COLOUR = {1: 0, 3: 2, 4: 6}


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an 8- or 16-bit image as OpenCV holds it: grey (H, W) or (H, W, 1), BGR
    (H, W, 3) or BGRA (H, W, 4); ``cv2.imread(..., IMREAD_UNCHANGED)`` gives it back exactly.

    The rows go unfiltered into one IDAT chunk deflated by ISA-L at its fastest level: on a
    noisy 12 MP frame 35 ms against 110 ms for OpenCV's encoder (libpng's Huffman coding), at
    the same size (noise does not compress; a clean frame is 0.15 MB). Filters would gain 1 %
    on noisy frames and lose on clean ones, whose flat rows deflate to almost nothing.
    """
    from isal import isal_zlib

    image = np.asarray(image)
    channels = 1 if image.ndim == 2 else image.shape[2] if image.ndim == 3 else 0
    if image.dtype not in (np.uint8, np.uint16) or channels not in _PNG_COLOUR \
            or image.size == 0:
        raise ValueError(f"PNG: expected a non-empty 8- or 16-bit image of 1, 3 or 4 channels, "
                         f"got {image.dtype} of shape {image.shape}")
    h, w = image.shape[:2]
    pixels = image.reshape(h, w, channels)
    if channels > 1:  # BGR(A) -> RGB(A)
        pixels = pixels[..., [2, 1, 0, 3][:channels]]
    row_bytes = w * channels * image.itemsize
    rows = np.zeros((h, 1 + row_bytes), np.uint8)  # a 0 per row: filter type None
    rows[:, 1:] = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder(">")) \
        .view(np.uint8).reshape(h, row_bytes)

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (len(data).to_bytes(4, "big") + kind + data
                + zlib.crc32(data, zlib.crc32(kind)).to_bytes(4, "big"))

    header = (w.to_bytes(4, "big") + h.to_bytes(4, "big")
              + bytes([8 * image.itemsize, _PNG_COLOUR[channels], 0, 0, 0]))
    return b"".join([b"\x89PNG\r\n\x1a\n", chunk(b"IHDR", header),
                     chunk(b"IDAT", isal_zlib.compress(rows, 1)), chunk(b"IEND", b"")])


def write_png(path, image: np.ndarray) -> Path:
    return write_bytes(path, encode_png(image))


#: The largest file a reader takes from outside (a COLMAP model with its 2D points, a results
#: file of a long sweep); anything larger is refused before it is read into memory.
MAX_READ_BYTES = 256 << 20


def read_grey(path) -> np.ndarray | None:
    """An image file as 8-bit grey, or None when OpenCV cannot read it: not an image, or one
    whose header claims more pixels than OPENCV_IO_MAX_IMAGE_PIXELS (stereo_bench/__init__.py),
    which OpenCV refuses with an exception rather than None."""
    import cv2

    try:
        return cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    except cv2.error:
        return None


def read_text(path, what: str = "file", max_bytes: int = MAX_READ_BYTES) -> str:
    """The UTF-8 text of a file, or an UnreadableFileError naming it and ``what`` was expected:
    a folder, unreadable, over ``max_bytes``, or not UTF-8. A missing file raises
    FileNotFoundError, so that callers can tell absent from broken."""
    path = Path(path)
    try:
        if path.is_dir():
            raise UnreadableFileError(f"{path}: is a folder; expected a {what}")
        size = path.stat().st_size
        if size > max_bytes:
            raise UnreadableFileError(f"{path}: {size:,} bytes; a {what} is expected to be "
                                      f"under {max_bytes:,}")
        with open(path, "rb") as f:
            raw = f.read(max_bytes + 1)  # a file that grows while it is read is still bounded
    except FileNotFoundError:
        raise
    except OSError as e:
        raise UnreadableFileError(f"{path}: cannot read {what} ({e.strerror})") from None
    if len(raw) > max_bytes:
        raise UnreadableFileError(f"{path}: over {max_bytes:,} bytes; expected a {what}")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError as e:
        raise UnreadableFileError(f"{path}: not UTF-8 text (byte {e.start}); expected a "
                                  f"{what}") from None


def read_arrays(path, what: str = "array file"):
    """The array of an .npy file, or every array of an .npz as a dict (read whole, so that a
    torn member fails here and not at first use); an UnreadableFileError naming the file when
    it is not one numpy wrote (torn, truncated, flipped bytes, a pickle)."""
    import zipfile
    import zlib

    try:
        loaded = np.load(path, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            return loaded
        with loaded:
            return {k: loaded[k] for k in loaded.files}
    except FileNotFoundError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
        raise UnreadableFileError(f"{path}: unreadable ({type(e).__name__}: {e}); expected "
                                  f"{what}") from None


def read_json(path, what: str = "JSON file"):
    """Parse a JSON file; raise UnreadableFileError naming the file when it cannot be (too
    large, not UTF-8, not JSON, or nested past the parser's recursion limit)."""
    text = read_text(path, what)
    try:
        return json.loads(text)
    except ValueError as e:
        raise UnreadableFileError(f"{path}: unreadable (not JSON: {e}); expected a "
                                  f"{what}") from None
    except RecursionError:
        raise UnreadableFileError(f"{path}: unreadable (nested too deeply); expected a "
                                  f"{what}") from None
