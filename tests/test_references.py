"""The stored references (tests/references, made by ``segmitsuba reference``): present for every scene,
well-formed, converged, current with their scene files, and in agreement with a fresh low-spp render."""

from __future__ import annotations

import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
import scipy.stats

from segmitsuba import cli
from segmitsuba import references as refs
from segmitsuba.references import (
    BENCHMARK_RES,
    BENCHMARK_SCENES,
    DEFAULT_MAX_DEPTH,
    DEFAULT_RES,
    EXCLUDED,
    REFERENCES_DIR,
    border_gain,
    default_spp,
    load_reference,
    method,
    reference_path,
    reference_scenes,
    reference_scenes_at,
    regenerate_command,
    relmse,
    scene_file,
    stale_reason,
)

SCENES = reference_scenes()
BENCH = reference_scenes_at(BENCHMARK_RES)
#: the benchmark references' own noise must stay well below the errors they judge (~1e-3 .. 1e-2 at 30 s)
BENCH_EXPECTED_RELMSE = 2e-4
REQUIRED = ("integrator", "method_reason", "spp", "half_spp", "seed", "pass_seeds", "time", "res", "max_depth",
            "scene", "scene_sha256", "half_relmse", "expected_relmse", "mitsuba_version", "drjit_version",
            "segmitsuba_version", "variant")


def test_every_scene_has_a_reference_and_no_other():
    stored = sorted(p.name for p in REFERENCES_DIR.glob(f"*_r{DEFAULT_RES}_d{DEFAULT_MAX_DEPTH}.exr"))
    expected = sorted(reference_path(s).name for s in SCENES)
    missing, extra = sorted(set(expected) - set(stored)), sorted(set(stored) - set(expected))
    assert not missing, f"no reference for {missing}; generate with: segmitsuba reference --all"
    assert not extra, f"references without a scene: {extra}"
    assert not set(EXCLUDED) & set(SCENES)


@pytest.mark.parametrize("scene", SCENES)
def test_reference_loads_with_metadata(scene: str):
    image, meta = load_reference(scene)
    assert image.shape == (DEFAULT_RES, DEFAULT_RES, 3) and image.dtype == np.float32
    assert meta["channels"] == ["R", "G", "B"]
    missing = [k for k in REQUIRED if k not in meta]
    assert not missing, f"metadata lacks {missing}"
    assert meta["integrator"] == method(scene).integrator
    assert (meta["res"], meta["max_depth"]) == (DEFAULT_RES, DEFAULT_MAX_DEPTH)
    assert meta["scene"] == f"scenes/{scene}.xml"
    assert sum(meta["half_spp"]) == meta["spp"] and len(meta["pass_seeds"]) == 2
    assert not set(meta["pass_seeds"][0]) & set(meta["pass_seeds"][1]), "the halves share seeds"
    assert meta["half_relmse"] < 1e-3, f"{scene}: reference not converged (half_relmse {meta['half_relmse']:.2e})"
    if meta["integrator"] == "ptracer":
        assert meta["method_check"]["agree"], meta["method_check"]


@pytest.mark.parametrize("scene", SCENES)
def test_reference_is_finite_and_not_black(scene: str):
    image, _ = load_reference(scene)
    assert np.all(np.isfinite(image)) and np.all(image >= 0)
    assert image.mean() > 0.02, f"{scene}: mean {image.mean():.4f}"
    assert np.mean(image.max(axis=2) > 1e-3) > 0.25, f"{scene}: mostly black"


@pytest.mark.parametrize("scene", SCENES)
def test_reference_is_current(scene: str):
    _, meta = load_reference(scene)
    reason = stale_reason(meta, scene)
    assert reason is None, f"stale reference for {scene}: {reason}; regenerate with: {regenerate_command(scene)}"


def test_benchmark_references_are_stored_and_no_other():
    assert BENCH == sorted(BENCHMARK_SCENES)
    stored = sorted(p.name for p in REFERENCES_DIR.glob(f"*_r{BENCHMARK_RES}_d{DEFAULT_MAX_DEPTH}.exr"))
    assert stored == sorted(reference_path(s, BENCHMARK_RES).name for s in BENCH), \
        f"regenerate with: segmitsuba reference --res {BENCHMARK_RES} {' '.join(BENCHMARK_SCENES)}"


@pytest.mark.parametrize("scene", BENCH)
def test_benchmark_reference_is_current_converged_and_half(scene: str):
    """The 256x256 references: current with their scene, made by the method and spp of the tables at this
    resolution, converged (expected relMSE well below the errors they judge), stored as half floats."""
    import OpenEXR

    image, meta = load_reference(scene, res=BENCHMARK_RES)
    reason = stale_reason(meta, scene)
    assert reason is None, f"stale: {reason}; regenerate with: {regenerate_command(scene, BENCHMARK_RES)}"
    assert image.shape == (BENCHMARK_RES, BENCHMARK_RES, 3) and image.dtype == np.float32
    assert np.all(np.isfinite(image)) and np.all(image >= 0) and image.mean() > 0.02
    missing = [k for k in REQUIRED if k not in meta]
    assert not missing, f"metadata lacks {missing}"
    assert (meta["res"], meta["max_depth"]) == (BENCHMARK_RES, DEFAULT_MAX_DEPTH)
    assert meta["integrator"] == method(scene, BENCHMARK_RES).integrator
    assert meta["spp"] == default_spp(scene, BENCHMARK_RES) == sum(meta["half_spp"])
    assert not set(meta["pass_seeds"][0]) & set(meta["pass_seeds"][1]), "the halves share seeds"
    assert meta["expected_relmse"] == pytest.approx(meta["half_relmse"] / 4)
    assert meta["expected_relmse"] < BENCH_EXPECTED_RELMSE, f"{scene}: expected relMSE {meta['expected_relmse']:.2e}"
    assert meta["command"] == regenerate_command(scene, BENCHMARK_RES)
    assert meta["pixel_type"] == "half" and meta["half_rounding_relmse"] < 1e-6
    f = OpenEXR.File(str(reference_path(scene, BENCHMARK_RES)), separate_channels=True)
    assert {str(ch.type()) for ch in f.channels().values()} == {"PixelType.HALF"}
    if meta["integrator"] != "path":
        # segment_bdpt renders 0.2-0.3% brighter than path next to a small sphere light (see the method's reason):
        # the check against path must stay within that (t-values say "disagree" at 8 x 16 spp per method)
        check = meta["method_check"]
        assert "full scene" in check["compared"], check
        assert abs(check["ratio_image"] - 1) < 0.005 and abs(check["ratio_border"] - 1) < 0.01, check


def test_reference_method_and_spp_depend_on_the_resolution():
    assert method("caustic").integrator == "path" and method("caustic", BENCHMARK_RES).integrator == "segment_bdpt"
    assert method("delta_caustic_point", BENCHMARK_RES).integrator == "ptracer"  # no entry: the test table's
    assert method("cornell", BENCHMARK_RES).integrator == "path"
    assert default_spp("caustic") == 65536 and default_spp("caustic", BENCHMARK_RES) == 1024
    assert default_spp("emitter_area", 64) == refs.DEFAULT_SPP
    assert regenerate_command("sds", BENCHMARK_RES) == "segmitsuba reference sds --res 256"


def test_make_reference_with_segment_bdpt_in_half_floats(tmp_path: Path, monkeypatch: pytest.MonkeyPatch):
    """make_reference with a per-resolution method (segment_bdpt) and spp, half-float storage and the method
    check against path on the full scene (at 16x16, with the tables patched to say so)."""
    import OpenEXR

    monkeypatch.setitem(refs.METHODS_BY_RES, 16, {"caustic": refs.METHODS_BY_RES[BENCHMARK_RES]["caustic"]})
    monkeypatch.setitem(refs.SPP_BY_RES, 16, {"caustic": 8})
    monkeypatch.setitem(refs.CHECK_SPP, "segment_bdpt", 4)
    monkeypatch.setattr(refs, "HALF_MIN_RES", 16)
    said: list[str] = []
    out = refs.make_reference("caustic", res=16, directory=tmp_path, say=said.append)
    assert out == reference_path("caustic", 16, directory=tmp_path)
    image, meta = load_reference("caustic", res=16, directory=tmp_path)
    assert image.shape == (16, 16, 3) and np.isfinite(image).all() and image.mean() > 0.02
    assert (meta["integrator"], meta["spp"], meta["res"]) == ("segment_bdpt", 8, 16)
    assert meta["command"] == "segmitsuba reference caustic --res 16"
    assert meta["pixel_type"] == "half" and 0 < meta["half_rounding_relmse"] < 1e-6
    assert {str(c.type()) for c in OpenEXR.File(str(out), separate_channels=True).channels().values()} == \
        {"PixelType.HALF"}
    check = meta["method_check"]
    assert check["removed"] == [] and "full scene" in check["compared"] and "4 spp" in check["compared"]
    assert isinstance(check["agree"], bool) and math.isfinite(check["t_image"])
    assert stale_reason(meta, "caustic") is None
    assert said and said[0].startswith("caustic: segment_bdpt, 8 spp") and "on the full scene" in said[0]


def test_missing_reference_names_the_command(tmp_path: Path):
    with pytest.raises(FileNotFoundError, match="segmitsuba reference cornell --res 16 --max-depth 3"):
        load_reference("cornell.xml", res=16, max_depth=3, directory=tmp_path)
    with pytest.raises(FileNotFoundError, match="excluded"):
        load_reference("medium")


def test_relmse_definition():
    a, b = np.full((2, 2, 3), 1.0), np.full((2, 2, 3), 3.0)
    assert relmse(a, b) == pytest.approx(4.0 / (4.0 + 1e-2))
    assert relmse(a, a) == 0.0


def test_border_gain():
    """Light tracers lose the splat weight outside the image: the Gaussian (stddev 0.5) keeps Phi(1) of it in
    the edge pixels, ~Phi(3) one pixel in, all of it inside; a box filter loses nothing."""
    gauss = mi.load_dict({"type": "gaussian"})
    g = border_gain(gauss, 16, 8)
    assert g.shape == (8, 16)
    edge = scipy.stats.norm.cdf(1.0)
    assert g[4, 0] == pytest.approx(edge, abs=3e-3) and g[0, 8] == pytest.approx(edge, abs=3e-3)
    assert g[0, 0] == pytest.approx(edge**2, abs=5e-3)
    assert g[4, 1] == pytest.approx(scipy.stats.norm.cdf(3.0), abs=3e-3)
    assert np.allclose(g[2:-2, 2:-2], 1.0, atol=1e-6)
    assert np.allclose(border_gain(mi.load_dict({"type": "box"}), 8, 8), 1.0, atol=1e-6)


def _tile_means(images: np.ndarray, tiles: int = 4) -> np.ndarray:
    """(K, 1 + tiles^2): image mean, then tile means (over the colour channels)."""
    k, h, w, _ = images.shape
    ys = np.array_split(np.arange(h), tiles)
    xs = np.array_split(np.arange(w), tiles)
    out = [images.mean(axis=(1, 2, 3))] + [images[:, y][:, :, x].mean(axis=(1, 2, 3)) for y in ys for x in xs]
    return np.stack(out, axis=1)


def test_fresh_render_agrees_with_reference():
    """A stale reference (scene edited, reference not regenerated) or a broken one is caught: K independent
    low-spp path renders of emitter_area agree with the stored image on the whole image and 4x4 tiles (t-test
    reported as a normal z, the reference's own noise included), and their relMSE is what their noise explains."""
    scene_name, k, spp = "emitter_area", 16, 32
    reference, meta = load_reference(scene_name)
    reason = stale_reason(meta, scene_name)
    if reason is not None:
        pytest.fail(f"{reason}; regenerate with: segmitsuba reference {scene_name}")

    scene = mi.load_file(str(scene_file(scene_name)), res=DEFAULT_RES, max_depth=DEFAULT_MAX_DEPTH)
    integrator = mi.load_dict({"type": "path", "max_depth": DEFAULT_MAX_DEPTH})
    images = np.stack([np.array(mi.render(scene, integrator=integrator, spp=spp, seed=1000 + i),
                                dtype=np.float64)[..., :3] for i in range(k)])
    ref = reference.astype(np.float64)

    # reference noise per pixel and channel, from its measured relMSE: var ~ expected_relmse * (ref^2 + eps)
    ref_var = meta["expected_relmse"] * (ref**2 + 1e-2)
    tiles = _tile_means(images)
    ref_tiles = _tile_means(ref[None])[0]
    sizes = np.array([ref.size] + [len(y) * len(x) * ref.shape[2] for y in np.array_split(np.arange(ref.shape[0]), 4)
                                   for x in np.array_split(np.arange(ref.shape[1]), 4)])
    ref_tile_var = _tile_means(ref_var[None])[0] / sizes  # variance of a mean of `sizes` values (independent)
    se = np.sqrt(tiles.var(axis=0, ddof=1) / k + ref_tile_var)
    t = (tiles.mean(axis=0) - ref_tiles) / se
    z = scipy.stats.norm.isf(scipy.stats.t.sf(np.abs(t), k - 1))
    assert np.max(z) < 4.5, f"fresh render vs reference: max z {np.max(z):.2f} (means {tiles.mean(0)[0]:.5f} vs " \
        f"{ref_tiles[0]:.5f}); regenerate with: segmitsuba reference {scene_name}"

    mean = images.mean(axis=0)
    observed = relmse(mean, ref, ref)
    expected = float(np.mean(images.var(axis=0, ddof=1) / k / (ref**2 + 1e-2))) + meta["expected_relmse"]
    assert observed < 1.5 * expected, f"relMSE {observed:.2e} vs {expected:.2e} expected from noise alone"
    assert observed > expected / 1.5, f"relMSE {observed:.2e} suspiciously below the {expected:.2e} expected"


def test_delta_caustic_reference_has_the_caustics_path_misses():
    """The ptracer reference of delta_caustic_point holds the point-light caustics that path cannot sample, and
    agrees with path where there are none (path's pixel convention, also at the image border)."""
    reference, meta = load_reference("delta_caustic_point")
    assert meta["integrator"] == "ptracer"
    scene = mi.load_file(str(scene_file("delta_caustic_point")), res=DEFAULT_RES, max_depth=DEFAULT_MAX_DEPTH)
    path = np.array(mi.render(scene, integrator=mi.load_dict({"type": "path", "max_depth": DEFAULT_MAX_DEPTH}),
                              spp=256, seed=3), dtype=np.float64)[..., :3]
    ratio = path.mean() / reference.mean()
    assert 0.6 < ratio < 0.92, f"path / reference = {ratio:.3f}: the reference should hold the caustics"
    # the missing light is concentrated in the caustics: most pixels agree (relative difference < 10%)
    close = np.abs(path.mean(-1) - reference.mean(-1)) < 0.1 * reference.mean(-1) + 0.01
    assert close.mean() > 0.5, f"only {close.mean():.0%} of pixels agree with path"
    ring = np.ones(reference.shape[:2], dtype=bool)
    ring[1:-1, 1:-1] = False
    assert math.isclose(float(path[ring].mean() / reference[ring].mean()), ratio, abs_tol=0.1)


def test_cli_reference(tmp_path: Path, capsys: pytest.CaptureFixture[str]):
    assert cli.main(["reference", "emitter_point.xml", "--spp", "8", "--res", "8", "--dir", str(tmp_path)]) == 0
    image, meta = load_reference("emitter_point", res=8, directory=tmp_path)
    assert image.shape == (8, 8, 3) and meta["spp"] == 8 and meta["command"].startswith("segmitsuba reference")
    assert "emitter_point: path, 8 spp" in capsys.readouterr().out
    assert cli.main(["reference", "medium"]) == cli.EXIT_USAGE
    assert cli.main(["reference"]) == cli.EXIT_USAGE
    assert cli.main(["reference", "cornell", "--all"]) == cli.EXIT_USAGE
    assert "no reference" in capsys.readouterr().err


def test_stale_reference_is_detected(tmp_path: Path):
    _, meta = load_reference("emitter_envmap")
    scenes = tmp_path / "scenes"
    (scenes / "textures").mkdir(parents=True)
    xml = scene_file("emitter_envmap").read_text()
    (scenes / "emitter_envmap.xml").write_text(xml)
    sky = scene_file("emitter_envmap").parent / "textures" / "sky.exr"
    (scenes / "textures" / "sky.exr").write_bytes(sky.read_bytes())
    assert stale_reason(meta, "emitter_envmap", scenes) is None
    (scenes / "textures" / "sky.exr").write_bytes(sky.read_bytes() + b"\0")
    assert "textures/sky.exr" in (stale_reason(meta, "emitter_envmap", scenes) or "")
    (scenes / "emitter_envmap.xml").write_text(xml.replace('value="0.6"', 'value="0.7"'))
    assert "emitter_envmap.xml changed" in (stale_reason(meta, "emitter_envmap", scenes) or "")
