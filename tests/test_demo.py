"""``make demo`` (segmitsuba.demo): the labelled side-by-side picture and the EXRs, at a tiny scale."""

from __future__ import annotations

from pathlib import Path

import matplotlib.image
import numpy as np
import pytest

from segmitsuba.demo import demo, labelled_images
from segmitsuba.imageio import read_exr


def test_labelled_images_keep_the_pixel_size(tmp_path: Path):
    panels = [(np.full((40, 30, 3), v, np.float32), f"panel {v}") for v in (0.0, 0.5, 1.0)]
    labelled_images(panels, tmp_path / "p.png")
    png = matplotlib.image.imread(tmp_path / "p.png")
    assert png.shape[:2] == (40, 3 * 30 + 2 * 4)  # three panels, 4-pixel gaps
    assert png[3, 15, :3].max() < 0.05 and png[3, 34 + 15, :3].min() > 0.5  # black panel, grey panel


def test_demo_writes_the_picture_and_exrs(tmp_path: Path):
    finals = demo(tmp_path, time_budget=0.3, res=32, methods=("path",))
    assert set(finals) == {"path"} and finals["path"]["spp"] >= 1 and finals["path"]["relmse"] > 0
    assert matplotlib.image.imread(tmp_path / "demo.png").shape[:2] == (32, 2 * 32 + 4)  # path + reference
    image, meta = read_exr(tmp_path / "demo_path.exr")
    assert image.shape == (32, 32, 3) and np.isfinite(image).all()
    assert meta["integrator"] == "path" and meta["relmse"] == pytest.approx(finals["path"]["relmse"], rel=1e-6)
