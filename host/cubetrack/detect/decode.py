"""JPEG (or any OpenCV-readable image) bytes to 8-bit grayscale, decoding no more than is needed.

A JPEG goes to libjpeg-turbo through simplejpeg (PyPI wheels that bundle libjpeg-turbo, no system
package): the luma plane straight from the decoder, the pixels OpenCV's ``IMREAD_GRAYSCALE`` gives
(both are libjpeg-turbo's accurate integer IDCT; tested byte for byte), at less CPU. Anything
simplejpeg declines (another format, a JPEG it finds broken) goes to ``cv2.imdecode``, which
decodes what it can and reports the rest.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import simplejpeg

from cubetrack.core.errors import ImageError

_SEQUENTIAL_SOF = (0xC0, 0xC1)   # baseline and extended sequential, Huffman-coded
_STANDALONE_MARKERS = frozenset((0x01, *range(0xD0, 0xD9)))   # TEM, RSTn, SOI: no length field
_TOP_ROWS_MAX_PIXELS = 40_000_000   # larger tops decode in full


def read_gray(path: str | Path) -> np.ndarray:
    """An image file as 8-bit grayscale; ImageError naming the file when missing or corrupt."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except FileNotFoundError:
        raise ImageError(f"{path}: image file not found") from None
    except OSError as exc:
        raise ImageError(f"{path}: cannot read image: {exc.strerror or exc}") from None
    return decode_gray(data, str(path))


def decode_gray(jpeg: bytes, source: str = "JPEG", rows: int | None = None) -> np.ndarray:
    """Decode JPEG (or any OpenCV-readable image) bytes to an 8-bit grayscale image.

    ``rows``: only the top ``rows`` rows are needed (the regions a tracker searches end there).
    A sequential (baseline) JPEG is then decoded only down to the first MCU row boundary at or
    below them (:func:`_decode_top_rows`): an image of at least ``rows`` rows whose pixels are
    those of the full decode's top rows, at a fraction of its cost. Anything else, or ``rows``
    not above the image, is decoded in full.

    Raises ImageError naming ``source`` for empty, truncated or undecodable data. A JPEG must end
    with its end-of-image marker: libjpeg would otherwise pad a truncated frame with grey.
    """
    data = bytes(jpeg) if not isinstance(jpeg, bytes) else jpeg
    if len(data) == 0:
        raise ImageError(f"{source}: empty image data")
    is_jpeg = data[:2] == b"\xff\xd8"
    if is_jpeg and b"\xff\xd9" not in data[-64:]:
        raise ImageError(f"{source}: truncated JPEG (no end-of-image marker)")
    if is_jpeg:
        if rows is not None:
            top = _decode_top_rows(data, rows)
            if top is not None:
                return top
        gray = _turbo_gray(data, strict=True)
        if gray is not None:
            return gray
    try:
        gray = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
    except cv2.error as exc:
        raise ImageError(f"{source}: cannot decode image: {str(exc).strip().splitlines()[-1]}") from None
    if gray is None or gray.size == 0:
        raise ImageError(f"{source}: not a decodable JPEG/image ({len(data)} bytes)")
    return gray


def _turbo_gray(data: bytes | bytearray, strict: bool) -> np.ndarray | None:
    """The JPEG's luma plane (H, W) through simplejpeg, or None where it declines the data.
    ``strict``: libjpeg's warnings (corrupt data it would patch over) decline too."""
    try:
        gray = simplejpeg.decode_jpeg(data, colorspace="GRAY", strict=strict)
    except ValueError:   # simplejpeg's one error for data libjpeg-turbo rejects (or warns about, when strict)
        return None
    return gray[..., 0] if gray.ndim == 3 else gray   # (H, W, 1): the channel axis dropped (a view, C-contiguous)


def _sequential_frame_header(data: bytes) -> tuple[int, int, int, int, int] | None:
    """A sequential 8-bit JPEG's frame header: (offset of its SOF marker, height, width, MCU
    height in rows, components), or None (another kind of JPEG, a height given later by DNL, or data that
    does not parse: the caller decodes it in full, where errors are reported)."""
    i, end = 2, min(len(data), 65536)
    while i + 4 <= end:
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:        # fill byte
            i += 1
            continue
        if marker in _STANDALONE_MARKERS:
            i += 2
            continue
        length = (data[i + 2] << 8) | data[i + 3]
        if marker in _SEQUENTIAL_SOF:
            if i + 10 > len(data) or data[i + 4] != 8:
                return None
            height, width, components = (data[i + 5] << 8) | data[i + 6], (data[i + 7] << 8) | data[i + 8], data[i + 9]
            if height == 0 or width == 0 or not 1 <= components <= 4 or i + 10 + 3 * components > len(data):
                return None
            # one component: its scan's MCU is one 8 x 8 block; interleaved: 8 x the largest vertical sampling
            v_max = 1 if components == 1 else max(data[i + 11 + 3 * c] & 0x0F for c in range(components))
            return i, height, width, 8 * max(v_max, 1), components
        if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC) or marker in (0xDA, 0xD9):
            return None           # progressive, lossless or arithmetic-coded; or no frame header first
        i += 2 + length
    return None


def _decode_top_rows(data: bytes, rows: int) -> np.ndarray | None:
    """The top of a sequential JPEG, down to the first MCU row boundary at or below ``rows``, as
    8-bit grayscale; None when that is the whole image or the data is not such a JPEG.

    The frame header's height is lowered to that boundary in a copy: a sequential decoder then
    decodes those MCU rows exactly as it would in the full image (entropy decoding runs top to
    bottom, each block's pixels depend only on its own coefficients) and skips the rest of the
    scan. libjpeg-turbo warns about the skipped data ("extraneous bytes"): not strict here, so
    that warning is not an error (a broken top fails the shape check or decodes as the full
    decode would; tested on mangled frames)."""
    header = _sequential_frame_header(data)
    if header is None:
        return None
    sof, height, width, mcu_rows, _components = header
    keep = -(-max(int(rows), 1) // mcu_rows) * mcu_rows
    if keep >= height or keep * width > _TOP_ROWS_MAX_PIXELS:
        return None
    patched = bytearray(data)
    patched[sof + 5:sof + 7] = keep.to_bytes(2, "big")
    gray = _turbo_gray(patched, strict=False)
    return gray if gray is not None and gray.shape == (keep, width) else None
