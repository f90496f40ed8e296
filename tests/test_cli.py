"""The ``segmitsuba`` command line, driven as a user would (``python -m segmitsuba`` in a subprocess), and the
pass loop behind it (segmitsuba.rendering). Renders are tiny: the machine is small and shared."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from conftest import default_sigint, small_cornell

from segmitsuba import cli
from segmitsuba.imageio import read_exr
from segmitsuba.rendering import pass_seed, plan_passes, render_passes

SCENE = """<scene version="3.0.0">
  <default name="res" value="16"/>
  <default name="format" value="rgb"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm">
      <integer name="width" value="$res"/><integer name="height" value="$res"/>
      <string name="pixel_format" value="$format"/>
    </film>
  </sensor>
  <shape type="sphere"><bsdf type="diffuse"/></shape>
  <emitter type="constant"/>
</scene>
"""


def segmitsuba(*args: str, cwd: Path | None = None, timeout: float = 120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "segmitsuba", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=timeout)


@pytest.fixture
def scene_file(tmp_path: Path) -> Path:
    path = tmp_path / "sphere.xml"
    path.write_text(SCENE)
    return path


# --- render ---------------------------------------------------------------------------------------------


def test_default_render_writes_exr_and_png_with_metadata(tmp_path):
    r = segmitsuba("render", "--res", "24x16", "--spp", "4", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    exr = tmp_path / "out" / f"cornell_box_{cli.DEFAULT_INTEGRATOR}.exr"
    png = exr.with_suffix(".png")
    assert exr.is_file() and png.is_file()
    assert str(exr.relative_to(tmp_path)) in r.stdout and str(png.relative_to(tmp_path)) in r.stdout

    image, meta = read_exr(exr)
    assert image.shape == (16, 24, 3) and meta["channels"] == ["R", "G", "B"]
    assert np.isfinite(image).all() and image.mean() > 0
    assert meta["integrator"] == cli.DEFAULT_INTEGRATOR == "segment_bdf"
    assert meta["spp"] == 4 and meta["passes"] == 1 and meta["seed"] == 0
    assert meta["stop_reason"] == "spp" and meta["interrupted"] == 0
    assert meta["scene"] == cli.BUILTIN_SCENE and meta["variant"] == "llvm_ad_rgb"
    assert meta["mitsuba_version"] == mi.__version__ and meta["segmitsuba_version"]
    assert meta["llvm_version"].split(".")[0].isdigit() and meta["render_time"] > 0
    assert json.loads(meta["integrator_params"]) == {}
    assert tuple(mi.Bitmap(str(png)).size()) == (24, 16)


def test_scene_file_defines_params_and_passes(tmp_path, scene_file):
    out = tmp_path / "nested" / "dir" / "img.exr"
    r = segmitsuba("render", str(scene_file), "-D", "res=12", "-D", "format=rgba", "-i", "path",
                   "-p", "max_depth=2", "-p", "hide_emitters=true", "--spp", "6", "--passes", "3",
                   "--seed", "7", "-o", str(out))
    assert r.returncode == 0, r.stderr
    image, meta = read_exr(out)
    assert image.shape == (12, 12, 4) and meta["channels"] == ["R", "G", "B", "A"]
    assert meta["integrator"] == "path"
    assert json.loads(meta["integrator_params"]) == {"max_depth": 2, "hide_emitters": True}
    assert "max_depth = 2" in meta["integrator_description"]
    assert meta["spp"] == 6 and meta["passes"] == 3 and json.loads(meta["pass_spp"]) == [2, 2, 2]
    assert json.loads(meta["pass_seeds"])[0] == 7 and meta["seed"] == 7
    assert meta["scene"] == str(scene_file.resolve())
    assert json.loads(meta["defines"]) == {"res": "12", "format": "rgba"}
    assert np.all(image[..., 3] <= 1.0001)


def test_scene_integrator_and_reproducible_seed(tmp_path, scene_file):
    outs = []
    for name in ("a", "b"):
        out = tmp_path / f"{name}.exr"
        r = segmitsuba("render", str(scene_file), "-i", "scene", "--spp", "4", "--passes", "2", "-o", str(out),
                       "-q")
        assert r.returncode == 0, r.stderr
        assert r.stderr == ""  # --quiet
        outs.append(read_exr(out))
    assert outs[0][1]["integrator"] == "scene:PathIntegrator"
    np.testing.assert_allclose(outs[0][0], outs[1][0], rtol=1e-5, atol=1e-6)  # threads reorder float sums


def test_time_budget_is_honoured(tmp_path, scene_file):
    budget = 3.0
    out = tmp_path / "t.exr"
    start = time.perf_counter()
    r = segmitsuba("render", str(scene_file), "-i", "path", "--time", str(budget), "-o", str(out))
    wall = time.perf_counter() - start
    assert r.returncode == 0, r.stderr
    assert "time budget reached" in r.stderr
    _, meta = read_exr(out)
    longest = max(json.loads(meta["pass_seconds"]))
    assert meta["stop_reason"] == "time" and meta["passes"] >= 2
    assert abs(meta["render_time"] - budget) <= 0.1 * budget + longest
    assert meta["time_budget"] == pytest.approx(budget)
    assert meta["spp"] == sum(json.loads(meta["pass_spp"]))
    assert wall < budget + 30  # start-up and writing come on top; nothing runs away


def test_sigint_writes_the_finished_passes(tmp_path, scene_file):
    out = tmp_path / "int.exr"
    proc = subprocess.Popen(
        [sys.executable, "-m", "segmitsuba", "render", str(scene_file), "-i", "path", "-D", "res=32",
         "--spp", "1000000", "--pass-spp", "16", "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=default_sigint,
    )
    try:
        lines = []
        for line in proc.stderr:  # progress is one line per pass when stderr is not a terminal
            lines.append(line)
            if line.startswith("pass 1/"):
                proc.send_signal(signal.SIGINT)
                break
        else:
            pytest.fail("no pass was reported: " + "".join(lines))
        stdout, stderr = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == cli.EXIT_INTERRUPTED, stderr
    assert "interrupted: writing the average" in stderr and "Traceback" not in stderr
    assert str(out) in stdout
    image, meta = read_exr(out)
    assert image.shape == (32, 32, 3) and np.isfinite(image).all()
    assert meta["interrupted"] == 1 and meta["stop_reason"] == "interrupt"
    assert meta["passes"] >= 1 and meta["spp"] == 16 * meta["passes"] < 1000000


def test_interrupt_before_any_pass_writes_nothing(tmp_path, monkeypatch, capsys):
    import segmitsuba.rendering

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(segmitsuba.rendering, "render_passes", interrupted)
    out = tmp_path / "x.exr"
    assert cli.main(["render", "--res", "8", "--spp", "1", "-i", "path", "-o", str(out), "-q"]) == 130
    assert "nothing written" in capsys.readouterr().err
    assert not out.exists() and not out.with_suffix(".png").exists()


@pytest.mark.parametrize(
    "args, code, message",
    [
        (["missing.xml"], 2, "does not exist"),
        (["{dir}"], 2, "is not a file"),
        (["{broken}"], 2, "Error parsing"),
        (["{scene}", "-D", "nope=1"], 2, "unused parameters"),
        (["{scene}", "-D", "res=abc"], 2, 'could not parse integer value "abc"'),
        (["{scene}", "-i", "no_such_integrator"], 2, "unknown integrator 'no_such_integrator'"),
        (["{scene}", "-i", "sphere"], 2, "not an integrator"),
        (["{scene}", "-i", "path", "-p", "bogus=1"], 2, "unreferenced property"),
        (["{scene}", "-i", "path", "-p", "max_depth=abc"], 2, 'property "max_depth" has the wrong type'),
        (["{scene}", "-i", "segment_pt", "-p", "bogus=1"], 2, "unreferenced property"),
        (["{scene}", "-i", "scene", "-p", "max_depth=1"], 2, "--param needs an explicit --integrator"),
        (["--spp", "0"], 2, "argument --spp: expected a positive integer, got '0'"),
        (["--spp", "abc"], 2, "argument --spp: expected a positive integer, got 'abc'"),
        (["--time", "-1"], 2, "argument --time: expected a positive number, got '-1'"),
        (["--time", "0"], 2, "argument --time: expected a positive number"),
        (["--time", "1", "--spp", "2"], 2, "not allowed with argument"),
        (["--time", "1", "--passes", "2"], 2, "--passes needs --spp"),
        (["--seed", "-3"], 2, "argument --seed"),
        (["--res", "0"], 2, "argument --res"),
        (["-D", "novalue"], 2, "expected NAME=VALUE"),
        (["{scene}", "--res", "8"], 2, "--res only applies to the built-in scene"),
        (["--variant", "nope_rgb"], 2, "unknown Mitsuba variant 'nope_rgb'"),
        (["--variant", "scalar_rgb", "-i", "segment_pt"], 2, "cannot run in a scalar variant"),
        (["-o", "{tmp}/image.png"], 2, "--out must name an .exr file"),
        (["-o", "{file}/sub/x.exr"], 2, "cannot create output directory"),
        (["-o", "/proc/segmitsuba/x.exr"], 2, "cannot create output directory"),
        (["-o", "{tmp}/d.exr"], 2, "is a directory"),
    ],
)
def test_bad_input_gives_one_line_error(tmp_path, scene_file, args, code, message):
    broken = tmp_path / "broken.xml"
    broken.write_text(SCENE.replace("</scene>", "<shape type=\n</scene>"))
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    (tmp_path / "d.exr").mkdir()
    subs = {"{scene}": str(scene_file), "{broken}": str(broken), "{dir}": str(tmp_path), "{tmp}": str(tmp_path),
            "{file}": str(a_file)}
    args = [next((a.replace(k, v) for k, v in subs.items() if k in a), a) for a in args]
    r = segmitsuba("render", *args, "--spp" if "--spp" not in args and "--time" not in args else "--seed",
                   "1", cwd=tmp_path)
    assert r.returncode == code, r.stderr
    assert message in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not [p for p in tmp_path.rglob("*.exr") if p.is_file()]


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only directories")
def test_read_only_output_directory(tmp_path, scene_file):
    ro = tmp_path / "ro"
    ro.mkdir(mode=0o500)
    r = segmitsuba("render", str(scene_file), "-o", str(ro / "x.exr"))
    assert r.returncode == 2 and "not writable" in r.stderr


def test_render_failure_exit_code(tmp_path, monkeypatch, capsys):
    import segmitsuba.rendering

    def fails(*args, **kwargs):
        raise RuntimeError("[foo.cpp:12] kernel exploded\nsecond line")

    monkeypatch.setattr(segmitsuba.rendering, "render_passes", fails)
    assert cli.main(["render", "--res", "8", "--spp", "1", "-i", "path", "-o", str(tmp_path / "x.exr")]) == 1
    assert "render failed: kernel exploded second line" in capsys.readouterr().err


def test_an_error_inside_mi_render_is_reported_by_its_own_message():
    """Dr.Jit wraps what a plugin raises inside ``mi.render`` in "... custom differentiable operation. (see
    above)": the one-line message must be the plugin's."""
    from segmitsuba.cli.common import mitsuba_message

    scene = mi.load_string(SCENE)
    integrator = mi.load_dict({"type": "segment_bdf", "spp_per_pass": 64, "memory_budget": 16.0})
    with pytest.raises(Exception) as info:
        mi.render(scene, integrator=integrator, spp=64)
    message = mitsuba_message(info.value)
    assert "spp_per_pass=64 needs about" in message and "see above" not in message, message


# --- info, bench, entry points --------------------------------------------------------------------------


def test_info():
    r = segmitsuba("info")
    assert r.returncode == 0, r.stderr
    for word in ("llvm_ad_rgb", "libLLVM", "threads", "mitsuba", "drjit", "segment_pt", "segment_lt"):
        assert word in r.stdout
    r = segmitsuba("info", "--json")
    info = json.loads(r.stdout)
    assert int(info["llvm_version"].split(".")[0]) >= 16
    assert info["threads"] >= 1 and "segment_pt" in info["integrators"]
    assert info["default_integrator"] == cli.DEFAULT_INTEGRATOR


def test_bench_discovery_and_unknown_name():
    from segmitsuba import benchmarks

    r = segmitsuba("bench", "--list")
    assert r.returncode == 0 and r.stdout.split() == benchmarks.available()
    r = segmitsuba("bench", "no_such_benchmark")
    assert r.returncode == 2 and "unknown benchmark 'no_such_benchmark'" in r.stderr


def test_bench_prints_its_table_once(capsys):
    assert cli.main(["bench", "grid", "--n", "2000"]) == 0
    assert capsys.readouterr().out.count("hash grid benchmark") == 1


def test_help_and_version():
    r = segmitsuba("--help")
    assert r.returncode == 0 and all(c in r.stdout for c in ("render", "info", "bench"))
    r = segmitsuba("--version")
    assert r.returncode == 0 and r.stdout.startswith("segmitsuba ")
    r = segmitsuba()
    assert r.returncode == 2 and "required" in r.stderr


# --- the pass loop (Python API) -------------------------------------------------------------------------


def test_one_pass_equals_mi_render_and_passes_average():
    scene = mi.load_dict(small_cornell())
    integrator = mi.load_dict({"type": "path", "max_depth": 4})
    one = render_passes(scene, integrator, spp=8, passes=1, seed=5, progress=False)
    reference = np.array(mi.render(scene, integrator=integrator, spp=8, seed=5))
    np.testing.assert_allclose(one.image, reference, rtol=1e-5, atol=1e-6)
    many = render_passes(scene, integrator, spp=7, passes=3, seed=5, progress=False)
    assert many.pass_spp == [3, 2, 2] and many.seeds == [pass_seed(5, i) for i in range(3)]
    expected = sum(np.array(mi.render(scene, integrator=integrator, spp=n, seed=s), np.float64) * n
                   for n, s in zip(many.pass_spp, many.seeds, strict=True)) / 7
    np.testing.assert_allclose(many.image, expected, rtol=1e-5, atol=1e-6)
    assert many.spp == 7 and many.passes == 3 and not many.interrupted


def test_plan_and_seeds():
    assert plan_passes(10, 100, passes=4) == [3, 3, 2, 2]
    assert plan_passes(10, 100, pass_spp=4) == [4, 3, 3]
    assert plan_passes(3, 100, passes=10) == [1, 1, 1]
    assert sum(plan_passes(1000, 1024 * 1024)) == 1000
    seeds = {pass_seed(s, i) for s in range(20) for i in range(20)}
    assert len(seeds) == 400 and all(0 <= s < 2**32 for s in seeds)


@pytest.mark.parametrize("ignored", [False, True])
def test_ctrl_c_in_process_stops_after_the_running_pass(ignored):
    """Ctrl-C stops a render after its running pass, and the handler is restored; a process that ignores
    SIGINT (nohup, a background job) renders on."""
    reports = []

    def on_pass(report):
        reports.append(report)
        if report.index == 1:
            os.kill(os.getpid(), signal.SIGINT)  # as if the user pressed Ctrl-C during pass 2

    outer = signal.signal(signal.SIGINT, signal.SIG_IGN if ignored else signal.default_int_handler)
    try:
        result = render_passes(mi.load_dict(small_cornell(8)), mi.load_dict({"type": "path"}), spp=40, passes=10,
                               progress=False, callback=on_pass)
        restored = signal.getsignal(signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, outer)
    if ignored:
        assert not result.interrupted and result.passes == 10 and result.spp == 40
        assert restored is signal.SIG_IGN
    else:
        assert result.interrupted and result.stop_reason == "interrupt"
        assert result.passes == 2 and result.spp == 8 and len(reports) == 2
        assert restored is signal.default_int_handler


def test_aov_channels_are_named():
    integrator = mi.load_dict({"type": "aov", "aovs": "dd:depth,nn:sh_normal", "img": {"type": "path"}})
    result = render_passes(mi.load_dict(small_cornell(8)), integrator, spp=2, progress=False)
    assert result.image.shape[2] == len(result.channels)
    assert result.channels[:3] == ["R", "G", "B"] and "dd.T" in result.channels and "nn.X" in result.channels


def test_rounding_sampler_counts_real_samples():
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 8
    d["sensor"]["sampler"] = {"type": "stratified", "sample_count": 4}
    result = render_passes(mi.load_dict(d), mi.load_dict({"type": "path"}), spp=6, passes=2, progress=False)
    assert result.pass_spp == [4, 4] and result.spp == 8  # 3 -> next square
