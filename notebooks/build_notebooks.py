"""Write the notebooks of this folder (sources only); `python notebooks/build_notebooks.py --execute` also runs
them at full scale with nbclient, so that the committed files carry real outputs. Name notebooks to write only
those (`python notebooks/build_notebooks.py --execute equal_time.ipynb`). The tests run them at a small scale
(SEGMITSUBA_NOTEBOOK_SCALE=small)."""

from __future__ import annotations

import sys
from pathlib import Path

import nbformat
from nbformat.v4 import new_code_cell, new_markdown_cell, new_notebook

HERE = Path(__file__).resolve().parent

SETUP = '''import os, sys
from pathlib import Path
import segmitsuba  # first: sets the libLLVM Dr.Jit needs
import mitsuba as mi
import numpy as np
import matplotlib.pyplot as plt
from IPython.display import Image, display
from segmitsuba.rendering import environment
from segmitsuba.references import load_reference
from segmitsuba import metrics

mi.set_variant("llvm_ad_rgb")
ROOT = Path(segmitsuba.__file__).resolve().parent.parent
SCENES = ROOT / "scenes"
SMALL = os.environ.get("SEGMITSUBA_NOTEBOOK_SCALE") == "small"   # the test suite's setting
env = environment()
print({k: env[k] for k in ("variant", "threads", "llvm_version", "mitsuba_version", "drjit_version", "segmitsuba_version")})'''

def machine(res: int = 32) -> str:
    """The settings paragraph of a notebook whose full-scale scenes are rendered at ``res``."""
    return ("Settings and machine: the committed outputs come from a full-scale run (`python notebooks/"
            "build_notebooks.py --execute`) on a 2-core x86-64 VM (LLVM 19, `llvm_ad_rgb`), scenes at "
            f"{res}x{res} with max_depth 8 against the stored references in `tests/references`. The test suite "
            "runs the same notebook at a small scale (`SEGMITSUBA_NOTEBOOK_SCALE=small`).")


MACHINE = machine()


def equal_time() -> nbformat.NotebookNode:
    return new_notebook(cells=[
        new_markdown_cell("# Equal-time comparison at 256x256\n\n"
                          "The five benchmark scenes of `segmitsuba bench equal-time`: `cornell` (diffuse, "
                          "*kitchen-like*), `caustic` (small light, glass and mirror, *disco-ball-like*), "
                          "`glossy_occluded` (glossy materials lit indirectly, *warehouse-like*), `sds` (a caustic "
                          "seen through glass: no vertex connection samples it) and `veach_glossy` (Veach's "
                          "plates: lights of different sizes on plates of different roughness). Every method "
                          "renders each scene for the same time; the error (relMSE against the stored converged "
                          "reference) is recorded after every pass. The time-to-error ratio against a peer P "
                          "(`path`, `segment_bdpt`) is the time P needs to reach its own final error divided by "
                          "the time the method needs to reach it (> 1: faster; `never`: not within the time).\n\n"
                          "This notebook calls the benchmark's functions (`segmitsuba.benchmarks.equal_time`); "
                          "`segmitsuba bench equal-time` runs the same and writes the JSON of every checkpoint.\n\n"
                          + machine(256)),
        new_code_cell(SETUP),
        new_code_cell("# Parameters\n"
                      "from segmitsuba.benchmarks import equal_time as et\n"
                      "RES = 32 if SMALL else et.BENCHMARK_RES     # the stored references: 32 (tests) and 256\n"
                      "import os\n"
                      "# seconds per method and scene (SEGMITSUBA_NOTEBOOK_TIME sets a full-scale run's)\n"
                      "TIME = 0.3 if SMALL else float(os.environ.get('SEGMITSUBA_NOTEBOOK_TIME', et.DEFAULT_TIME))\n"
                      "METHODS = ['path', 'segment_pf', 'segment_bdf'] if SMALL else list(et.METHODS)\n"
                      "SCENE_NAMES = ['cornell', 'sds'] if SMALL else list(et.BENCHMARK_SCENES)"),
        new_code_cell('''results = {}
for name in SCENE_NAMES:
    results[name] = et.run_scene(name, METHODS, TIME, RES)
    print(et.scene_table(results[name]), "\\n", flush=True)
for claim in et.evaluate_claims({name: r.final_errors() for name, r in results.items()}):
    print(claim)'''),
        new_code_cell('''n = len(SCENE_NAMES)
fig, axes = plt.subplots(1, n, figsize=(4.2 * n, 3.8), squeeze=False)
for ax, name in zip(axes[0], SCENE_NAMES):
    for run in results[name].runs:
        ax.loglog([c.time for c in run.checkpoints], [c.relmse for c in run.checkpoints], marker="o", ms=3,
                  label=run.method)
    floor = results[name].reference.get("expected_relmse")
    if floor:
        ax.axhline(floor, color="grey", ls="--", lw=1, label="reference noise")
    ax.set_title(name); ax.set_xlabel("render time (s)"); ax.set_ylabel("relMSE")
    ax.grid(True, which="both", alpha=0.3)
axes[0][0].legend(fontsize=7)
plt.tight_layout(); plt.show()'''),
        new_code_cell('''from segmitsuba.compare import plot_grid
out = Path("out/notebook_equal_time"); out.mkdir(parents=True, exist_ok=True)
for name in SCENE_NAMES:
    path = out / f"grid_{name}.png"
    plot_grid(results[name].runs, results[name].reference_image, path)
    display(Image(filename=str(path), width=1000))'''),
        new_markdown_cell("Reading: the tables give each method's relMSE after the same render time and how much "
                          "faster (ratio > 1) or slower than `path` and `segment_bdpt` it reaches their error; the "
                          "claims check the talk's statements on the filters. The grids show the final images with "
                          "zoomed crops where the methods differ most. Timings come from a shared 2-core machine "
                          "and vary by ~10-20% from run to run."),
    ])


def kernel_size() -> nbformat.NotebookNode:
    return new_notebook(cells=[
        new_markdown_cell("# Kernel size: bias against variance, and progressive shrinking\n\n"
                          "A large kernel blurs (bias), a small one is noisy (variance). `segment_bdf` with the "
                          "cluster kernel at fixed samples, then the convergence with a fixed kernel (`alpha = 1`) "
                          "against the paper's progressive shrinking (`alpha = 0.67`).\n\n" + MACHINE),
        new_code_cell(SETUP),
        new_code_cell("# Parameters\nSPP = 8 if SMALL else 32\nSIZES = [0.4, 0.1] if SMALL else [0.4, 0.2, 0.1, 0.05, 0.025]\n"
                      "SPPS = [4, 8] if SMALL else [8, 32, 128]\nSCENE_NAMES = ['cornell', 'caustic']"),
        new_code_cell('''rows = []
for name in SCENE_NAMES:
    ref, _ = load_reference(name)
    scene = mi.load_file(str(SCENES / f"{name}.xml"), res=32)
    for size in SIZES:
        integ = mi.load_dict({"type": "segment_bdf", "kernel_size": size, "alpha": 1.0})
        img = np.array(mi.render(scene, integrator=integ, spp=SPP, seed=1))[..., :3]
        rows.append((name, size, metrics.relmse(img, ref), img.mean() / ref.mean()))
for r in rows:
    print(f"{r[0]:10s} size {r[1]:6.3f}  relMSE {r[2]:.4f}  mean/ref {r[3]:.3f}")
fig, axes = plt.subplots(1, 2, figsize=(10, 4))
for name in SCENE_NAMES:
    sel = [r for r in rows if r[0] == name]
    axes[0].loglog([r[1] for r in sel], [r[2] for r in sel], marker="o", label=name)
    axes[1].semilogx([r[1] for r in sel], [r[3] for r in sel], marker="o", label=name)
axes[0].set_xlabel("voxel side"); axes[0].set_ylabel(f"relMSE at {SPP} spp"); axes[0].legend()
axes[1].axhline(1, color="grey", lw=1); axes[1].set_xlabel("voxel side"); axes[1].set_ylabel("image mean / reference (bias)")
plt.tight_layout(); plt.show()'''),
        new_code_cell('''ref, _ = load_reference("cornell")
scene = mi.load_file(str(SCENES / "cornell.xml"), res=32)
fig, ax = plt.subplots(figsize=(5, 4))
for alpha in (1.0, 0.67):
    errs = [metrics.relmse(np.array(mi.render(scene, integrator=mi.load_dict({"type": "segment_bdf", "alpha": alpha}),
                                               spp=s, seed=1))[..., :3], ref) for s in SPPS]
    print(alpha, [f"{e:.4f}" for e in errs])
    ax.loglog(SPPS, errs, marker="o", label=f"alpha = {alpha}")
ax.set_xlabel("spp"); ax.set_ylabel("relMSE (cornell)"); ax.legend(); ax.grid(True, which="both", alpha=0.3)
plt.tight_layout(); plt.show()'''),
    ])


def stability() -> nbformat.NotebookNode:
    return new_notebook(cells=[
        new_markdown_cell("# Failure cases and stability\n\n"
                          "Where each unidirectional filter fails (and that `segment_bdf` does not), and that no "
                          "method produces NaN/Inf or negative pixels on the scenes and on adversarial set-ups.\n\n"
                          + MACHINE),
        new_code_cell(SETUP),
        new_code_cell("# Parameters\nSPP = 4 if SMALL else 32\n"
                      "CASES = ['caustic', 'emitter_point', 'emitter_constant', 'delta_caustic_point']\n"
                      "METHODS = ['segment_mvf', 'segment_pf', 'segment_bdf']"),
        new_code_cell('''fig, axes = plt.subplots(len(CASES), len(METHODS) + 1, figsize=(2.6 * (len(METHODS) + 1), 2.6 * len(CASES)))
for i, name in enumerate(CASES):
    ref, _ = load_reference(name)
    scene = mi.load_file(str(SCENES / f"{name}.xml"), res=32)
    for j, method in enumerate(METHODS):
        img = np.array(mi.render(scene, integrator=mi.load_dict({"type": method}), spp=SPP, seed=2))[..., :3]
        bad = int((~np.isfinite(img)).sum() + (img < 0).sum())
        axes[i, j].imshow(np.clip(img ** (1 / 2.2), 0, 1)); axes[i, j].axis("off")
        axes[i, j].set_title(f"{method[8:]} relMSE {metrics.relmse(np.nan_to_num(img), ref):.3f}\\nbad pixels {bad}", fontsize=8)
    axes[i, -1].imshow(np.clip(ref ** (1 / 2.2), 0, 1)); axes[i, -1].axis("off"); axes[i, -1].set_title(f"{name} reference", fontsize=8)
plt.tight_layout(); plt.show()'''),
        new_markdown_cell("Expected: `segment_mvf` is black for the point light and noisy on caustics (the camera "
                          "cannot hit a point or sample caustics well); `segment_pf` is noisy under the constant "
                          "environment (few photons reach where the camera looks); `segment_bdf` is usable on all."),
        new_code_cell('''base = mi.cornell_box(); base["sensor"]["film"]["width"] = base["sensor"]["film"]["height"] = 16
inside = dict(base)
inside["light"] = {"type": "sphere", "radius": 0.05, "center": [0, 0.2, 0],
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [200, 200, 200]}}}
inside["glass"] = {"type": "sphere", "radius": 0.3, "center": [0, 0.2, 0], "bsdf": {"type": "dielectric"}}
for label, d, props in [("light inside glass", inside, {}), ("tiny kernel", base, {"kernel_size": 1e-5}),
                        ("huge kernel", base, {"kernel_size": 10.0})]:
    scene = mi.load_dict(d)
    for method in METHODS:
        img = np.array(mi.render(scene, integrator=mi.load_dict({"type": method, **props}), spp=SPP))
        print(f"{label:20s} {method:12s} finite {np.isfinite(img).all()}  min {img.min():.3g}  mean {img.mean():.3g}")'''),
    ])


NOTEBOOKS = {"equal_time.ipynb": equal_time, "kernel_size.ipynb": kernel_size, "stability.ipynb": stability}


def main() -> None:
    names = [a for a in sys.argv[1:] if not a.startswith("-")]
    unknown = sorted(set(names) - set(NOTEBOOKS))
    if unknown:
        raise SystemExit(f"unknown notebook(s) {', '.join(unknown)} (notebooks: {', '.join(NOTEBOOKS)})")
    for name, make in NOTEBOOKS.items():
        if names and name not in names:
            continue
        nb = make()
        nb.metadata["kernelspec"] = {"name": "python3", "display_name": "Python 3", "language": "python"}
        if "--execute" in sys.argv:
            from nbclient import NotebookClient

            NotebookClient(nb, timeout=3600, kernel_name="python3",
                           resources={"metadata": {"path": str(HERE.parent)}}).execute()
        nbformat.write(nb, HERE / name)
        print("wrote", HERE / name)


if __name__ == "__main__":
    main()
