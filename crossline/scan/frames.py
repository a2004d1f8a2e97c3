"""Read the frames of a scan once, streamed, decoded and processed in parallel threads.

Two pieces:

- :func:`decode_png`, a grey-PNG decoder faster than ``cv2.imdecode`` on scan frames
  (``python benchmarks/bench_scan.py`` prints both decoders' ms per frame): libdeflate
  (through ``imagecodecs``) inflates, a numba kernel undoes the PNG row filters. Both
  release the GIL. It handles what scan frames are (grey, 8 or 16 bit, not interlaced) and
  hands anything else to ``cv2.imdecode``; it needs the optional packages ``numba`` and
  ``imagecodecs`` and falls back to OpenCV without them. Identical pixels either
  way (PNG is lossless; the tests compare both decoders on every filter type). Each worker
  thread reuses its inflate and row buffers from frame to frame.
- :func:`read_frame`, one frame file to a grey array: grey PNGs by :func:`decode_png`, every
  other format a capture may hold (TIFF, BMP, JPEG, colour PNG) by
  :func:`crossline.io.images.read_image` with the rig's colour channel.
- :func:`map_frames`, an ordered map over frame files with a bounded number of frames in
  flight: memory stays flat however long the scan is.
"""

from __future__ import annotations

import os
import struct
import threading
import zlib
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import TypeVar

import cv2
import numpy as np

from crossline.io.images import ImageError
from crossline.jit import HAVE_NUMBA, jit

__all__ = ["DECODERS", "decode_png", "fast_decoder_available", "keep_freed_memory", "map_frames",
           "read_frame"]

T = TypeVar("T")

_SIGNATURE = b"\x89PNG\r\n\x1a\n"

try:  # optional accelerators: libdeflate inflate and a JIT row-unfilter kernel
    import imagecodecs as _imagecodecs

    _inflate_lib = _imagecodecs.deflate_decode if _imagecodecs.DEFLATE.available else None
except ImportError:  # pragma: no cover - depends on the environment
    _inflate_lib = None


def _average4_py(raw: np.ndarray, r: int, stride: int, out: np.ndarray) -> None:
    """Undo the Average filter (1 byte per pixel) of rows r..r+3 (r >= 1) as one wavefront.

    Each row's recurrence (its left neighbour feeds the next pixel) is latency-bound; row
    j + 1 at column x needs row j only at column x, so the four rows run skewed by one column
    and their four independent chains overlap. The carries stay in registers: updated in the
    order 3, 2, 1, 0, row j - 1's carry still holds the pixel above row j's.
    """
    s = stride + 1
    b0 = r * s + 1
    b1 = b0 + s
    b2 = b1 + s
    b3 = b2 + s
    a0 = np.int32(0)
    a1 = np.int32(0)
    a2 = np.int32(0)
    a3 = np.int32(0)
    for t in range(stride + 3):
        if t >= 3 and t < stride:  # all four rows inside: no bounds to test
            a3 = (np.int32(raw[b3 + t - 3]) + ((a3 + a2) >> 1)) & 255
            a2 = (np.int32(raw[b2 + t - 2]) + ((a2 + a1) >> 1)) & 255
            a1 = (np.int32(raw[b1 + t - 1]) + ((a1 + a0) >> 1)) & 255
            a0 = (np.int32(raw[b0 + t]) + ((a0 + np.int32(out[r - 1, t])) >> 1)) & 255
            out[r + 3, t - 3] = a3
            out[r + 2, t - 2] = a2
            out[r + 1, t - 1] = a1
            out[r, t] = a0
            continue
        if 0 <= t - 3 < stride:
            a3 = (np.int32(raw[b3 + t - 3]) + ((a3 + a2) >> 1)) & 255
            out[r + 3, t - 3] = a3
        if 0 <= t - 2 < stride:
            a2 = (np.int32(raw[b2 + t - 2]) + ((a2 + a1) >> 1)) & 255
            out[r + 2, t - 2] = a2
        if 0 <= t - 1 < stride:
            a1 = (np.int32(raw[b1 + t - 1]) + ((a1 + a0) >> 1)) & 255
            out[r + 1, t - 1] = a1
        if t < stride:
            a0 = (np.int32(raw[b0 + t]) + ((a0 + np.int32(out[r - 1, t])) >> 1)) & 255
            out[r, t] = a0


_average4 = jit(_average4_py)


def _unfilter_py(raw: np.ndarray, h: int, stride: int, bpp: int, out: np.ndarray) -> bool:
    """PNG row unfiltering (filter types 0-4) into ``out`` (h, stride); False on a bad type."""
    s = stride + 1
    r = 0
    while r < h:
        base = r * s + 1
        f = raw[base - 1]
        if (f == 3 and bpp == 1 and r >= 1 and r + 3 < h and raw[base - 1 + s] == 3
                and raw[base - 1 + 2 * s] == 3 and raw[base - 1 + 3 * s] == 3):
            _average4(raw, r, stride, out)  # the simulator's frames: every row Average
            r += 4
            continue
        if f == 0:
            for x in range(stride):
                out[r, x] = raw[base + x]
        elif f == 1:
            for x in range(stride):
                a = np.int32(out[r, x - bpp]) if x >= bpp else np.int32(0)
                out[r, x] = (np.int32(raw[base + x]) + a) & 255
        elif f == 2:
            if r == 0:
                for x in range(stride):
                    out[r, x] = raw[base + x]
            else:
                for x in range(stride):
                    out[r, x] = (np.int32(raw[base + x]) + np.int32(out[r - 1, x])) & 255
        elif f == 3:
            if bpp == 1:
                # carry the left neighbour in a register: the recurrence is latency-bound
                a = np.int32(0)
                for x in range(stride):
                    b = np.int32(out[r - 1, x]) if r > 0 else np.int32(0)
                    a = (np.int32(raw[base + x]) + ((a + b) >> 1)) & 255
                    out[r, x] = a
            else:
                for x in range(stride):
                    a = np.int32(out[r, x - bpp]) if x >= bpp else np.int32(0)
                    b = np.int32(out[r - 1, x]) if r > 0 else np.int32(0)
                    out[r, x] = (np.int32(raw[base + x]) + ((a + b) >> 1)) & 255
        elif f == 4:
            for x in range(stride):
                a = np.int32(out[r, x - bpp]) if x >= bpp else np.int32(0)
                b = np.int32(out[r - 1, x]) if r > 0 else np.int32(0)
                c = np.int32(out[r - 1, x - bpp]) if (x >= bpp and r > 0) else np.int32(0)
                p = a + b - c
                pa = abs(p - a)
                pb = abs(p - b)
                pc = abs(p - c)
                if pa <= pb and pa <= pc:
                    pr = a
                elif pb <= pc:
                    pr = b
                else:
                    pr = c
                out[r, x] = (np.int32(raw[base + x]) + pr) & 255
        else:
            return False
        r += 1
    return True


_unfilter = jit(_unfilter_py) if HAVE_NUMBA else None


def fast_decoder_available() -> bool:
    """True when the libdeflate + numba PNG decoder can be used (else OpenCV decodes)."""
    return _unfilter is not None and _inflate_lib is not None


def _inflate(data: bytes, size: int, out: np.ndarray | None = None) -> bytes | np.ndarray:
    """zlib stream to bytes (into ``out``, of ``size`` bytes, when given)."""
    if _inflate_lib is not None:
        return _inflate_lib(data, out=size if out is None else out)
    return zlib.decompress(data)  # pragma: no cover - without imagecodecs


def _decode_cv2(data: bytes, path: str | Path) -> np.ndarray:
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise ImageError(f"{path}: unreadable or truncated image")
    return img


def _decode_fast(data: bytes, path: str | Path, transposed: bool = False) -> np.ndarray | None:
    """Decode a plain grey PNG (``transposed``: 8-bit ones as (width, height)); None if it is
    of a kind left to OpenCV."""
    if not data.startswith(_SIGNATURE) or len(data) < 33:
        return None
    length, ctype = struct.unpack(">I4s", data[8:16])
    if ctype != b"IHDR" or length != 13:
        return None
    if zlib.crc32(data[12:29]) & 0xFFFFFFFF != struct.unpack(">I", data[29:33])[0]:
        raise ImageError(f"{path}: corrupt PNG (CRC mismatch in IHDR)")
    w, h, depth, colour, comp, filt, interlace = struct.unpack(">IIBBBBB", data[16:29])
    if colour != 0 or depth not in (8, 16) or comp or filt or interlace or w == 0 or h == 0:
        return None
    idat: list[bytes] = []
    pos = 33
    n = len(data)
    while True:
        if pos + 8 > n:
            raise ImageError(f"{path}: truncated PNG (file ends at byte {n} before IEND)")
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 12 + length
        if end > n:
            raise ImageError(f"{path}: truncated PNG (chunk {ctype!r} runs past the end of the file)")
        if ctype == b"IDAT":
            idat.append(data[pos + 8 : pos + 8 + length])
        elif ctype == b"IEND":
            break
        elif ctype[0] & 0x20 == 0:  # an unknown critical chunk (e.g. PLTE): not ours
            return None
        pos = end
    if not idat:
        raise ImageError(f"{path}: corrupt PNG (no image data)")
    bpp = depth // 8
    stride = w * bpp
    size = h * (stride + 1)
    bufs = _buffers(size, (h, stride))
    try:
        raw = _inflate(b"".join(idat), size, bufs[0])
    except Exception as exc:  # libdeflate/zlib raise their own error types
        raise ImageError(f"{path}: corrupt PNG image data ({exc})") from exc
    if len(raw) != size:
        raise ImageError(f"{path}: corrupt PNG (image data of {len(raw)} bytes, expected {size})")
    # transposed, the rows are undone into this thread's scratch array and cv2.transpose
    # (cache-blocked, GIL released) writes the result: cheaper than unfiltering through a
    # transposed view, whose stores stride across the whole image
    scratch = transposed or depth == 16  # the result is a new array made from ``out``
    out = bufs[1] if scratch else np.empty((h, stride), np.uint8)
    if not _unfilter(np.frombuffer(raw, np.uint8), h, stride, bpp, out):
        raise ImageError(f"{path}: corrupt PNG (unknown row filter type)")
    if depth == 8 and transposed:
        return cv2.transpose(out)
    if depth == 16:
        img = out.view(">u2").astype(np.uint16)
        return cv2.transpose(img) if transposed else img
    return out


_local = threading.local()


def _buffers(size: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """This thread's inflate output and row scratch arrays, reused from frame to frame
    (fresh ones of 2 MB each would be fresh pages, faulted in on every frame)."""
    b = getattr(_local, "bufs", None)
    if b is None or b[0].size != size or b[1].shape != shape:
        b = _local.bufs = (np.empty(size, np.uint8), np.empty(shape, np.uint8))
    return b


DECODERS = ("auto", "fast", "opencv")


def decode_png(data: bytes, path: str | Path = "<bytes>", decoder: str = "auto",
               transposed: bool = False) -> np.ndarray:
    """Decode a grey 8/16-bit PNG's bytes to a (height, width) uint8/uint16 array.

    ``decoder``: ``fast`` (libdeflate + numba, see module doc), ``opencv`` (``cv2.imdecode``)
    or ``auto`` (fast when available). ``transposed`` returns the image transposed, a
    C-contiguous (width, height) array (each image column contiguous, as the stripe
    extractors scan it), made without a separate transpose by the fast decoder. Errors
    name ``path``.
    """
    if decoder not in DECODERS:
        raise ValueError(f"decoder must be one of {DECODERS}, got {decoder!r}")
    if decoder != "opencv" and fast_decoder_available():
        img = _decode_fast(data, path, transposed)
        if img is not None:
            return img
    elif decoder == "fast":
        raise RuntimeError("the fast PNG decoder needs the packages numba and imagecodecs")
    img = _decode_cv2(data, path)
    return np.ascontiguousarray(cv2.transpose(img) if img.ndim == 2 else img.swapaxes(0, 1)) \
        if transposed else img


def _as_grey(data: bytes, path: Path, channel: str | None) -> np.ndarray:
    """Any other image (TIFF, BMP, JPEG, colour or palette PNG) as one grey channel."""
    from crossline.io.images import read_image

    return read_image(path, data=data, channel=channel)


def read_frame(
    path: str | Path, shape: tuple[int, int] | None = None, decoder: str = "auto",
    transposed: bool = False, channel: str | None = None,
) -> np.ndarray:
    """Read and decode one grey frame; ``shape`` (height, width) is checked if given.

    Grey PNGs take :func:`decode_png`; every other format the capture may hold (TIFF, BMP,
    JPEG, colour PNG) goes to :func:`crossline.io.images.read_image`, which gives the
    ``channel`` of a colour image (the rig's ``sensor.channel``; None = its automatic choice).
    ``transposed``: return it as (width, height), see :func:`decode_png`.
    """
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise ImageError(f"{path}: cannot be read ({exc.strerror})") from exc
    img = None
    if data.startswith(_SIGNATURE):
        if decoder not in DECODERS:
            raise ValueError(f"decoder must be one of {DECODERS}, got {decoder!r}")
        if decoder != "opencv" and fast_decoder_available():
            img = _decode_fast(data, path, transposed)
        elif decoder == "fast":
            raise RuntimeError("the fast PNG decoder needs the packages numba and imagecodecs")
        else:
            img = _decode_cv2(data, path)
            if img.ndim != 2:
                img = None
            elif transposed:
                img = cv2.transpose(img)
    if img is None:
        img = _as_grey(data, path, channel)
        if img.ndim != 2:
            raise ImageError(f"{path}: expected a single-channel grey image, got shape {img.shape}")
        if transposed:
            img = cv2.transpose(img)
    h, w = img.shape[::-1] if transposed else img.shape
    if shape is not None and (h, w) != tuple(shape):
        raise ImageError(f"{path}: image is {w}x{h} px, expected {shape[1]}x{shape[0]} px")
    return img


def map_frames(
    paths: Iterable[str | Path],
    fn: Callable[[int, np.ndarray], T],
    *,
    shape: tuple[int, int] | None = None,
    threads: int = 1,
    in_flight: int | None = None,
    decoder: str = "auto",
    transposed: bool = False,
    channel: str | None = None,
    on_read_error: Callable[[int, BaseException], None] | None = None,
) -> Iterator[T]:
    """Yield ``fn(i, image)`` for the i-th frame file, in order, reading each file once.

    With ``transposed``, ``image`` is the frame as (width, height) (:func:`decode_png`);
    ``channel`` is the colour channel of colour frames (:func:`read_frame`).

    Reading, decoding and ``fn`` run together in ``threads`` worker threads (decoding and
    OpenCV/numpy kernels release the GIL); at most ``in_flight`` frames (default 2 per
    thread) are being worked on or waiting, so memory does not grow with the scan length.
    ``on_read_error(i, exc)`` is told of a file that cannot be read before its error is
    raised (an ``fn`` of a later frame may be waiting for that one).
    """
    threads = max(1, int(threads))
    in_flight = max(1, in_flight or 2 * threads)

    def work(i: int, p: str | Path) -> T:
        try:
            img = read_frame(p, shape, decoder, transposed, channel)
        except BaseException as exc:
            if on_read_error is not None:
                on_read_error(i, exc)
            raise
        return fn(i, img)

    paths = list(paths)
    if threads == 1:
        for i, p in enumerate(paths):
            yield work(i, p)
        return
    pending: deque[Future[T]] = deque()
    with ThreadPoolExecutor(threads, thread_name_prefix="frames") as pool:
        try:
            for i, p in enumerate(paths):
                if len(pending) >= in_flight:
                    yield pending.popleft().result()
                pending.append(pool.submit(work, i, p))
            while pending:
                yield pending.popleft().result()
        finally:
            for f in pending:
                f.cancel()


M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (glibc malloc.h)
MMAP_THRESHOLD = 32 << 20  # glibc's largest on 64-bit: blocks up to it come from the heap
TRIM_THRESHOLD = 1 << 30  # free memory the heap keeps before it gives any back


def keep_freed_memory() -> bool:
    """Let the process's heap keep the frame-sized blocks it frees, for the next frame (glibc).

    A scan stage allocates and frees arrays of a frame's size every frame. glibc serves a block
    above its mmap threshold with a fresh mapping and unmaps it when freed, and gives back heap
    tops above its trim threshold, so the next frame faults the same pages in again and the
    kernel zeroes them, every frame (docs/method.md gives the figures). A fixed mmap
    threshold (glibc's largest) and a large trim threshold keep the blocks; the process's peak
    memory is what it was, only not returned until it ends. Returns whether both were set
    (False where the C library has no ``mallopt``: nothing is changed).
    """
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (macOS, musl builds without it)
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(M_TRIM_THRESHOLD,
                                                                             TRIM_THRESHOLD))


def default_threads() -> int:
    """CPU threads available to this process."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
