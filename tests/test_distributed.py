"""Passes on a Dask cluster (segmitsuba.distributed, ``segmitsuba render --workers/--scheduler``).

One local cluster of 2 worker processes (1 Dr.Jit thread each) serves the module. A distributed render with
the same pass plan and seed as a local one draws the same samples, so besides the z-test over seeds (the
statistical acceptance test) the images are compared exactly (up to float summation order): a pass lost or
counted twice would show.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest
from conftest import ROOT, SCENES, default_sigint
from stats import compare

distributed = pytest.importorskip("distributed")

from segmitsuba import cli  # noqa: E402
from segmitsuba.distributed import (  # noqa: E402
    DistributedError,
    package_scene,
    render_distributed,
)
from segmitsuba.imageio import read_exr  # noqa: E402
from segmitsuba.rendering import pass_seed, render_passes  # noqa: E402

RES = 24


@pytest.fixture(scope="module")
def client():
    import logging

    cluster = distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None,
                                       silence_logs=logging.ERROR)
    c = distributed.Client(cluster, set_as_default=False)
    yield c
    c.close()
    cluster.close()


def cornell(res: int = RES) -> mi.Scene:
    return mi.load_file(str(SCENES / "cornell.xml"), res=str(res))


def local(scene: mi.Scene, integrator: dict, **kwargs) -> np.ndarray:
    return render_passes(scene, mi.load_dict(integrator), progress=False, **kwargs).image


def check_passes(result, spp: int, passes: int, seed: int) -> None:
    """Every pass exactly once, with its own seed, and the samples add up."""
    assert result.spp == spp == sum(result.pass_spp)
    assert result.passes == passes == len(result.seeds)
    assert result.seeds == [pass_seed(seed, i) for i in range(passes)]  # in pass order
    assert len(set(result.seeds)) == passes  # seeds never repeat across tasks
    indices = sorted(i for task in result.task_passes for i in task)
    assert indices == list(range(passes))  # the tasks partition the passes


def test_agrees_with_a_local_render(client):
    """z-test over seeds against single-process renders of the same total samples (disjoint seeds), and the
    same seed gives the same image as render_passes."""
    integrator = {"type": "segment_pt", "max_depth": 6}
    k, spp, passes = 8, 16, 4
    a, seeds, used = [], set(), set()
    for seed in range(k):
        r = render_distributed(str(SCENES / "cornell.xml"), integrator, spp=spp, passes=passes, seed=seed,
                               defines={"res": RES}, scheduler=client, threads=1, progress=False)
        check_passes(r, spp, passes, seed)
        assert r.image.shape == (RES, RES, 3) and r.channels == ["R", "G", "B"]
        assert r.stop_reason == "spp" and not r.interrupted and r.cancelled_tasks == 0
        seeds.update(r.seeds)
        used.update(r.task_workers)
        a.append(r.image.astype(np.float64))
    assert len(seeds) == k * passes
    assert len(used) == 2  # both workers took part
    scene = cornell()
    b = [local(scene, integrator, spp=spp, passes=passes, seed=1000 + s) for s in range(k)]
    result = compare(np.stack(a), np.stack(b).astype(np.float64), tiles=3)
    print(result)
    assert result.mean_b > 0 and result.max_abs < 4, str(result)
    np.testing.assert_allclose(a[3], local(scene, integrator, spp=spp, passes=passes, seed=3), rtol=1e-5,
                               atol=1e-6)


def test_tasks_group_passes_and_a_scene_dict_ships(client):
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 16
    r = render_distributed(d, "path", spp=14, passes=7, task_passes=3, seed=11, scheduler=client, threads=1,
                           progress=False)
    check_passes(r, 14, 7, 11)
    assert sorted(r.task_passes) == [[0, 1, 2], [3, 4, 5], [6]]
    expected = local(mi.load_dict(d), {"type": "path"}, spp=14, passes=7, seed=11)
    np.testing.assert_allclose(r.image, expected, rtol=1e-5, atol=1e-6)


def test_a_killed_worker_loses_nothing(client):
    """SIGKILL a worker while it has tasks: Dask runs them again, every pass is counted exactly once."""
    integrator = {"type": "path", "max_depth": 6}
    spp, passes = 48, 24
    before = client.run(os.getpid)
    killed, lost = [], []

    def kill_busy_worker(report):
        if killed:
            return
        busy = [(w, keys) for w, keys in client.processing().items() if keys]
        if busy:
            worker, keys = busy[0]
            pid = client.run(os.getpid, workers=[worker])[worker]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)
            lost.extend(keys)  # tasks it was running or had queued: never returned by it

    r = render_distributed(str(SCENES / "cornell.xml"), integrator, spp=spp, passes=passes, task_passes=1,
                           seed=5, defines={"res": 48}, scheduler=client, threads=1, progress=False,
                           callback=kill_busy_worker)
    assert killed and lost, "no worker was busy after the first task"
    check_passes(r, spp, passes, 5)
    client.wait_for_workers(2, timeout=60)  # the nanny restarted it
    after = client.run(os.getpid)
    assert killed[0] in before.values() and killed[0] not in after.values()
    expected = local(cornell(48), integrator, spp=spp, passes=passes, seed=5)
    np.testing.assert_allclose(r.image, expected, rtol=1e-5, atol=1e-6)


def test_time_budget_keeps_what_finished(client):
    budget = 3.0
    reports = []
    r = render_distributed(str(SCENES / "cornell.xml"), "path", time_budget=budget, seed=2, defines={"res": 32},
                           scheduler=client, threads=1, progress=False, callback=reports.append)
    assert r.stop_reason == "time" and not r.interrupted
    assert r.spp == sum(r.pass_spp) == reports[-1].spp and r.passes == len(r.seeds) >= 2
    assert len(set(r.seeds)) == r.passes
    assert sorted(r.seeds) == sorted(pass_seed(2, i) for task in r.task_passes for i in task)
    assert np.isfinite(r.image).all() and r.image.mean() > 0
    assert r.seconds < budget + 30  # nothing runs away (generous: the machine is small and shared)


def test_shipped_files_load_from_anywhere(client, tmp_path, monkeypatch):
    """An <include>, a $define'd texture, a ../ path and an absolute path: the workers get them as bytes (the
    originals are deleted before rendering) and load them in their own folder, whatever the cwd."""
    proj, shared, far = tmp_path / "src" / "proj", tmp_path / "src" / "shared", tmp_path / "far"
    for folder in (proj / "parts", proj / "textures", shared, far):
        folder.mkdir(parents=True)
    texture = SCENES / "textures" / "checker_light.exr"
    shutil.copy(texture, proj / "textures" / "checker.exr")
    shutil.copy(texture, shared / "shared.exr")
    shutil.copy(SCENES / "textures" / "sky.exr", far / "sky.exr")
    (proj / "main.xml").write_text(f"""<scene version="3.0.0">
  <default name="tex" value="textures/checker.exr"/>
  <integrator type="path"><integer name="max_depth" value="3"/></integrator>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 0, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="sphere">
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance"><string name="filename" value="$tex"/>
    </texture></bsdf>
  </shape>
  <include filename="parts/walls.xml"/>
  <emitter type="envmap"><string name="filename" value="{far / 'sky.exr'}"/></emitter>
</scene>""")
    # relative paths in included files are relative to the main scene's folder, as Mitsuba resolves them
    (proj / "parts" / "walls.xml").write_text("""<scene version="3.0.0">
  <shape type="rectangle">
    <transform name="to_world"><translate z="-1.5"/><scale value="3"/></transform>
    <bsdf type="diffuse"><texture type="bitmap" name="reflectance">
      <string name="filename" value="../shared/shared.exr"/><boolean name="raw" value="true"/>
    </texture></bsdf>
  </shape>
</scene>""")
    defines = {"tex": "textures/checker.exr"}
    expected = local(mi.load_file(str(proj / "main.xml"), **defines), {"type": "path"}, spp=4, passes=2, seed=9)

    bundle = package_scene(proj / "main.xml", defines)
    assert sorted(bundle.files) == ["far/sky.exr", "src/proj/main.xml", "src/proj/parts/walls.xml",
                                    "src/proj/textures/checker.exr", "src/shared/shared.exr"]
    assert str(far) not in bundle.files["src/proj/main.xml"].decode()  # the absolute path was rewritten
    shutil.rmtree(tmp_path / "src")
    shutil.rmtree(far)
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    r = render_distributed(bundle, "path", spp=4, passes=2, seed=9, scheduler=client, threads=1, progress=False)
    check_passes(r, 4, 2, 9)
    np.testing.assert_allclose(r.image, expected, rtol=1e-5, atol=1e-6)
    assert r.image.mean() > 0


def test_scene_dict_files_ship(client, tmp_path):
    texture = tmp_path / "t.exr"
    mi.Bitmap(np.random.default_rng(1).uniform(0.2, 0.8, (4, 4, 3)).astype(np.float32)).write(str(texture))
    d = mi.cornell_box()
    d["sensor"]["film"]["width"] = d["sensor"]["film"]["height"] = 16
    d["white"]["reflectance"] = {"type": "bitmap", "filename": str(texture)}
    expected = local(mi.load_dict(d), {"type": "path"}, spp=4, passes=2, seed=1)
    bundle = package_scene(d)
    assert list(bundle.files) == ["0/t.exr"]
    texture.unlink()
    r = render_distributed(bundle, "path", spp=4, passes=2, seed=1, scheduler=client, threads=1, progress=False)
    np.testing.assert_allclose(r.image, expected, rtol=1e-5, atol=1e-6)


def test_packaging_errors(tmp_path):
    scene = tmp_path / "s.xml"
    scene.write_text('<scene version="3.0.0"><shape type="obj"><string name="filename" value="$mesh"/></shape>'
                     "</scene>")
    with pytest.raises(FileNotFoundError, match="nope.obj"):
        package_scene(scene, {"mesh": "nope.obj"})
    with pytest.raises(ValueError, match="undefined parameter"):
        package_scene(scene)
    with pytest.raises(FileNotFoundError, match="does not exist"):
        package_scene(tmp_path / "missing.xml")
    with pytest.raises(TypeError, match="cannot be shipped"):
        package_scene({"type": "scene", "shape": mi.load_dict({"type": "sphere"})})


def test_worker_errors_are_reported(client):
    with pytest.raises(DistributedError, match="(?s)cannot load the scene or integrator.*bogus"):
        render_distributed(str(SCENES / "cornell.xml"), {"type": "path", "bogus": 1}, spp=1, scheduler=client,
                           progress=False)


# --- command line ---------------------------------------------------------------------------------------


def segmitsuba(*args: str, cwd: Path | None = None, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "segmitsuba", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300, env={**os.environ, **(env or {})})


def test_cli_workers_writes_the_same_outputs(tmp_path):
    out = tmp_path / "d.exr"
    r = segmitsuba("render", str(SCENES / "cornell.xml"), "-D", "res=16", "-i", "path", "--spp", "12",
                   "--passes", "6", "--seed", "4", "--workers", "2", "-o", str(out), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "dask: local cluster" in r.stderr and "task 6/6" in r.stderr and "Traceback" not in r.stderr
    image, meta = read_exr(out)
    assert out.with_suffix(".png").is_file()
    assert image.shape == (16, 16, 3) and meta["channels"] == ["R", "G", "B"]
    assert meta["spp"] == 12 and meta["passes"] == 6 and json.loads(meta["pass_spp"]) == [2] * 6
    assert json.loads(meta["pass_seeds"]) == [pass_seed(4, i) for i in range(6)]
    assert meta["dask_workers"] == 2 and meta["tasks"] == len(json.loads(meta["task_passes"]))
    assert json.loads(meta["worker_environment"])["variant"] == "llvm_ad_rgb"
    expected = local(cornell(16), {"type": "path"}, spp=12, passes=6, seed=4)
    np.testing.assert_allclose(image, expected, rtol=1e-5, atol=1e-6)


def test_cli_scheduler_file(client, tmp_path):
    """--scheduler with a running cluster (here through its scheduler file), the built-in scene as a dict."""
    # what `dask scheduler --scheduler-file` writes (client.write_scheduler_file fails in distributed 2026.8)
    (tmp_path / "scheduler.json").write_text(json.dumps({"type": "Scheduler", "address": client.scheduler.address}))
    out = tmp_path / "s.exr"
    r = segmitsuba("render", "--res", "12x8", "-i", "segment_pt", "--spp", "6", "--scheduler",
                   str(tmp_path / "scheduler.json"), "-o", str(out), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert f"dask: scheduler {client.scheduler.address}" in r.stderr
    image, meta = read_exr(out)
    assert image.shape == (8, 12, 3) and meta["spp"] == 6 and meta["passes"] == 4  # 2 per worker
    assert meta["scene"] == cli.BUILTIN_SCENE and meta["dask_workers"] == 2
    assert len(set(json.loads(meta["pass_seeds"]))) == 4


def test_cli_ctrl_c_keeps_the_finished_tasks(tmp_path):
    """Ctrl-C in a terminal signals the whole process group: the local workers must survive it (they leave
    the group), unfinished tasks are cancelled and the finished passes written."""
    out = tmp_path / "int.exr"
    proc = subprocess.Popen(
        [sys.executable, "-m", "segmitsuba", "render", str(SCENES / "cornell.xml"), "-D", "res=16", "-i", "path",
         "--spp", "16000", "--pass-spp", "8", "--workers", "2", "-o", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
        preexec_fn=default_sigint,
    )
    try:
        lines = []
        for line in proc.stderr:  # one line per task when stderr is not a terminal
            lines.append(line)
            if line.startswith("task 2/"):
                os.killpg(proc.pid, signal.SIGINT)
                break
        else:
            pytest.fail("no task was reported: " + "".join(lines))
        stdout, stderr = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == cli.EXIT_INTERRUPTED, stderr
    assert "cancelled" in stderr and "interrupted: writing the average" in stderr and "Traceback" not in stderr
    image, meta = read_exr(out)
    assert np.isfinite(image).all() and meta["interrupted"] == 1 and meta["stop_reason"] == "interrupt"
    assert meta["spp"] == 8 * meta["passes"] < 16000
    assert len(set(json.loads(meta["pass_seeds"]))) == meta["passes"]


def test_cli_unreachable_scheduler(tmp_path):
    r = segmitsuba("render", "--res", "8", "--spp", "1", "--scheduler", "tcp://127.0.0.1:9", "-q", "-o",
                   str(tmp_path / "x.exr"), env={"DASK_DISTRIBUTED__COMM__TIMEOUTS__CONNECT": "1s"})
    assert r.returncode == 2, r.stderr
    assert "cannot connect to the Dask scheduler at 'tcp://127.0.0.1:9'" in r.stderr
    assert "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert not (tmp_path / "x.exr").exists()


def test_cli_without_dask(tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if it were not installed
    code = cli.main(["render", "--res", "8", "--spp", "1", "--workers", "2", "-o", str(tmp_path / "x.exr")])
    assert code == 2
    assert "pip install 'segmitsuba[distributed]'" in capsys.readouterr().err
    with pytest.raises(ImportError, match=r"segmitsuba\[distributed\]"):
        render_distributed(str(SCENES / "cornell.xml"), spp=1, workers=1)
    r = segmitsuba("render", "--workers", "2", "--scheduler", "tcp://x:1")
    assert r.returncode == 2 and "not allowed with argument" in r.stderr


def test_core_package_does_not_import_dask():
    code = ("import sys, segmitsuba, segmitsuba.cli, segmitsuba.rendering, segmitsuba.distributed; "
            "print(sorted(m for m in sys.modules if m.split('.')[0] in ('dask', 'distributed')))")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stderr
    assert r.stdout.strip() == "[]"


def test_filters_follow_the_render_on_workers(client):
    """The kernel schedule is the render's: a 2-worker render of 4-spp passes uses the per-pool kernel sizes,
    offsets and seeds of one mi.render call, and (box filter: pixels average their own samples) its image."""
    d = mi.cornell_box()
    d["sensor"]["film"].update({"width": 16, "height": 16, "rfilter": {"type": "box"}})
    scene = mi.load_dict(d)
    integrator = mi.load_dict({"type": "segment_bdf"})
    one = np.array(mi.render(scene, integrator=integrator, spp=16, seed=5))
    pools = integrator.last_stats["pools"]
    assert len(pools) == 4
    # Dask may give one worker every task of a render this short (a task takes a fraction of a second): render
    # again until both workers have rendered pools, each render held to the one call
    workers = set()
    for _ in range(4):
        r = render_distributed(d, {"type": "segment_bdf"}, spp=16, pass_spp=4, seed=5, scheduler=client,
                               progress=False)
        assert [(p["spp_offset"], p["spp"], p["seed"]) for p in r.pools] == [
            (p["spp_offset"], p["spp"], p["seed"]) for p in pools]
        assert [p["kernel_size"] for p in r.pools] == pytest.approx([p["kernel_size"] for p in pools], rel=1e-6)
        np.testing.assert_allclose(r.image, one, rtol=1e-4, atol=1e-6)
        workers.update(r.task_workers)
        if len(workers) == 2:
            break
    assert len(workers) == 2  # both workers rendered

