"""Converged reference images of the test scenes (``scenes/*.xml``), kept as EXR files in ``tests/references``.

A reference is rendered with an unbiased integrator that is complete for its scene (``path`` in general,
``ptracer`` where ``path`` cannot sample some light transport, ``segment_bdpt`` where it is much more
efficient than ``path``), in two independent halves (disjoint seeds). The file stores their average; its
metadata records the relMSE between the halves (``half_relmse``), which measures the reference's own noise:
the stored average has a relMSE of about ``half_relmse / 4`` against the converged image
(``expected_relmse``).

Two sets are stored: every scene at the test resolution (32x32, float32 pixels), and the equal-time benchmark
scenes (:data:`BENCHMARK_SCENES`) at :data:`BENCHMARK_RES` (256x256, half-float pixels, see
:data:`HALF_MIN_RES`). The method and the spp of a reference depend on the scene and the resolution
(:func:`method`, :func:`default_spp`: the tables :data:`METHODS` / :data:`SPP` at 32 and
:data:`METHODS_BY_RES` / :data:`SPP_BY_RES` per resolution).

    import segmitsuba
    from segmitsuba.references import load_reference

    image, meta = load_reference("cornell")          # res 32, max_depth 8: the test resolution
    print(image.shape, meta["integrator"], meta["spp"], meta["half_relmse"])
    image, meta = load_reference("caustic", res=256) # the benchmark resolution

Regenerate with ``segmitsuba reference --all`` (or ``segmitsuba reference SCENE ...``), and the benchmark set
with ``segmitsuba reference --res 256 cornell caustic glossy_occluded sds veach_glossy``; see
``tests/references/README.md`` for the tables of references.

**Image convention.** References follow ``path``'s pixel definition: each pixel is the filter-weighted
average of the radiance over the image, normalized by the filter weight that falls inside the image.
Mitsuba's ``ptracer`` (and segmitsuba's light tracers, which splat the same way) normalize each splat over
the whole filter footprint and drop what falls outside the image, so with a filter wider than a pixel
(the default Gaussian) their outermost pixels come out darker (~16% in the edge rows and columns at
stddev 0.5). ``ptracer`` references are divided by that deterministic gain (:func:`border_gain`); multiply
a reference by it to get the light-tracing convention.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
import time
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
#: the test scenes
SCENES_DIR = ROOT / "scenes"
#: where the references are kept
REFERENCES_DIR = ROOT / "tests" / "references"

DEFAULT_RES = 32
DEFAULT_MAX_DEPTH = 8
DEFAULT_SEED = 0
#: total spp (both halves) of a scene that :data:`SPP` does not list
DEFAULT_SPP = 16384
#: regularizer of the relMSE denominator: mean((a - b)^2 / (ref^2 + RELMSE_EPS))
RELMSE_EPS = 1e-2
#: the second half's seeds start here (the first half's at the seed itself), so the halves never share a pass
HALF_SEED_OFFSET = 1 << 20

#: scenes without a reference, and why
EXCLUDED: dict[str, str] = {
    "medium": "participating media: path/ptracer ignore the medium (volpath scene)",
    "textured": "Mitsuba's ptracer cannot emit from its procedural checkerboard light: the stored references "
    "use textured_bitmap, the same scene with the checker as a bitmap",
}

#: total spp (both halves together) per scene: chosen from measured noise so that half_relmse is well below
#: 1e-3 while ``segmitsuba reference --all`` stays within a few minutes on 2 CPU cores
SPP: dict[str, int] = {
    "caustic": 65536,  # complete with path, but the glass/mirror caustics from a small light are noisy
    "cornell": 32768,  # diffuse interreflection: noisier than the one-light emitter scenes
    "glossy_occluded": 32768,  # light reaches the visible region only indirectly
    "delta_caustic_point": 262144,  # ptracer: noisy per pixel
    # path reaches the coating's caustic only by hitting the small light through the delta lobe. segment_bdpt
    # is more efficient there but renders ~0.4% too bright next to small sphere lights (README, limitations)
    "plastic_caustic": 262144,
}

_PATH_REASON = "path is complete here: every light path has a non-specular vertex that next-event estimation connects"


@dataclass(frozen=True)
class Method:
    """How a scene's reference is rendered."""

    integrator: str
    reason: str
    #: ids of the specular shapes that make ``path`` incomplete (removed to check ptracer against path)
    specular_ids: tuple[str, ...] = ()


#: the integrator per scene at the test resolution, where it is not ``path``
METHODS: dict[str, Method] = {
    "delta_caustic_point": Method(
        "ptracer",
        "path cannot sample point light -> specular -> diffuse (delta light and delta BSDF both need "
        "connecting); ptracer can, and is complete here because the camera sees no specular surface (the glass "
        "sphere and mirror are outside the frustum), so every camera connection is made on a diffuse surface. "
        "Checked: with the glass and mirror removed, path and border-corrected ptracer agree (method_check). "
        "The ptracer image is divided by border_gain (path's pixel convention at the image border).",
        specular_ids=("glass", "mirror"),
    ),
}


#: the scenes of the equal-time benchmark (``segmitsuba bench equal-time``), stored at :data:`BENCHMARK_RES`
BENCHMARK_SCENES = ("cornell", "caustic", "glossy_occluded", "sds", "veach_glossy")
#: the benchmark resolution
BENCHMARK_RES = 256
#: stored references beyond the test resolution: res -> scenes
EXTRA_RESOLUTIONS: dict[int, tuple[str, ...]] = {BENCHMARK_RES: BENCHMARK_SCENES}
#: references at this resolution or more are stored as half floats (half the size; the rounding, below 2^-11
#: relative, adds a relMSE of ~1e-8, recorded as ``half_rounding_relmse``)
HALF_MIN_RES = 128
#: lossless EXR compression of the stored references
COMPRESSION = "zip"

#: total spp per scene at other resolutions than the test one: res -> scene -> spp (else :data:`SPP`), chosen
#: from measured noise so that expected_relmse is ~1e-4 or less within ~10 minutes per scene on 2 CPU cores
SPP_BY_RES: dict[int, dict[str, int]] = {
    BENCHMARK_RES: {
        "cornell": 4096,
        "caustic": 1024,  # segment_bdpt: ~7x the efficiency of path on the glass and mirror caustics
        "glossy_occluded": 4096,
        "sds": 32768,  # path must hit the small light through the glass sphere: noisy per sample, fast
        "veach_glossy": 4096,
    },
}

#: the integrator per scene at other resolutions, where it is not the test resolution's one (:data:`METHODS`)
METHODS_BY_RES: dict[int, dict[str, Method]] = {
    BENCHMARK_RES: {
        "caustic": Method(
            "segment_bdpt",
            "segment_bdpt is complete here (an area light: every light path also has a technique that path has) "
            "and much more efficient on the glass sphere's and mirror's caustics, which light tracing and bridge "
            "segments reach and path only by hitting the small light (measured at 256x256, max_depth 8: ~7x lower "
            "relMSE than path at equal time). Not exactly unbiased: near the small sphere light it renders "
            "0.2-0.3% brighter than path (method_check: max |t| 6.5 over 4x4 tiles, image ratio 1.001; the same "
            "excess on a diffuse wall next to a lone sphere light, none with a rectangle light), which adds ~1e-6 "
            "to the relMSE of what the reference judges, against its own noise of ~6e-5.",
        ),
        "sds": Method(
            "path",
            "path is complete here (area and environment lights: every path can hit a light). segment_bdpt has no "
            "better technique for the caustic seen through the glass slab (every connection edge of L S S S S D "
            "S S E touches a delta vertex, so it too must hit the light), and was ~4x less efficient than path "
            "at 256x256 (bridges to every light vertex cost time).",
        ),
    },
}

# --- scenes and files ------------------------------------------------------------------------------------


def scene_stem(scene_name: str | Path) -> str:
    """``cornell``, ``cornell.xml`` and ``scenes/cornell.xml`` all name the scene ``cornell``."""
    name = Path(scene_name).name
    return name[:-4] if name.endswith(".xml") else name


def scene_file(scene_name: str | Path, scenes_dir: Path = SCENES_DIR) -> Path:
    return Path(scenes_dir) / f"{scene_stem(scene_name)}.xml"


def reference_scenes(scenes_dir: Path = SCENES_DIR) -> list[str]:
    """Stems of the scenes that have references: every ``*.xml`` in ``scenes_dir`` except :data:`EXCLUDED`."""
    return sorted(p.stem for p in Path(scenes_dir).glob("*.xml") if p.stem not in EXCLUDED)


def reference_scenes_at(res: int, scenes_dir: Path = SCENES_DIR) -> list[str]:
    """Stems of the scenes with a stored reference at ``res``: :func:`reference_scenes` at the test
    resolution, :data:`EXTRA_RESOLUTIONS` elsewhere (empty where none is stored)."""
    if res == DEFAULT_RES:
        return reference_scenes(scenes_dir)
    return sorted(EXTRA_RESOLUTIONS.get(res, ()))


def method(scene_name: str | Path, res: int = DEFAULT_RES) -> Method:
    """How the reference of a scene at resolution ``res`` is rendered: :data:`METHODS_BY_RES`, else
    :data:`METHODS`, else ``path``."""
    stem = scene_stem(scene_name)
    found = METHODS_BY_RES.get(res, {}).get(stem) if res != DEFAULT_RES else None
    return found or METHODS.get(stem, Method("path", _PATH_REASON))


def default_spp(scene_name: str | Path, res: int = DEFAULT_RES) -> int:
    """Total spp (both halves) of a scene's reference at ``res``: :data:`SPP_BY_RES`, else :data:`SPP`, else
    :data:`DEFAULT_SPP`."""
    stem = scene_stem(scene_name)
    found = SPP_BY_RES.get(res, {}).get(stem) if res != DEFAULT_RES else None
    return found or SPP.get(stem, DEFAULT_SPP)


def stored_as_half(res: int) -> bool:
    """Whether references at ``res`` are stored with half-float pixels (:data:`HALF_MIN_RES`)."""
    return res >= HALF_MIN_RES


def reference_path(scene_name: str | Path, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH,
                   directory: Path = REFERENCES_DIR) -> Path:
    """``tests/references/<stem>_r<res>_d<max_depth>.exr``."""
    return Path(directory) / f"{scene_stem(scene_name)}_r{res}_d{max_depth}.exr"


def regenerate_command(scene_name: str | Path, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH) -> str:
    cmd = f"segmitsuba reference {scene_stem(scene_name)}"
    if res != DEFAULT_RES:
        cmd += f" --res {res}"
    if max_depth != DEFAULT_MAX_DEPTH:
        cmd += f" --max-depth {max_depth}"
    return cmd


def sha256_file(path: Path) -> str:
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def scene_dependencies(path: Path) -> dict[str, str]:
    """sha256 of the files a scene loads (``<string name="filename" .../>``: textures), by relative path."""
    deps: dict[str, str] = {}
    for element in ET.parse(path).getroot().iter("string"):
        if element.get("name") == "filename" and element.get("value") and "$" not in element.get("value", ""):
            rel = element.get("value", "")
            dep = Path(path).parent / rel
            deps[rel] = sha256_file(dep) if dep.is_file() else "missing"
    return deps


def stale_reason(metadata: dict[str, Any], scene_name: str | Path, scenes_dir: Path = SCENES_DIR) -> str | None:
    """Why a reference no longer matches its scene (the scene file or a texture changed), or None."""
    path = scene_file(scene_name, scenes_dir)
    if not path.is_file():
        return f"scene file {path} does not exist"
    if metadata.get("scene_sha256") != sha256_file(path):
        return f"{path.name} changed since the reference was rendered (sha256 differs)"
    stored = metadata.get("scene_dependencies", "{}")
    stored = json.loads(stored) if isinstance(stored, str) else stored
    current = scene_dependencies(path)
    for rel in sorted(set(stored) | set(current)):
        if stored.get(rel) != current.get(rel):
            return f"{rel} (used by {path.name}) changed since the reference was rendered (sha256 differs)"
    return None


def load_reference(scene_name: str | Path, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH,
                   directory: Path = REFERENCES_DIR) -> tuple[np.ndarray, dict[str, Any]]:
    """The reference image (H x W x 3 float32) and its metadata (JSON values decoded).

    Raises FileNotFoundError naming the command that generates the missing file.
    """
    from .imageio import read_exr

    path = reference_path(scene_name, res, max_depth, directory)
    if not path.is_file():
        stem = scene_stem(scene_name)
        why = f" ({stem} is excluded: {EXCLUDED[stem]})" if stem in EXCLUDED else ""
        raise FileNotFoundError(
            f"no reference for scene '{stem}' at res {res}, max_depth {max_depth}: {path} is missing{why}; "
            f"generate it with: {regenerate_command(stem, res, max_depth)}"
        )
    image, metadata = read_exr(path)
    for key, value in list(metadata.items()):
        if isinstance(value, str) and value[:1] in "{[":
            try:
                metadata[key] = json.loads(value)
            except ValueError:
                pass
    return image, metadata


def relmse(a: np.ndarray, b: np.ndarray, ref: np.ndarray | None = None, eps: float = RELMSE_EPS) -> float:
    """mean((a - b)^2 / (ref^2 + eps)) over pixels and channels; ``ref`` defaults to (a + b) / 2."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    ref = (a + b) / 2 if ref is None else np.asarray(ref, dtype=np.float64)
    return float(np.mean((a - b) ** 2 / (ref**2 + eps)))


# --- rendering -------------------------------------------------------------------------------------------


def border_gain(rfilter: Any, width: int, height: int, steps: int = 256) -> np.ndarray:
    """Per-pixel ratio (H x W) of a light tracer's image to ``path``'s, for locally smooth radiance.

    A splat at film position x gives pixel k the weight w(c_k - x) / sum_j w(c_j - x) (normalized over the
    whole footprint, also the pixels outside the image, which are dropped); ``path`` instead divides by the
    weights that fall inside the image. The gain is the integral of the first over the image, per axis
    (the filter is separable): 1 inside, < 1 within the filter radius of the image border.
    """
    import mitsuba as mi

    def axis(n: int) -> np.ndarray:
        r = float(rfilter.radius())
        reach = int(math.ceil(r)) + 1
        k = np.arange(-reach, n + reach)
        x = (np.arange(n * steps) + 0.5) / steps
        d = (k[None, :] + 0.5) - x[:, None]
        w = np.array(rfilter.eval(mi.Float(d.ravel().astype(np.float32))), dtype=np.float64).reshape(d.shape)
        w = np.where(np.abs(d) <= r, w, 0.0)
        g = w / w.sum(axis=1, keepdims=True)
        return g[:, (k >= 0) & (k < n)].sum(axis=0) / steps

    return np.outer(axis(height), axis(width))


def _scene_without(path: Path, shape_ids: Iterable[str]) -> str:
    root = ET.parse(path).getroot()
    ids = set(shape_ids)
    for shape in list(root.findall("shape")):
        if shape.get("id") in ids:
            root.remove(shape)
    return ET.tostring(root, encoding="unicode")


def _render(scene: Any, integrator: str, max_depth: int, spp: int, seed: int) -> tuple[np.ndarray, Any]:
    """One render (in passes) as float64 RGB, in path's pixel convention, and the RenderResult."""
    import mitsuba as mi

    from .rendering import render_passes

    result = render_passes(scene, mi.load_dict({"type": integrator, "max_depth": max_depth}), spp=spp,
                           seed=seed, progress=False, handle_sigint=False)
    image = result.image.astype(np.float64)[..., :3]
    if integrator == "ptracer":
        film = scene.sensors()[0].film()
        w, h = (int(v) for v in film.crop_size())
        image = image / border_gain(film.rfilter(), w, h)[..., None]
    return image, result


def _tile_means(image: np.ndarray, tiles: int = 4) -> np.ndarray:
    ys = np.array_split(np.arange(image.shape[0]), tiles)
    xs = np.array_split(np.arange(image.shape[1]), tiles)
    out = [image[y][:, x].mean() for y in ys for x in xs]
    ring = np.ones(image.shape[:2], dtype=bool)
    ring[2:-2, 2:-2] = False
    return np.array([image.mean(), image[ring].mean(), *out])


def check_method(scene_name: str | Path, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH,
                 spp: int = 512, renders: int = 8, seed: int = 1 << 24) -> dict[str, Any]:
    """Check that a scene's reference method (``ptracer`` or ``segment_bdpt``, :func:`method` at ``res``) agrees
    with ``path`` where ``path`` is complete: on the scene without its :attr:`Method.specular_ids` (``ptracer``:
    with them removed, ``path`` can render it completely), or on the full scene where there are none
    (``segment_bdpt`` on an area-lit scene: ``path`` is complete but noisy). Compares ``renders`` independent
    renders of each (spp each) on the whole image, the 2-pixel border ring and 4x4 tiles with Welch's t;
    ``agree`` if every |t| < 5."""
    import mitsuba as mi

    m = method(scene_name, res)
    path = scene_file(scene_name)
    scene = (mi.load_string(_scene_without(path, m.specular_ids), res=res, max_depth=max_depth) if m.specular_ids
             else mi.load_file(str(path), res=res, max_depth=max_depth))
    stats = {}
    for integrator in ("path", m.integrator):
        stats[integrator] = np.stack([_tile_means(_render(scene, integrator, max_depth, spp, seed + i)[0].mean(-1))
                                      for i in range(renders)])
    a, b = stats["path"], stats[m.integrator]
    se = np.sqrt(a.var(axis=0, ddof=1) / len(a) + b.var(axis=0, ddof=1) / len(b))
    t = (b.mean(axis=0) - a.mean(axis=0)) / np.where(se > 0, se, 1.0)
    return {
        "removed": list(m.specular_ids),
        "compared": f"path vs {m.integrator}, {renders} renders x {spp} spp each, at {res}x{res}, max_depth "
        f"{max_depth}" + (f", without {'/'.join(m.specular_ids)}" if m.specular_ids else ", full scene"),
        "ratio_image": round(float(b[:, 0].mean() / a[:, 0].mean()), 5),
        "ratio_border": round(float(b[:, 1].mean() / a[:, 1].mean()), 5),
        "t_image": round(float(t[0]), 3),
        "t_border": round(float(t[1]), 3),
        "max_abs_t_tiles": round(float(np.max(np.abs(t[2:]))), 3),
        "agree": bool(np.all(np.abs(t) < 5)),
    }


#: spp per render of :func:`check_method` for each reference method (``segment_bdpt`` is slow per sample)
CHECK_SPP = {"ptracer": 512, "segment_bdpt": 16}


def make_reference(scene_name: str | Path, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH,
                   spp: int | None = None, seed: int = DEFAULT_SEED, directory: Path = REFERENCES_DIR,
                   check: bool = True, say: Callable[[str], None] | None = None) -> Path:
    """Render a scene's reference and write it to :func:`reference_path`; returns that path.

    The method is :func:`method` at ``res``; ``spp`` is the total over both halves (default :func:`default_spp`
    at ``res``). The halves use pass seeds derived from ``seed`` and ``seed + HALF_SEED_OFFSET``. Where the
    method is not ``path``, ``check`` also runs :func:`check_method` and records it. Pixels are half floats
    from :data:`HALF_MIN_RES` on (float32 below), compressed with :data:`COMPRESSION`. Needs a Mitsuba variant
    to be set.
    """
    import mitsuba as mi

    from . import __version__
    from .imageio import HALF_MAX, write_exr
    from .rendering import environment

    stem = scene_stem(scene_name)
    path = scene_file(stem)
    if stem in EXCLUDED:
        raise ValueError(f"scene '{stem}' has no reference: {EXCLUDED[stem]}")
    if not path.is_file():
        raise FileNotFoundError(f"scene file {path} does not exist")
    if not mi.variant():
        raise RuntimeError("make_reference: set a Mitsuba variant first (e.g. mi.set_variant('llvm_ad_rgb'))")
    spp = default_spp(stem, res) if spp is None else spp
    if spp < 2:
        raise ValueError(f"spp must be >= 2 (two halves), got {spp}")
    m = method(stem, res)
    scene = mi.load_file(str(path), res=res, max_depth=max_depth)

    start = time.perf_counter()
    half_a, result_a = _render(scene, m.integrator, max_depth, spp // 2, seed)
    half_b, result_b = _render(scene, m.integrator, max_depth, spp - spp // 2, seed + HALF_SEED_OFFSET)
    seconds = time.perf_counter() - start
    if set(result_a.seeds) & set(result_b.seeds):
        raise RuntimeError(f"make_reference: the two halves of {stem} share pass seeds")
    image = (half_a * result_a.spp + half_b * result_b.spp) / (result_a.spp + result_b.spp)
    half = relmse(half_a, half_b)
    as_half = stored_as_half(res) and float(np.max(np.abs(image))) <= HALF_MAX
    stored = image.astype(np.float16 if as_half else np.float32).astype(np.float64)

    metadata: dict[str, Any] = {
        "software": f"segmitsuba {__version__}",
        "capDate": time.strftime("%Y:%m:%d %H:%M:%S"),
        "integrator": m.integrator,
        "integrator_description": str(mi.load_dict({"type": m.integrator, "max_depth": max_depth})),
        "method_reason": m.reason,
        "spp": result_a.spp + result_b.spp,
        "half_spp": [result_a.spp, result_b.spp],
        "seed": seed,
        "half_seeds": [seed, seed + HALF_SEED_OFFSET],
        "pass_seeds": [result_a.seeds, result_b.seeds],
        "time": round(seconds, 3),
        "res": res,
        "max_depth": max_depth,
        "scene": f"{SCENES_DIR.name}/{path.name}",
        "scene_sha256": sha256_file(path),
        "scene_dependencies": scene_dependencies(path),
        "half_relmse": half,
        "half_relmse_definition": "mean over pixels and channels of (a - b)^2 / (ref^2 + 1e-2), a and b the two "
        "independent halves, ref = (a + b) / 2",
        "expected_relmse": half / 4,
        "expected_relmse_definition": "relMSE of the stored average against the converged image, about "
        "half_relmse / 4",
        "command": regenerate_command(stem, res, max_depth) + (f" --spp {spp}" if spp != default_spp(stem, res) else "")
        + (f" --seed {seed}" if seed != DEFAULT_SEED else ""),
        "pixel_type": "half" if as_half else "float",
        "exr_compression": COMPRESSION,
    }
    if as_half:
        metadata["half_rounding_relmse"] = relmse(stored, image, ref=image)
    if m.integrator == "ptracer":
        metadata["border_gain"] = "divided out: the image is in path's pixel convention (see segmitsuba.references)"
    if m.integrator != "path" and check:
        t0 = time.perf_counter()
        metadata["method_check"] = check_method(stem, res, max_depth, spp=CHECK_SPP.get(m.integrator, 512))
        metadata["method_check_time"] = round(time.perf_counter() - t0, 3)
    metadata.update(environment())

    out = reference_path(stem, res, max_depth, directory)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_exr(out, stored.astype(np.float32), ["R", "G", "B"], metadata, half=as_half, compression=COMPRESSION)
    if say is not None:
        extra = ""
        if "method_check" in metadata:
            c = metadata["method_check"]
            where = f"without {'/'.join(c['removed'])}" if c["removed"] else "on the full scene"
            extra = (f"; check {where}: path vs {m.integrator} "
                     f"{'agree' if c['agree'] else 'DISAGREE'} (ratio {c['ratio_image']}, border {c['ratio_border']},"
                     f" max |t| {max(abs(c['t_image']), abs(c['t_border']), c['max_abs_t_tiles']):.2f})")
        say(f"{stem}: {m.integrator}, {metadata['spp']} spp, half_relmse {half:.2e}, expected relMSE {half / 4:.2e}, "
            f"{seconds:.1f} s, {metadata['pixel_type']} pixels{extra}")
    return out


def table(directory: Path = REFERENCES_DIR, res: int = DEFAULT_RES, max_depth: int = DEFAULT_MAX_DEPTH) -> str:
    """Markdown table (scene, method, spp, half_relmse, expected relMSE, time, pixels, size) of the references
    in ``directory`` at ``res`` / ``max_depth``."""
    rows = ["| scene | method | spp | half_relmse | expected relMSE | time (s) | pixels | KB |",
            "|---|---|---:|---:|---:|---:|---|---:|"]
    pattern = re.compile(rf"(.+)_r{res}_d{max_depth}\.exr$")
    for path in sorted(Path(directory).glob("*.exr")):
        match = pattern.match(path.name)
        if match is None:
            continue
        _, meta = load_reference(match.group(1), res, max_depth, directory)
        rows.append(f"| `{match.group(1)}.xml` | {meta['integrator']} | {meta['spp']} | {meta['half_relmse']:.2e} "
                    f"| {meta['expected_relmse']:.2e} | {meta['time']:.1f} | {meta.get('pixel_type', 'float')} "
                    f"| {path.stat().st_size / 1024:.0f} |")
    return "\n".join(rows)
