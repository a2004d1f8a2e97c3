"""What a scan's frames are measured on: the colour channel and the sensor's data range.

Split from :mod:`crossline.scan.stripes` (issue 21.3). Both are chosen once per scan,
before its frames are extracted, from the same up to ``DATA_RANGE_FRAMES`` frames spread over
the whole scan (:func:`_sample_frames`), so that every chunk of a chunked run chooses alike:
:func:`scan_channel` (rig.yaml's ``sensor.channel``, else the channel in which the stripes
stand highest above the noise) and :func:`_data_range` (``sensor.data_bits``, else inferred).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from crossline.scan.stripe_levels import data_bits_for, frame_levels

__all__ = [
    "CHANNEL_DISC_PX",
    "DATA_RANGE_FRAMES",
    "scan_channel",
]

DATA_RANGE_FRAMES = 16  # frames spread over a scan that the data range is inferred from
CHANNEL_DISC_PX = 31  # wider than a stripe (3-12 px, more where it grazes a surface)


def _data_range(paths: list[Path], data_bits: int | None, shape, decoder: str,
                channel: str | None = None) -> dict[str, Any]:
    """The sensor's data range: ``rig.yaml``'s ``sensor.data_bits``, else inferred.

    Inferred from the largest value over up to ``DATA_RANGE_FRAMES`` frames spread evenly over
    the whole scan (the same frames for every chunk, so chunks agree), rounded up to
    ``2^b - 1`` for the fewest bits ``b`` of :data:`DATA_BITS` that hold it; an 8-bit container
    holds 8 bits.
    """
    from crossline.scan.frames import read_frame

    if data_bits is not None:
        return {"max": 2 ** int(data_bits) - 1, "bits": int(data_bits), "source": "rig.yaml sensor.data_bits"}
    if not paths:
        return {"max": 255, "bits": 8, "source": "no frames"}
    idx = _sample_frames(len(paths))
    top = 0
    for k in idx:
        img = read_frame(paths[k], shape, decoder, True, channel)
        if img.dtype == np.uint8:
            return {"max": 255, "bits": 8, "source": "8-bit frames"}
        top = max(top, int(img.max()))
    bits = data_bits_for(top)
    return {"max": 2**bits - 1, "bits": bits,
            "source": f"inferred from the frames (largest value {top} over {idx.size} frames)"}


def _sample_frames(n: int) -> np.ndarray:
    """Indices of up to ``DATA_RANGE_FRAMES`` frames spread evenly over a scan of ``n`` frames
    (the same for every chunk of the scan, so that chunks agree)."""
    return np.unique(np.linspace(0, n - 1, min(DATA_RANGE_FRAMES, n)).round().astype(int))


def scan_channel(paths: list[Path], channel: str | None, shape) -> dict[str, Any]:
    """The colour channel a scan's stripes are measured on: ``rig.yaml``'s, else chosen.

    Chosen (colour frames, no ``sensor.channel``) as the channel of red, green, blue and the
    luminance in which the stripes stand highest above their surroundings (the 99.9 %
    quantile of the frame less its opening by a disc of ``CHANNEL_DISC_PX``, wider than a
    stripe) in units of the channel's own noise (:func:`frame_levels`), summed over the frames
    the data range is inferred from: a red laser on a part lit white by the room stands out in
    red, not in the luminance that mixes in the other channels' noise, nor in a channel the
    room lights brightly. Grey frames have no choice to make.
    """
    from crossline.io.images import ImageError, read_image_channels

    if channel is not None:
        return {"name": channel, "source": "rig.yaml sensor.channel"}
    if not paths:
        return {"name": None, "source": "no frames"}
    names = ("red", "green", "blue", "grey")
    score = np.zeros(len(names))
    d = CHANNEL_DISC_PX // 2 | 1  # on every second pixel
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    for k in _sample_frames(len(paths)):
        rgb = read_image_channels(paths[k])  # a bad file raises ImageError naming it
        if rgb.shape[2] == 1:
            return {"name": None, "source": "grey frames"}
        if rgb.shape[:2] != tuple(shape):
            raise ImageError(f"{paths[k]}: image is {rgb.shape[1]}x{rgb.shape[0]} px, expected "
                             f"{shape[1]}x{shape[0]} px")
        grey = cv2.cvtColor(np.ascontiguousarray(rgb[:, :, ::-1]), cv2.COLOR_BGR2GRAY)
        for j, img in enumerate((rgb[:, :, 0], rgb[:, :, 1], rgb[:, :, 2], grey)):
            # a stripe is a ridge narrower than the disc: the opening takes it away, and what
            # stands above the opening is the stripe, not a patch the room lights brightly
            # (on every second pixel: a stripe at least 3 px wide keeps its peak)
            sub = np.ascontiguousarray(img[::2, ::2])
            ridge = sub.astype(np.float32) - cv2.morphologyEx(sub, cv2.MORPH_OPEN, disc)
            top = float(np.quantile(ridge, 0.999))
            score[j] += top / frame_levels(np.ascontiguousarray(img.T), 0.5)["noise"]
    best = int(np.argmax(score))
    shown = ", ".join(f"{n} {v:.0f}" for n, v in zip(names, score, strict=True))
    return {"name": names[best], "source": f"chosen: stripe over noise summed over frames ({shown})",
            "scores": dict(zip(names, score.round(3).tolist(), strict=True))}
