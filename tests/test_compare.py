"""``segmitsuba compare``: equal-time runs, checkpoints, outputs (PNG plots, JSON, CSV) and one-line errors."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from segmitsuba import cli
from segmitsuba.compare import crop_regions, run_method

ROOT = Path(__file__).resolve().parent.parent
CORNELL = ROOT / "scenes" / "cornell.xml"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def test_compare_writes_results(tmp_path, capsys):
    out = tmp_path / "cmp"
    code = cli.main(["compare", str(CORNELL), "--methods", "path,segment_pt", "--time", "1", "--res", "32",
                     "--out", str(out), "--param", "segment_pt.rr_depth=6", "-q"])
    stdout = capsys.readouterr().out
    assert code == 0
    for name in ("error_vs_time.png", "grid.png"):
        data = (out / name).read_bytes()
        assert data.startswith(PNG_MAGIC) and len(data) > 5000
    for name in ("path.exr", "segment_pt.exr", "reference.exr"):
        assert (out / name).is_file()
    results = json.loads((out / "results.json").read_text())
    assert results["reference"]["source"] == "stored"  # cornell at 32 / depth 8 has a stored reference
    assert results["settings"]["time_budget"] == 1
    assert results["machine"]["variant"] == "llvm_ad_rgb"
    assert results["methods"]["segment_pt"]["params"] == {"max_depth": 8, "rr_depth": 6}
    for method in ("path", "segment_pt"):
        run = results["methods"][method]
        cps = run["checkpoints"]
        times = [c["time"] for c in cps]
        spps = [c["spp"] for c in cps]
        assert len(cps) >= 3
        assert all(b > a for a, b in zip(times, times[1:], strict=False))
        assert all(b > a for a, b in zip(spps, spps[1:], strict=False))
        assert times[-1] < 2.5  # the 1 s budget, plus at most about one pass of noise
        for c in cps:
            assert 0 < c["relmse_trimmed"] <= c["relmse"]
            assert c["mse"] > 0 and 0 < c["flip"] <= 1
        assert cps[0]["relmse"] > cps[-1]["relmse"]  # error falls as samples accumulate
        final = run["final"]
        assert final["spp"] == spps[-1] and final["relmse"] == pytest.approx(cps[-1]["relmse"])
        assert 0 < final["flip"] < 1
    rows = list(csv.DictReader(open(out / "results.csv")))
    assert {r["method"] for r in rows} == {"path", "segment_pt"}
    assert len(rows) == sum(len(m["checkpoints"]) for m in results["methods"].values())
    assert sum(int(r["final"]) for r in rows) == 2
    # summary table on stdout
    assert "relMSE" in stdout and "segment_pt" in stdout and "wrote" in stdout


def test_rendered_reference_when_none_is_stored(tmp_path, capsys):
    out = tmp_path / "r16"
    assert cli.main(["compare", str(CORNELL), "--methods", "path,segment_bdf", "--time", "0.3", "--res", "16",
                     "--out", str(out), "-q"]) == 0
    results = json.loads((out / "results.json").read_text())
    assert results["reference"]["source"] == "rendered" and results["reference"]["integrator"] == "path"
    assert results["settings"]["width"] == 16
    assert set(results["methods"]) == {"path", "segment_bdf"}


def test_run_method_running_average_is_exact():
    """With warm-up off and a budget that stops after a few passes, the final image is the spp-weighted
    average of mi.render passes with rendering.pass_seed seeds."""
    from segmitsuba.rendering import pass_seed

    scene = mi.load_file(str(CORNELL), res=8)
    integrator = mi.load_dict({"type": "path", "max_depth": 8})
    ref = np.full((8, 8, 3), 0.5)
    run = run_method(scene, "path", ref, time_budget=0.05, params={"max_depth": 8}, warmup=False)
    acc = sum(np.array(mi.render(scene, integrator=integrator, spp=c.pass_spp, seed=pass_seed(0, c.index)))
              [..., :3] * c.pass_spp for c in run.checkpoints)
    assert np.allclose(run.image, acc / run.final["spp"], rtol=1e-5, atol=1e-6)


def test_crop_regions_find_the_disagreement():
    ref = np.ones((20, 20, 3))
    a = ref.copy()
    b = ref.copy()
    b[12:15, 3:6] = 5.0  # only method b is wrong here
    regions = crop_regions([a, b], ref)
    assert len(regions) == 2
    y, x, c = regions[0]
    assert y <= 12 and y + c >= 15 and x <= 3 and x + c >= 6
    (y2, x2, _) = regions[1]
    assert abs(y2 - y) >= c or abs(x2 - x) >= c  # no overlap


@pytest.mark.parametrize(
    "args, message",
    [
        (["--methods", "path,nosuch"], "unknown method 'nosuch'"),
        (["--methods", "path,path"], "twice"),
        (["--param", "segment_bdf.alpha=0.5"], "not one of the methods"),
        (["--param", "alpha=0.5"], "METHOD.KEY=VALUE"),
        (["--param", "path.no_such_property=1"], "cannot create method 'path'"),
        (["--reference", "/nonexistent/ref.exr"], "does not exist"),
        (["-D", "res=8"], "--res"),
    ],
)
def test_bad_input_one_line_error(tmp_path, capsys, args, message):
    code = cli.main(["compare", str(CORNELL), "--methods", "path", "--time", "0.1", "--res", "8",
                     "--out", str(tmp_path / "o"), *args])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert message in err and len(err.splitlines()) == 1, err


def test_missing_scene_and_bad_reference_size(tmp_path, capsys):
    assert cli.main(["compare", str(tmp_path / "nope.xml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "does not exist" in err and len(err.splitlines()) == 1
    from segmitsuba.imageio import write_exr

    ref = tmp_path / "ref.exr"
    write_exr(ref, np.ones((4, 4, 3), np.float32), ["R", "G", "B"], {})
    assert cli.main(["compare", str(CORNELL), "--methods", "path", "--time", "0.1", "--res", "8",
                     "--reference", str(ref), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert "4x4" in err and "8x8" in err and len(err.splitlines()) == 1
