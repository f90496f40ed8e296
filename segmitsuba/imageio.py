"""EXR and PNG files for renders: float EXR with render metadata in the header, and an sRGB PNG preview.

EXR pixels are 32-bit floats by default, or 16-bit half floats (``half=True``: half the size, 11 significant
bits, finite up to :data:`HALF_MAX`), compressed losslessly (ZIP by default, or PIZ).

EXR goes through the OpenEXR Python package (not ``mi.Bitmap``) so that arbitrary channel names and typed
header attributes survive a round trip without a Mitsuba variant being set. Header floats are 32-bit (the
binding has no double attribute): store exact values as text/JSON.
"""

from __future__ import annotations

import json
import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

#: header attributes that every EXR file has; they describe the file layout, not the render
_LAYOUT_ATTRIBUTES = frozenset(
    {
        "channels", "compression", "dataWindow", "displayWindow", "lineOrder", "pixelAspectRatio",
        "screenWindowCenter", "screenWindowWidth", "type", "tiles", "version", "chunkCount", "name",
    }
)
#: where write_exr records the channel order (EXR itself stores channels sorted by name)
CHANNEL_ORDER_ATTRIBUTE = "channelOrder"

_INT32 = (-(2**31), 2**31 - 1)
#: the largest finite half float
HALF_MAX = 65504.0
#: lossless EXR compressions that :func:`write_exr` offers: name -> OpenEXR constant
COMPRESSIONS = {"zip": "ZIP_COMPRESSION", "piz": "PIZ_COMPRESSION", "zips": "ZIPS_COMPRESSION",
                "rle": "RLE_COMPRESSION", "none": "NO_COMPRESSION"}


def default_channels(count: int) -> list[str]:
    """Channel names for an image with ``count`` channels and no names: Y, Y+A, RGB, RGBA, then C<i>."""
    known = {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}
    return known.get(count, ["R", "G", "B", "A"][: min(count, 4)] + [f"C{i}" for i in range(4, count)])


def _attribute(value: Any) -> str | int | float:
    """A header value that OpenEXR stores faithfully (it silently wraps ints beyond 32 bits, rejects numpy
    scalars and drops lists): bools and small ints as int, floats as double, everything else as text/JSON."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int):
        return value if _INT32[0] <= value <= _INT32[1] else str(value)
    if isinstance(value, (float, str)):
        return value
    if isinstance(value, os.PathLike):
        return os.fspath(value)
    return json.dumps(value, default=str, sort_keys=True)


def write_exr(
    path: str | os.PathLike,
    image: np.ndarray,
    channels: Sequence[str] | None = None,
    metadata: Mapping[str, Any] | None = None,
    half: bool = False,
    compression: str = "zip",
) -> None:
    """Write ``image`` (H x W x C or H x W) as an EXR file: float32 pixels, or half floats with ``half``
    (ValueError if a value is not finite as a half, beyond :data:`HALF_MAX`), losslessly compressed
    (``compression``: one of :data:`COMPRESSIONS`, default ZIP).

    ``channels`` names the C channels (default: see :func:`default_channels`). ``metadata`` becomes header
    attributes: str, int (32-bit), float and bool are stored as such, anything else (dicts, lists, big ints)
    as JSON/decimal text. Keys that clash with EXR's own layout attributes are refused.
    """
    import OpenEXR

    if compression not in COMPRESSIONS:
        raise ValueError(f"write_exr: compression must be one of {', '.join(COMPRESSIONS)}, got {compression!r}")
    image = np.asarray(image, dtype=np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or image.shape[0] == 0 or image.shape[1] == 0 or image.shape[2] == 0:
        raise ValueError(f"write_exr: expected an H x W x C image, got shape {image.shape}")
    names = list(channels) if channels is not None else default_channels(image.shape[2])
    if len(names) != image.shape[2]:
        raise ValueError(f"write_exr: {len(names)} channel names for an image with {image.shape[2]} channels")
    if len(set(names)) != len(names):
        raise ValueError(f"write_exr: duplicate channel names {names}")

    if half:
        big = np.abs(image[np.isfinite(image)])
        if big.size and big.max() > HALF_MAX:
            raise ValueError(f"write_exr: {big.max():.6g} does not fit a half float (at most {HALF_MAX:g})")
        image = image.astype(np.float16)

    header: dict[str, Any] = {"compression": getattr(OpenEXR, COMPRESSIONS[compression]),
                              "type": OpenEXR.scanlineimage}
    for key, value in (metadata or {}).items():
        if key in _LAYOUT_ATTRIBUTES or key == CHANNEL_ORDER_ATTRIBUTE:
            raise ValueError(f"write_exr: metadata key {key!r} is reserved by the EXR format")
        header[str(key)] = _attribute(value)
    header[CHANNEL_ORDER_ATTRIBUTE] = ",".join(names)

    pixels = {name: np.ascontiguousarray(image[..., i]) for i, name in enumerate(names)}
    tmp = f"{os.fspath(path)}.tmp{os.getpid()}.exr"
    try:  # write then rename, so an interrupted write never leaves a truncated file under the real name
        OpenEXR.File(header, pixels).write(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def read_exr(path: str | os.PathLike) -> tuple[np.ndarray, dict[str, Any]]:
    """Read an EXR file as (H x W x C float32 image, metadata).

    The metadata holds the file's own header attributes (not the layout ones) and ``"channels"``: the channel
    names in image order, which is the order given to :func:`write_exr` (else R, G, B, A first, then by name).
    """
    import OpenEXR

    f = OpenEXR.File(os.fspath(path), separate_channels=True)
    header = dict(f.header())
    planes = {name: np.asarray(ch.pixels, dtype=np.float32) for name, ch in f.channels().items()}

    stored = header.get(CHANNEL_ORDER_ATTRIBUTE)
    order = stored.split(",") if isinstance(stored, str) else []
    if sorted(order) != sorted(planes):
        rank = {"R": 0, "G": 1, "B": 2, "A": 3}
        order = sorted(planes, key=lambda n: (rank.get(n, 4), n))
    image = np.stack([planes[n] for n in order], axis=-1)
    metadata = {k: v for k, v in header.items() if k not in _LAYOUT_ATTRIBUTES and k != CHANNEL_ORDER_ATTRIBUTE}
    metadata["channels"] = order
    return image, metadata


def to_srgb8(image: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Tone-map linear RGB (H x W x >=3, or H x W x 1/2 grey) to 8-bit sRGB: scale by 2^exposure, clamp, sRGB
    transfer curve. Extra channels (alpha, AOVs) are ignored, so premultiplied RGB shows over black."""
    image = np.asarray(image, dtype=np.float64)
    if image.ndim == 2:
        image = image[..., None]
    rgb = image[..., :3] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=2)
    x = np.clip(np.nan_to_num(rgb * 2.0**exposure, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1.0 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def write_png(path: str | os.PathLike, image: np.ndarray, exposure: float = 0.0) -> None:
    """Write an 8-bit sRGB PNG preview of a linear image (see :func:`to_srgb8`)."""
    import mitsuba as mi  # Bitmap is variant-independent

    bitmap = mi.Bitmap(to_srgb8(image, exposure), pixel_format=mi.Bitmap.PixelFormat.RGB)
    bitmap.write(os.fspath(path))
