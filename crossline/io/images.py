"""Read and write the images of a capture (PNG, TIFF, BMP, JPEG; grey or colour), with errors
that name the file.

Decoding uses OpenCV (libpng/libspng through ``cv2.imdecode``), which releases the GIL so
that frames can be decoded in parallel threads; ``benchmarks/`` compares it with the other
decoders tried. ``png_info`` walks the PNG chunks and checks their CRCs without decoding the
pixels, which finds truncated and corrupt files in a fraction of a decode's time;
``image_info`` does the same for every format (Pillow's lazy header parse for the others), and
refuses a header that claims more than ``MAX_PIXELS`` before anything is allocated.
"""

from __future__ import annotations

import io
import struct
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from crossline.errors import CrosslineError
from crossline.io.atomic import atomic_path

# libpng's warnings about broken files would duplicate the errors raised here
cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)

__all__ = [
    "CHANNELS",
    "IMAGE_EXTENSIONS",
    "MAX_PIXELS",
    "ImageError",
    "ImageInfo",
    "PngInfo",
    "image_info",
    "png_info",
    "read_image",
    "read_image_channels",
    "write_image",
    "write_png",
]

# the file name extensions a capture's images may have (compared in lower case)
IMAGE_EXTENSIONS = (".png", ".tif", ".tiff", ".bmp", ".jpg", ".jpeg")
CHANNELS = ("grey", "red", "green", "blue")
MAX_PIXELS = 100_000_000  # a header claiming more is refused before any allocation

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


_PNG_CHANNELS = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}  # palette images decode to colour
# Pillow's modes: (samples per pixel, bits per sample)
_MODES = {"1": (1, 1), "L": (1, 8), "P": (3, 8), "LA": (2, 8), "PA": (4, 8), "RGB": (3, 8),
          "RGBA": (4, 8), "RGBX": (4, 8), "CMYK": (4, 8), "YCbCr": (3, 8), "I": (1, 32),
          "F": (1, 32), "I;16": (1, 16), "I;16B": (1, 16), "I;16L": (1, 16), "I;16N": (1, 16)}


@dataclass(frozen=True)
class ImageInfo:
    """What an image's header says: size, bits per sample, samples per pixel, file format."""

    width: int
    height: int
    bit_depth: int
    channels: int  # 1 grey, 2 grey+alpha, 3 colour, 4 colour+alpha
    format: str  # PNG | TIFF | BMP | JPEG

    @property
    def colour(self) -> bool:
        """True for a colour image (3 or 4 channels)."""
        return self.channels >= 3


def _too_large(path: Path, w: int, h: int) -> None:
    if w < 1 or h < 1:
        raise ImageError(f"{path}: header claims an empty image ({w}x{h} px)")
    if w * h > MAX_PIXELS:
        raise ImageError(f"{path}: header claims {w}x{h} px, more than the "
                         f"{MAX_PIXELS // 1_000_000} MP an image may have")


def _pillow_header(path: Path, fp) -> tuple[ImageInfo, dict, list]:
    """Header of a TIFF, BMP or JPEG through Pillow's lazy open (no pixels decoded)."""
    from PIL import Image

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            im = Image.open(fp, formats=["TIFF", "BMP", "JPEG", "PNG"])
            fmt, mode, (w, h) = im.format, im.mode, im.size
            tags = dict(im.tag_v2) if fmt == "TIFF" else {}
            tile = list(im.tile)
    except Image.DecompressionBombError as exc:
        raise ImageError(f"{path}: header claims more than the {MAX_PIXELS // 1_000_000} MP an "
                         f"image may have ({exc})") from exc
    except Image.UnidentifiedImageError as exc:
        raise ImageError(f"{path}: not a PNG, TIFF, BMP or JPEG image, or its header is "
                         f"truncated or corrupt") from exc
    except Exception as exc:  # any parser failure on untrusted bytes is a bad file
        raise ImageError(f"{path}: corrupt or truncated image header "
                         f"({type(exc).__name__}: {exc})") from exc
    _too_large(path, w, h)
    channels, bits = _MODES.get(mode, (0, 0))
    if fmt == "TIFF":
        try:
            per = tags.get(258, (1,))
            per = tuple(per) if isinstance(per, tuple | list) else (per,)
            bits = int(per[0]) if len(set(per)) == 1 else 0
            channels = int(tags.get(277, channels))
        except (TypeError, ValueError):
            bits = 0
    if channels == 0:
        raise ImageError(f"{path}: {fmt} image of an unsupported pixel mode {mode!r}")
    return ImageInfo(w, h, bits, channels, str(fmt)), tags, tile


def _check_extent(path: Path, info: ImageInfo, tags: dict, tile: list, size: int, tail: bytes) -> None:
    """Refuse a TIFF, BMP or JPEG that ends before the pixel data its header describes."""
    if info.format == "JPEG" and b"\xff\xd9" not in tail:
        raise ImageError(f"{path}: truncated JPEG (no end-of-image marker)")
    if info.format == "TIFF":
        for off_tag, count_tag in ((273, 279), (324, 325)):
            if off_tag in tags and count_tag in tags:
                try:
                    offs, counts = tuple(tags[off_tag]), tuple(tags[count_tag])
                    need = max(int(o) + int(c) for o, c in zip(offs, counts, strict=False))
                except (TypeError, ValueError):
                    raise ImageError(f"{path}: corrupt TIFF (unreadable strip table)") from None
                if need > size:
                    raise ImageError(f"{path}: truncated TIFF (its strips need bytes up to "
                                     f"{need}, file has {size})")
    if info.format == "BMP" and tile and tile[0].codec_name == "raw":
        offset, stride = tile[0].offset, tile[0].args[1] if len(tile[0].args) > 1 else 0
        need = offset + abs(int(stride)) * info.height
        if need > size:
            raise ImageError(f"{path}: truncated BMP (pixel data needs {need} bytes, file has {size})")


def image_info(path: str | Path) -> ImageInfo:
    """Header of a PNG, TIFF, BMP or JPEG after checking that the file holds its pixel data.

    PNGs go through :func:`png_info` (chunk structure and CRCs); the others through Pillow's
    lazy header parse, with the strip table (TIFF), pixel array size (BMP) or end-of-image
    marker (JPEG) checked against the file's length. Nothing is decoded.
    """
    path = Path(path)
    try:
        with open(path, "rb") as f:
            head = f.read(32)
            size = f.seek(0, io.SEEK_END)
            f.seek(max(0, size - 1024))
            tail = f.read()
    except OSError as exc:
        raise ImageError(f"{path}: cannot be read ({exc.strerror})") from exc
    if head.startswith(_SIGNATURE):
        if len(head) >= 24 and head[12:16] == b"IHDR":
            _too_large(path, *struct.unpack(">II", head[16:24]))
        png = png_info(path)
        return ImageInfo(png.width, png.height, 8 if png.colour_type == 3 else png.bit_depth,
                         _PNG_CHANNELS.get(png.colour_type, 0), "PNG")
    with open(path, "rb") as f:
        info, tags, tile = _pillow_header(path, f)
    _check_extent(path, info, tags, tile, size, tail)
    return info


def _header_size(path: Path, data: bytes) -> None:
    """Refuse, before decoding, bytes whose header claims an image too large to allocate."""
    if data.startswith(_SIGNATURE):
        if len(data) >= 24 and data[12:16] == b"IHDR":
            _too_large(path, *struct.unpack(">II", data[16:24]))
        return
    info, tags, tile = _pillow_header(path, io.BytesIO(data))
    _check_extent(path, info, tags, tile, len(data), data[-1024:])


def _decode(path: Path, data: bytes | None) -> np.ndarray:
    """The image as stored: (H, W) grey or (H, W, C) in OpenCV's BGR(A) order, 8 or 16 bit."""
    if data is None:
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise ImageError(f"{path}: cannot be read ({exc.strerror})") from exc
    _header_size(path, data)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise ImageError(f"{path}: unreadable or corrupt image ({exc.err})") from exc
    if img is None:
        raise ImageError(f"{path}: unreadable or truncated image")
    if img.dtype not in (np.uint8, np.uint16):
        raise ImageError(f"{path}: expected 8- or 16-bit samples, got {img.dtype}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    return img


def read_image(
    path: str | Path,
    shape: tuple[int, int] | None = None,
    data: bytes | None = None,
    channel: str | None = None,
) -> np.ndarray:
    """Decode an image to a (height, width) uint8/uint16 array of one channel, never scaled.

    ``shape`` is the expected (height, width); ``data`` the file's bytes if already read.
    ``channel``: ``red``, ``green`` or ``blue`` takes that channel of a colour image; ``grey``
    or None its luminance (``cv2.cvtColor``); a grey image is returned as it is, whatever
    ``channel`` says. Alpha is dropped.
    """
    path = Path(path)
    if channel not in (None, *CHANNELS):
        raise ValueError(f"channel must be one of {CHANNELS} or None, got {channel!r}")
    img = _decode(path, data)
    if img.ndim == 3:
        c = img.shape[2]
        if c == 2:  # grey + alpha
            img = img[:, :, 0]
        elif channel in ("red", "green", "blue"):
            img = img[:, :, {"blue": 0, "green": 1, "red": 2}[channel]]
        else:
            img = cv2.cvtColor(img, cv2.COLOR_BGRA2GRAY if c == 4 else cv2.COLOR_BGR2GRAY)
        img = np.ascontiguousarray(img)
    if shape is not None and img.shape != tuple(shape):
        raise ImageError(
            f"{path}: image is {img.shape[1]}x{img.shape[0]} px, expected "
            f"{shape[1]}x{shape[0]} px"
        )
    return img


def read_image_channels(path: str | Path, data: bytes | None = None) -> np.ndarray:
    """Decode an image to (height, width, C): C = 1 for grey, 3 in the order red, green, blue
    for colour (alpha dropped); uint8/uint16, never scaled."""
    path = Path(path)
    img = _decode(path, data)
    if img.ndim == 2:
        return img[:, :, None]
    if img.shape[2] == 2:
        return np.ascontiguousarray(img[:, :, :1])
    return np.ascontiguousarray(img[:, :, 2::-1])


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


def write_image(path: str | Path, img: np.ndarray, jpeg_quality: int = 95) -> None:
    """Write a uint8/uint16 grey (H, W) or colour (H, W, 3, order red, green, blue) image
    atomically, its format from the extension (.png .tif .tiff .bmp .jpg .jpeg)."""
    path = Path(path)
    ext = path.suffix.lower()
    if ext not in IMAGE_EXTENSIONS:
        raise ValueError(f"{path}: extension must be one of {IMAGE_EXTENSIONS}")
    if ext == ".png" and img.ndim == 2:
        write_png(path, img)
        return
    if img.dtype not in (np.uint8, np.uint16) or img.ndim not in (2, 3) or (
        img.ndim == 3 and img.shape[2] != 3
    ):
        raise ValueError(f"write_image takes a uint8/uint16 (H, W) or (H, W, 3) array, got "
                         f"{img.dtype} {img.shape}")
    if ext in (".jpg", ".jpeg", ".bmp") and img.dtype != np.uint8:
        raise ValueError(f"{path}: {ext} holds 8-bit samples only, got {img.dtype}")
    bgr = img if img.ndim == 2 else np.ascontiguousarray(img[:, :, ::-1])
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if ext in (".jpg", ".jpeg") else []
    ok, buf = cv2.imencode(ext, bgr, params)
    if not ok:
        raise ImageError(f"{path}: {ext} encoding failed")
    with atomic_path(path) as tmp:
        tmp.write_bytes(buf.tobytes())
