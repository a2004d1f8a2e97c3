"""Read and write the grey PNG images of a capture, with errors that name the file.

Decoding uses OpenCV (libpng/libspng through ``cv2.imdecode``), which releases the GIL so
that frames can be decoded in parallel threads; ``benchmarks/`` compares it with the other
decoders tried. ``png_info`` walks the PNG chunks and checks their CRCs without decoding the
pixels, which finds truncated and corrupt files in a fraction of a decode's time.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crossline.errors import CrosslineError
from crossline.io.atomic import atomic_path

# libpng's warnings about broken files would duplicate the errors raised here
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)

__all__ = ["ImageError", "PngInfo", "png_info", "read_image", "write_png"]

_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey+alpha", 6: "RGBA"}


class ImageError(CrosslineError, ValueError):
    """An image file that cannot be used: unreadable, truncated, or of the wrong size or type."""


@dataclass(frozen=True)
class PngInfo:
    """What a PNG header says: size, bit depth and colour type."""

    width: int
    height: int
    bit_depth: int
    colour_type: int

    @property
    def colour(self) -> str:
        """Colour type as a word (``grey``, ``RGB``, ...)."""
        return _COLOUR_TYPES.get(self.colour_type, f"type {self.colour_type}")


def png_info(path: str | Path, check_crc: bool = True) -> PngInfo:
    """Header of a PNG file after checking its chunk structure (and CRCs) up to IEND."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageError(f"{path}: cannot be read ({exc.strerror})") from exc
    if not data.startswith(_SIGNATURE):
        raise ImageError(f"{path}: not a PNG file (bad signature)")
    pos = len(_SIGNATURE)
    info: PngInfo | None = None
    seen_idat = False
    while True:
        if pos + 8 > len(data):
            raise ImageError(f"{path}: truncated PNG (file ends at byte {len(data)} before IEND)")
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 8 + length + 4
        if end > len(data):
            raise ImageError(
                f"{path}: truncated PNG (chunk {ctype.decode('latin-1')!r} needs bytes up to "
                f"{end}, file has {len(data)})"
            )
        body = data[pos + 8 : pos + 8 + length]
        if check_crc:
            (crc,) = struct.unpack(">I", data[pos + 8 + length : end])
            if zlib.crc32(ctype + body) & 0xFFFFFFFF != crc:
                raise ImageError(f"{path}: corrupt PNG (CRC mismatch in chunk {ctype!r} at {pos})")
        if ctype == b"IHDR":
            if length != 13:
                raise ImageError(f"{path}: corrupt PNG (IHDR of {length} bytes)")
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
            info = PngInfo(w, h, depth, colour)
        elif ctype == b"IDAT":
            seen_idat = True
        elif ctype == b"IEND":
            break
        pos = end
    if info is None or not seen_idat:
        raise ImageError(f"{path}: corrupt PNG (no IHDR or no image data)")
    return info


def read_image(
    path: str | Path,
    shape: tuple[int, int] | None = None,
    data: bytes | None = None,
) -> np.ndarray:
    """Decode a grey 8- or 16-bit PNG to a (height, width) uint8/uint16 array.

    ``shape`` is the expected (height, width); ``data`` the file's bytes if already read.
    """
    path = Path(path)
    if data is None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ImageError(f"{path}: cannot be read ({exc.strerror})") from exc
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ImageError(f"{path}: unreadable or corrupt image ({exc.err})") from exc
    if img is None:
        raise ImageError(f"{path}: unreadable or truncated image")
    if img.ndim != 2:
        raise ImageError(f"{path}: expected a single-channel grey image, got shape {img.shape}")
    if shape is not None and img.shape != tuple(shape):
        raise ImageError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} px, expected "
            f"{shape[1]}x{shape[0]} px"
        )
    return img


PNG_PARAMS = [cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY,
              cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY, cv2.IMWRITE_PNG_FILTER, cv2.IMWRITE_PNG_FILTER_AVG]


def write_png(path: str | Path, img: np.ndarray) -> None:
    """Write a grey uint8/uint16 image as PNG atomically; same array, same bytes.

    The Average row filter, zlib level 1, Huffman coding only: noisy sensor images have no
    long repeats for LZ77 to find, and one fixed filter (the smooth background predicted from
    the left and upper neighbours) spares libpng's per-row trial of all five; both encode
    faster for about the same size. PNG is lossless: any decoder reads the array back.
    """
    if img.dtype not in (np.uint8, np.uint16) or img.ndim != 2:
        raise ValueError(f"write_png takes a 2-D uint8 or uint16 array, got {img.dtype} {img.shape}")
    ok, buf = cv2.imencode(".png", img, PNG_PARAMS)
    if not ok:
        raise ImageError(f"{path}: PNG encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
