"""EXR/PNG I/O of segmitsuba.imageio: round trips of pixels, channel names and metadata."""

from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest

from segmitsuba.imageio import read_exr, to_srgb8, write_exr, write_png


def test_rgb_round_trip_with_metadata(tmp_path):
    rng = np.random.default_rng(1)
    image = rng.random((5, 7, 3), dtype=np.float32) * 10
    metadata = {
        "integrator": "segment_pt",
        "spp": 64,
        "render_time": 1.5,
        "interrupted": True,
        "big": 2**40,  # beyond EXR's 32-bit int: kept as text, not silently wrapped
        "params": {"max_depth": 8, "rr": 0.5},
        "seeds": [0, 1],
        "count": np.int64(3),
    }
    path = tmp_path / "a.exr"
    write_exr(path, image, metadata=metadata)
    back, meta = read_exr(path)
    assert back.dtype == np.float32 and back.shape == image.shape
    np.testing.assert_array_equal(back, image)
    assert meta["channels"] == ["R", "G", "B"]
    assert meta["integrator"] == "segment_pt"
    assert meta["spp"] == 64 and meta["count"] == 3
    assert meta["render_time"] == pytest.approx(1.5)
    assert meta["interrupted"] == 1
    assert meta["big"] == str(2**40)
    assert json.loads(meta["params"]) == {"max_depth": 8, "rr": 0.5}
    assert json.loads(meta["seeds"]) == [0, 1]
    assert not [p for p in tmp_path.iterdir() if p.name != "a.exr"]  # no temporary file left


def test_channel_names_and_order_survive(tmp_path):
    names = ["R", "G", "B", "A", "albedo.R", "depth.T", "Z"]
    image = np.stack([np.full((3, 4), i, np.float32) for i in range(len(names))], axis=-1)
    write_exr(tmp_path / "aov.exr", image, names)
    back, meta = read_exr(tmp_path / "aov.exr")
    assert meta["channels"] == names  # EXR stores channels sorted; the order given is restored
    np.testing.assert_array_equal(back, image)


def test_single_channel_and_default_names(tmp_path):
    write_exr(tmp_path / "y.exr", np.ones((2, 3), np.float32))
    back, meta = read_exr(tmp_path / "y.exr")
    assert back.shape == (2, 3, 1) and meta["channels"] == ["Y"]
    write_exr(tmp_path / "rgba.exr", np.zeros((2, 3, 4)))
    assert read_exr(tmp_path / "rgba.exr")[1]["channels"] == ["R", "G", "B", "A"]


def test_reads_foreign_exr_rgba_first(tmp_path):
    """A file written by someone else (no channel order attribute): R, G, B, A first, then by name."""
    planes = {n: np.full((2, 2), i, np.float32) for i, n in enumerate(["A", "B", "G", "R", "N.x"])}
    OpenEXR.File({"owner": "me"}, planes).write(str(tmp_path / "f.exr"))
    back, meta = read_exr(tmp_path / "f.exr")
    assert meta["channels"] == ["R", "G", "B", "A", "N.x"]
    assert back[0, 0].tolist() == [3, 2, 1, 0, 4]
    assert meta["owner"] == "me"


@pytest.mark.parametrize(
    "image, channels, metadata, match",
    [
        (np.zeros((2, 2, 3)), ["R", "G"], None, "channel names"),
        (np.zeros((2, 2, 2)), ["R", "R"], None, "duplicate"),
        (np.zeros((2, 2, 3)), None, {"compression": "none"}, "reserved"),
        (np.zeros((2, 2, 3)), None, {"channels": "x"}, "reserved"),
        (np.zeros((0, 2, 3)), None, None, "H x W x C"),
        (np.zeros(5), None, None, "H x W x C"),
    ],
)
def test_write_exr_refuses_bad_input(tmp_path, image, channels, metadata, match):
    with pytest.raises(ValueError, match=match):
        write_exr(tmp_path / "bad.exr", image, channels, metadata)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("compression", ["zip", "piz"])
def test_half_float_round_trip(tmp_path, compression):
    """half=True stores HALF pixels (lossless compression): values come back rounded to 11 significant bits,
    as float32, and the file is smaller than the float32 one; values beyond the half range are refused."""
    rng = np.random.default_rng(2)
    image = (rng.random((16, 16, 3)) * 100).astype(np.float32)
    write_exr(tmp_path / "f.exr", image, compression=compression)
    write_exr(tmp_path / "h.exr", image, metadata={"spp": 4}, half=True, compression=compression)
    back, meta = read_exr(tmp_path / "h.exr")
    assert back.dtype == np.float32 and meta["spp"] == 4
    np.testing.assert_array_equal(back, image.astype(np.float16).astype(np.float32))
    assert np.max(np.abs(back / image - 1)) <= 2.0**-11
    f = OpenEXR.File(str(tmp_path / "h.exr"), separate_channels=True)
    assert {str(ch.type()) for ch in f.channels().values()} == {"PixelType.HALF"}
    assert compression.upper() in str(f.header()["compression"])
    assert (tmp_path / "h.exr").stat().st_size < (tmp_path / "f.exr").stat().st_size
    with pytest.raises(ValueError, match="half float"):
        write_exr(tmp_path / "big.exr", np.full((2, 2, 3), 7e4, np.float32), half=True)
    with pytest.raises(ValueError, match="compression"):
        write_exr(tmp_path / "c.exr", image, compression="dwaa")  # lossy: not offered


def test_srgb_tone_mapping():
    image = np.array([[[0.0, 0.5, 1.0], [2.0, -1.0, np.nan]]], np.float32)
    assert to_srgb8(image).tolist() == [[[0, 188, 255], [255, 0, 0]]]
    assert to_srgb8(image, exposure=-1.0)[0, 1, 0] == 255  # 2 * 2^-1 = 1
    assert to_srgb8(np.full((1, 1, 1), 1.0)).tolist() == [[[255, 255, 255]]]  # grey -> RGB


def test_png_preview(tmp_path):
    import mitsuba as mi

    image = np.zeros((6, 9, 4), np.float32)
    image[..., 0] = 1.0
    write_png(tmp_path / "p.png", image)
    data = (tmp_path / "p.png").read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    bitmap = mi.Bitmap(str(tmp_path / "p.png"))
    assert tuple(bitmap.size()) == (9, 6) and bitmap.channel_count() == 3
    assert np.array(bitmap)[0, 0].tolist() == [255, 0, 0]
