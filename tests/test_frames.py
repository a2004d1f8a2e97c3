"""Frame reading: the fast grey-PNG path, and the other formats through read_image."""

from __future__ import annotations

import sys

import cv2
import numpy as np
import pytest

from crossline.io.images import ImageError, write_png
from crossline.scan.frames import fast_decoder_available, map_frames, read_frame


def _stripe_frame(h: int = 60, w: int = 90, seed: int = 0) -> np.ndarray:
    """A grey frame with a bright oblique stripe on a noisy background."""
    rng = np.random.default_rng(seed)
    v = np.arange(h)[:, None]
    u = np.arange(w)[None, :]
    img = 20 + 200 * np.exp(-0.5 * ((v - 20 - 0.3 * u) / 1.8) ** 2) + rng.normal(0, 2, (h, w))
    return np.clip(np.round(img), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("transposed", [False, True])
@pytest.mark.parametrize("decoder", ["auto", "opencv"])
def test_colour_png_falls_back_to_the_chosen_channel(tmp_path, transposed, decoder):
    grey = _stripe_frame()
    bgr = np.dstack([grey // 4, grey // 2, grey])  # a red laser: red holds the stripe
    p = tmp_path / "000000.png"
    assert cv2.imwrite(str(p), bgr)
    for channel, want in (("red", grey), ("green", grey // 2), ("blue", grey // 4),
                          (None, cv2.cvtColor(bgr, cv2.COLOR_BGR2GRAY))):
        img = read_frame(p, shape=grey.shape, decoder=decoder, transposed=transposed, channel=channel)
        assert img.dtype == np.uint8 and img.flags.c_contiguous
        np.testing.assert_array_equal(img, want.T if transposed else want)


def test_jpeg_frame_reads_as_opencv_decodes_it(tmp_path):
    grey = _stripe_frame(seed=1)
    p = tmp_path / "000001.jpg"
    assert cv2.imwrite(str(p), np.dstack([grey] * 3), [cv2.IMWRITE_JPEG_QUALITY, 95])
    want = cv2.cvtColor(cv2.imread(str(p), cv2.IMREAD_COLOR), cv2.COLOR_BGR2GRAY)
    # lossy: the decoded frame is what OpenCV decodes, and close to the written one
    np.testing.assert_array_equal(read_frame(p, shape=grey.shape), want)
    np.testing.assert_array_equal(read_frame(p, transposed=True), want.T)
    assert np.abs(want.astype(int) - grey).mean() < 3.0
    with pytest.raises(ImageError, match="expected 90x61 px"):
        read_frame(p, shape=(61, 90))


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_grey_png_same_pixels_by_every_path(tmp_path, dtype):
    grey = _stripe_frame(seed=2).astype(dtype) * (257 if dtype == np.uint16 else 1)
    p = tmp_path / "000002.png"
    write_png(p, grey)
    decoders = ["opencv"] + (["fast", "auto"] if fast_decoder_available() else [])
    for dec in decoders:
        for tr in (False, True):
            img = read_frame(p, shape=grey.shape, decoder=dec, transposed=tr, channel="red")
            assert img.dtype == dtype and img.flags.c_contiguous
            np.testing.assert_array_equal(img, grey.T if tr else grey)


def test_map_frames_mixes_formats_and_reuses_no_buffer_it_returned(tmp_path):
    # the fast decoder reuses per-thread scratch arrays: frames handed out must stay intact
    frames = [_stripe_frame(seed=s) for s in range(6)]
    paths = []
    for k, f in enumerate(frames):
        if k % 3 == 2:
            p = tmp_path / f"{k:06d}.bmp"
            assert cv2.imwrite(str(p), f)
        else:
            p = tmp_path / f"{k:06d}.png"
            write_png(p, f)
        paths.append(p)
    for threads in (1, 2):
        got = list(map_frames(paths, lambda i, im: (i, im), shape=frames[0].shape, threads=threads,
                              transposed=True))
        assert [i for i, _ in got] == list(range(6))
        for (_, im), f in zip(got, frames, strict=True):
            np.testing.assert_array_equal(im, f.T)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_freed_memory_stops_frame_sized_page_faults():
    """Three frame-sized arrays (a 2248 x 840 frame in float64) made and freed 40 times, as a
    frame's work does: with glibc's defaults the freed heap top exceeds its trim threshold and
    is given back, so the pages fault in again every time; with the heap keeping freed blocks
    they fault in once. Each in a fresh interpreter, the setting being for the whole process."""
    import subprocess

    code = (
        "import resource, sys, numpy as np\n"
        "from crossline.scan.frames import keep_freed_memory\n"
        "ok = keep_freed_memory() if sys.argv[1] == 'keep' else True\n"
        "n = 2248 * 840\n"
        "a = [np.ones(n) for _ in range(3)]; del a\n"  # the first ones fault either way
        "f0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt\n"
        "for _ in range(40):\n"
        "    a = [np.ones(n) for _ in range(3)]; sum(x.sum() for x in a); del a\n"
        "print(int(ok), resource.getrusage(resource.RUSAGE_SELF).ru_minflt - f0)\n")
    got = {}
    for mode in ("default", "keep"):
        out = subprocess.run([sys.executable, "-c", code, mode], capture_output=True, text=True,
                             check=True).stdout.split()
        assert out[0] == "1"
        got[mode] = int(out[1])
    pages = 3 * 2248 * 840 * 8 // 4096  # the three arrays' 4 KiB pages
    assert got["default"] > 2 * pages  # faulted in again, frame after frame
    assert got["keep"] < pages // 10  # kept
