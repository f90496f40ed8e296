"""Equal-time comparison at 256x256 against the stored references (``segmitsuba bench equal-time``).

For each scene (default: :data:`segmitsuba.references.BENCHMARK_SCENES`), every method (:data:`METHODS`:
``path``, ``segment_pt``, ``segment_bdpt``, ``segment_mvf``, ``segment_pf``, ``segment_bdf``, all with
``max_depth`` 8) renders for the same time T (``--time``, default 30 s; ``--quick``: 10 s) with
:func:`segmitsuba.compare.run_method`: passes of doubling size, a checkpoint (render seconds so far, relMSE of
the running image against the reference) after each, JIT compilation excluded. The reference is the stored
converged one at ``--res`` (:func:`segmitsuba.references.load_reference`; refused when stale).

Reported per scene: relMSE at T per method, and **time-to-error ratios** against the peers ``path`` and
``segment_bdpt``: for a peer P whose error at T is e_P,

    ratio(M) = T_P(e_P) / T_M(e_P)

where T_X(e) is the time X's error curve first reaches e (:func:`time_to_error`: the running minimum of the
checkpoints' errors, interpolated linearly on log-log axes between the checkpoint before the first crossing
and the crossing). > 1: M reaches the peer's final error faster than the peer; "never": M does not reach it
within T; a ratio marked ">" is a lower bound (M was already below e_P at its first checkpoint). Then the
talk's three claims as PASS/FAIL lines (:data:`CLAIMS`), one log-log error-vs-time PNG per scene and
``results.json`` with every checkpoint in ``--out`` (default ``out/bench_equal_time``).

relMSE is heavy-tailed where rare paths carry much light: on the caustic scene single 30 s runs of one method
have differed several-fold (fireflies through the glass sphere). ``--seeds N`` runs every method N times
(seeds ``--seed`` .. ``--seed + N - 1``); relMSE at T is then their mean, the table shows its spread, and the
ratios are taken on the mean error curves (:func:`mean_curve`). The PNGs show the first seed.

    segmitsuba bench equal-time                       # 5 scenes x 6 methods x 30 s: about 16 minutes
    segmitsuba bench equal-time --quick --scenes caustic,cornell
    segmitsuba bench equal-time --res 32 --time 2     # against the 32x32 test references
    segmitsuba bench equal-time --scenes caustic --seeds 3   # the mean of three runs per method
    segmitsuba bench equal-time --methods "path,segment_bdf,segment_bdf[glossy_vertices=filtered]"

From Python (the notebook ``notebooks/equal_time.ipynb`` does this)::

    from segmitsuba.benchmarks.equal_time import run_scene, scene_table, evaluate_claims
    result = run_scene("caustic", time_budget=10)
    print(scene_table(result))
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from segmitsuba.references import (
    BENCHMARK_RES,
    BENCHMARK_SCENES,
    DEFAULT_MAX_DEPTH,
    load_reference,
    regenerate_command,
    scene_file,
    scene_stem,
    stale_reason,
)

#: the methods compared, in table order
METHODS = ("path", "segment_pt", "segment_bdpt", "segment_mvf", "segment_pf", "segment_bdf")
#: the peers of the time-to-error ratios
PEERS = ("path", "segment_bdpt")
#: the three filters of the talk's claims
FILTERS = ("segment_mvf", "segment_pf", "segment_bdf")
DEFAULT_TIME = 30.0
QUICK_TIME = 10.0
DEFAULT_OUT = Path("out") / "bench_equal_time"
#: an error below this many times the reference's own expected relMSE is marked as near the reference noise
FLOOR_MARGIN = 3.0

#: (scene, statement) of the talk's claims, checked on the relMSE at T by :func:`evaluate_claims`
CLAIMS = (
    ("caustic", "segment_mvf clearly worse than segment_pf (>= 1.5x relMSE) and segment_bdf at least as good as "
                "segment_pf (<= 1.1x)"),
    ("glossy_occluded", "segment_bdf the best of the three filters"),
    ("cornell", "segment_pf the weak one (worst of the three filters) and segment_bdf within 1.2x of segment_mvf"),
)


# --- error-vs-time curves ------------------------------------------------------------------------------------


def running_min(errors: Sequence[float]) -> np.ndarray:
    """The best error reached so far at each checkpoint."""
    return np.minimum.accumulate(np.asarray(errors, dtype=np.float64))


def time_to_error(times: Sequence[float], errors: Sequence[float], target: float) -> float | None:
    """Seconds an error-vs-time curve (checkpoints in increasing time) needs to reach ``target``.

    The curve is its running minimum (noise that raises the error again does not undo progress). At the first
    checkpoint whose error is <= ``target``, the time is interpolated linearly in (log time, log error) between
    that checkpoint and the one before it. None if the curve never reaches ``target``; the first checkpoint's
    time (an upper bound) if it is already there.
    """
    t = np.asarray(times, dtype=np.float64)
    best = running_min(errors)
    if len(t) == 0 or len(t) != len(best):
        raise ValueError(f"time_to_error: {len(t)} times for {len(best)} errors")
    if not target > 0:
        raise ValueError(f"time_to_error: the target error must be > 0, got {target}")
    hits = np.flatnonzero(best <= target)
    if len(hits) == 0:
        return None
    k = int(hits[0])
    if k == 0:
        return float(t[0])
    e0, e1 = best[k - 1], best[k]
    if e1 <= 0:  # a zero error: no log; the crossing is somewhere in the interval, take its end
        return float(t[k])
    f = (math.log(target) - math.log(e0)) / (math.log(e1) - math.log(e0))
    return float(math.exp(math.log(t[k - 1]) + f * (math.log(t[k]) - math.log(t[k - 1]))))


@dataclass(frozen=True)
class Ratio:
    """Time-to-error ratio of a method against a peer: ``peer_time / time`` to reach ``target``."""

    target: float  #: the peer's final error
    peer_time: float  #: when the peer first reached it
    time: float | None  #: when the method first reached it; None: never
    lower_bound: bool  #: the method was already below ``target`` at its first checkpoint

    @property
    def value(self) -> float | None:
        """peer_time / time (> 1: the method is faster); None if the method never reaches the target."""
        return None if self.time is None else self.peer_time / self.time

    def __str__(self) -> str:
        value = self.value
        if value is None:
            return "never"
        return (">" if self.lower_bound else "") + f"{value:.3g}"


def time_to_error_ratio(times: Sequence[float], errors: Sequence[float], peer_times: Sequence[float],
                        peer_errors: Sequence[float]) -> Ratio:
    """The :class:`Ratio` T_P(e_P) / T_M(e_P) of a method M (``times``, ``errors``) against a peer P, e_P the
    error of P's last checkpoint (its error at the common time budget)."""
    target = float(peer_errors[-1])
    if not target > 0:
        raise ValueError(f"time_to_error_ratio: the peer's final error must be > 0, got {target}")
    peer_time = time_to_error(peer_times, peer_errors, target)
    assert peer_time is not None  # its own last checkpoint reaches it
    own = time_to_error(times, errors, target)
    return Ratio(target, peer_time, own, own is not None and running_min(errors)[0] <= target)


def mean_curve(curves: Sequence[tuple[Sequence[float], Sequence[float]]], points: int = 24
               ) -> tuple[list[float], list[float]]:
    """The mean error curve of several runs of one method (``(times, errors)`` each, other seeds): each run's
    errors interpolated linearly on log-log axes at ``points`` log-spaced times, from the latest first
    checkpoint of the runs to the earliest last one, then averaged (arithmetic mean: an estimate of the
    expected relMSE at each time). One run is returned as it is."""
    if len(curves) == 1:
        return list(curves[0][0]), list(curves[0][1])
    if not curves:
        raise ValueError("mean_curve: no runs")
    start = max(float(t[0]) for t, _ in curves)
    end = min(float(t[-1]) for t, _ in curves)
    if not end > start:
        # runs of one checkpoint each, or that do not overlap: the mean error at the budget, at the latest time
        return [max(float(t[-1]) for t, _ in curves)], [float(np.mean([e[-1] for _, e in curves]))]
    grid = np.exp(np.linspace(math.log(start), math.log(end), points))
    values = [np.exp(np.interp(np.log(grid), np.log(np.asarray(t, dtype=float)),
                               np.log(np.maximum(np.asarray(e, dtype=float), 1e-30)))) for t, e in curves]
    return grid.tolist(), np.mean(values, axis=0).tolist()


# --- one scene -----------------------------------------------------------------------------------------------


@dataclass
class SceneResult:
    """The equal-time runs of one scene."""

    scene: str  #: scene stem
    res: int
    time_budget: float
    reference: dict[str, Any]  #: what the reference is (integrator, spp, expected_relmse, path)
    runs: list[Any] = field(default_factory=list)  #: segmitsuba.compare.MethodRun, in method order (first seed)
    reference_image: np.ndarray | None = None
    #: every seed's MethodRun per method (the first is in ``runs``); empty: one seed
    seed_runs: dict[str, list[Any]] = field(default_factory=dict)

    def run(self, method: str) -> Any | None:
        """The MethodRun of ``method`` (its first seed), None if it was not run."""
        return next((r for r in self.runs if r.method == method), None)

    def all_runs(self, method: str) -> list[Any]:
        """Every seed's MethodRun of ``method``."""
        return self.seed_runs.get(method) or [r for r in self.runs if r.method == method]

    def curve(self, method: str) -> tuple[list[float], list[float]]:
        """``method``'s error curve: its checkpoints, or with several seeds their :func:`mean_curve`."""
        return mean_curve([([c.time for c in r.checkpoints], [c.relmse for c in r.checkpoints])
                           for r in self.all_runs(method)])

    def final_errors(self) -> dict[str, float]:
        """relMSE at the time budget (the last checkpoint) per method, averaged over the seeds."""
        return {r.method: float(np.mean([x.checkpoints[-1].relmse for x in self.all_runs(r.method)]))
                for r in self.runs}

    def spread(self, method: str) -> float:
        """Largest over smallest relMSE at T among the seeds of ``method`` (1 with one seed)."""
        e = [x.checkpoints[-1].relmse for x in self.all_runs(method)]
        return float(max(e) / min(e)) if min(e) > 0 else math.inf

    def ratios(self, peer: str) -> dict[str, Ratio]:
        """Each method's time-to-error ratio against ``peer`` (empty if the peer was not run), on the mean
        curves over the seeds."""
        if self.run(peer) is None:
            return {}
        pt, pe = self.curve(peer)
        return {r.method: time_to_error_ratio(*self.curve(r.method), pt, pe) for r in self.runs}


def reference_for(stem: str, res: int) -> tuple[np.ndarray, dict[str, Any]]:
    """The stored reference of a scene at ``res`` (max_depth 8) and a summary of it; FileNotFoundError or
    ValueError (stale) naming the command that regenerates it."""
    image, meta = load_reference(stem, res, DEFAULT_MAX_DEPTH)
    reason = stale_reason(meta, stem)
    if reason is not None:
        raise ValueError(f"the stored reference of {stem} at {res}x{res} is stale ({reason}); regenerate with: "
                         f"{regenerate_command(stem, res)}")
    info = {k: meta.get(k) for k in ("integrator", "spp", "half_relmse", "expected_relmse", "time", "pixel_type")}
    info["path"] = str(Path("tests") / "references" / f"{stem}_r{res}_d{DEFAULT_MAX_DEPTH}.exr")
    return image[..., :3].astype(np.float64), info


def parse_method(spec: str) -> tuple[str, dict[str, Any]]:
    """``plugin`` or ``plugin[key=value,...]`` (integrator properties; numbers, true/false, else strings), so
    that one plugin can run with several settings: ``segment_bdf[glossy_vertices=filtered]``."""
    m = re.fullmatch(r"\s*([\w.]+)\s*(?:\[(.*)\])?\s*", spec)
    if m is None:
        raise ValueError(f"method {spec!r}: expected 'plugin' or 'plugin[key=value,...]'")
    params: dict[str, Any] = {}
    for item in filter(None, (x.strip() for x in (m.group(2) or "").split(","))):
        key, sep, text = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"method {spec!r}: property {item!r} is not key=value")
        text = text.strip()
        value: Any = text
        if text.lower() in ("true", "false"):
            value = text.lower() == "true"
        else:
            for tp in (int, float):
                try:
                    value = tp(text)
                    break
                except ValueError:
                    pass
        params[key.strip()] = value
    return m.group(1), params


def split_methods(text: str) -> list[str]:
    """The method specs of a comma-separated list (commas inside ``[...]`` belong to a spec)."""
    return [m.strip() for m in re.split(r",(?![^\[]*\])", text) if m.strip()]


def run_scene(scene_name: str, methods: Sequence[str] = METHODS, time_budget: float = DEFAULT_TIME,
              res: int = BENCHMARK_RES, seed: int = 0, say: Callable[[str], None] | None = None,
              seeds: int = 1) -> SceneResult:
    """Render one scene with every method for ``time_budget`` seconds each (max_depth 8) against its stored
    reference at ``res``, ``seeds`` times (seeds ``seed``, ``seed + 1``, ...); needs a Mitsuba variant to be
    set."""
    if seeds < 1:
        raise ValueError(f"seeds must be >= 1, got {seeds}")
    import mitsuba as mi

    from segmitsuba.compare import run_method

    stem = scene_stem(scene_name)
    ref, info = reference_for(stem, res)
    scene = mi.load_file(str(scene_file(stem)), res=res)
    result = SceneResult(stem, res, time_budget, info, reference_image=ref.astype(np.float32))
    for method in methods:
        plugin, params = parse_method(method)
        runs = []
        for k in range(seeds):
            if say is not None:
                say(f"[{stem}] {method}: {time_budget:g} s" + (f", seed {seed + k}" if seeds > 1 else ""))
            run = run_method(scene, plugin, ref, time_budget, {"max_depth": DEFAULT_MAX_DEPTH, **params}, seed + k,
                             True, flip_every=False, say=say)
            run.method = method  # the spec: one plugin may run with several settings
            runs.append(run)
        result.runs.append(runs[0])
        if seeds > 1:
            result.seed_runs[method] = runs
    return result


def scene_table(result: SceneResult) -> str:
    """The scene's table: passes, spp, time and relMSE at T per method, and the ratios against the peers."""
    ref = result.reference
    floor = float(ref.get("expected_relmse") or 0.0)
    ratios = {peer: result.ratios(peer) for peer in PEERS}
    finals = result.final_errors()
    seeds = max((len(result.all_runs(r.method)) for r in result.runs), default=1)
    lines = [f"[{result.scene}] {result.res}x{result.res}, max_depth {DEFAULT_MAX_DEPTH}, {result.time_budget:g} s "
             f"per method" + (f" x {seeds} seeds" if seeds > 1 else "")
             + f"; reference: {ref.get('integrator')} {ref.get('spp')} spp, own relMSE ~{floor:.1e}",
             f"  {'method':<13} {'passes':>6} {'spp':>6} {'time s':>7} {'relMSE at T':>12}"
             + (f" {'max/min':>8}" if seeds > 1 else "") + "".join(f" {'vs ' + p:>16}" for p in PEERS)]
    for r in result.runs:
        c = r.checkpoints[-1]
        e = finals[r.method]
        near = " ~ref" if floor > 0 and e < FLOOR_MARGIN * floor else ""
        spread = f" {result.spread(r.method):>8.2f}" if seeds > 1 else ""
        cells = "".join(f" {str(ratios[p].get(r.method, '-')) if ratios[p] else 'n/a':>16}" for p in PEERS)
        lines.append(f"  {r.method:<13} {len(r.checkpoints):>6} {c.spp:>6} {c.time:>7.2f} {e:>12.3e}{spread}{cells}"
                     f"{near}")
    lines.append("  ratio vs P = (time P needs for its own error at T) / (time the method needs for it): > 1 faster"
                 + (f"; ~ref: within {FLOOR_MARGIN:g}x of the reference's own noise" if floor > 0 else ""))
    if seeds > 1:
        lines.append("  relMSE at T: mean over the seeds; max/min: its spread; ratios on the mean error curves; "
                     "passes, spp, time: the first seed's")
    return "\n".join(lines)


# --- the talk's claims ---------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Claim:
    """One of :data:`CLAIMS`, checked: ``passed`` is None where its scene or filters were not run."""

    scene: str
    statement: str
    passed: bool | None
    detail: str

    def __str__(self) -> str:
        status = "SKIP" if self.passed is None else "PASS" if self.passed else "FAIL"
        return f"{status}  {self.scene}: {self.statement} ({self.detail})"


def evaluate_claims(errors: dict[str, dict[str, float]]) -> list[Claim]:
    """Check :data:`CLAIMS` on the relMSE at T, ``errors[scene][method]``."""
    out = []
    for scene, statement in CLAIMS:
        e = errors.get(scene, {})
        if not all(m in e for m in FILTERS):
            out.append(Claim(scene, statement, None, "needs " + ", ".join(FILTERS) + f" on {scene}"))
            continue
        mvf, pf, bdf = (e[m] for m in FILTERS)
        numbers = f"mvf {mvf:.3e}, pf {pf:.3e}, bdf {bdf:.3e}"
        if scene == "caustic":
            passed = mvf >= 1.5 * pf and bdf <= 1.1 * pf
            detail = f"mvf/pf {mvf / pf:.2f}, bdf/pf {bdf / pf:.2f}; {numbers}"
        elif scene == "glossy_occluded":
            passed = bdf <= min(mvf, pf)
            detail = f"bdf/min(mvf, pf) {bdf / min(mvf, pf):.2f}; {numbers}"
        else:
            passed = pf >= max(mvf, bdf) and bdf <= 1.2 * mvf
            detail = f"pf/max(mvf, bdf) {pf / max(mvf, bdf):.2f}, bdf/mvf {bdf / mvf:.2f}; {numbers}"
        out.append(Claim(scene, statement, bool(passed), detail))
    return out


# --- outputs -------------------------------------------------------------------------------------------------


def plot_scene(result: SceneResult, path: Path) -> None:
    """Log-log relMSE vs render seconds of every method, with the reference's own noise as a floor."""
    from segmitsuba.compare import plot_error_vs_time

    ref = result.reference
    floor = ref.get("expected_relmse")
    title = (f"{result.scene} {result.res}x{result.res}, max_depth {DEFAULT_MAX_DEPTH}, "
             f"{result.time_budget:g} s/method; reference {ref.get('integrator')} {ref.get('spp')} spp")
    plot_error_vs_time(result.runs, path, title, float(floor) if floor else None)


def results_json(results: Sequence[SceneResult], claims: Sequence[Claim], settings: dict[str, Any]) -> dict[str, Any]:
    """Everything measured, JSON-ready: settings, machine, and per scene the reference, every method's
    checkpoints and final metrics, and the ratios; then the claims."""
    from segmitsuba.rendering import environment

    scenes = {}
    for r in results:
        finals = r.final_errors()
        ratios = {peer: {m: {"value": x.value, "lower_bound": x.lower_bound, "target": x.target,
                             "peer_time": x.peer_time, "time": x.time} for m, x in r.ratios(peer).items()}
                  for peer in PEERS}
        scenes[r.scene] = {
            "reference": r.reference,
            "methods": {run.method: {"params": run.params, "integrator": run.integrator,
                                     "compile_seconds": run.compile_seconds, "final": run.final,
                                     "checkpoints": [asdict(c) for c in run.checkpoints],
                                     "mean_final_relmse": finals[run.method],
                                     "seeds": [{"final": x.final, "checkpoints": [asdict(c) for c in x.checkpoints]}
                                               for x in r.all_runs(run.method)[1:]]} for run in r.runs},
            "time_to_error_ratios": ratios,
        }
    return {"settings": settings, "machine": environment(), "scenes": scenes,
            "claims": [{"scene": c.scene, "statement": c.statement, "passed": c.passed, "detail": c.detail}
                       for c in claims]}


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    return str(value)


def _finite(value: Any) -> Any:
    """NaN/inf (not JSON) as None, recursively."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_finite(v) for v in value]
    return value


# --- command line --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="segmitsuba bench equal-time", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--time", type=float, default=None, metavar="SECONDS",
                    help=f"render time per method and scene (default {DEFAULT_TIME:g})")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_TIME:g} s per method (unless --time is given)")
    ap.add_argument("--res", type=int, default=BENCHMARK_RES,
                    help=f"image side; a stored reference must exist at it (default {BENCHMARK_RES})")
    ap.add_argument("--scenes", default=",".join(BENCHMARK_SCENES),
                    help=f"comma-separated scenes (default {','.join(BENCHMARK_SCENES)})")
    ap.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated (default {','.join(METHODS)}); "
                    "plugin[key=value,...] sets properties, e.g. segment_bdf[glossy_vertices=filtered]")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"output folder (default {DEFAULT_OUT})")
    ap.add_argument("--seed", type=int, default=0, help="seed of every method's first pass (default 0)")
    ap.add_argument("--seeds", type=int, default=1,
                    help="runs per method, seeds --seed, --seed + 1, ...: relMSE at T is their mean and the ratios "
                         "use the mean error curves (heavy-tailed scenes such as caustic vary several-fold "
                         "between single runs; default 1)")
    ap.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    ap.add_argument("-q", "--quiet", action="store_true", help="no per-pass progress on stderr")
    return ap


def run(args: list[str] | None = None) -> str:
    """Run the benchmark (command-line ``args``), write its outputs and return its report."""
    import mitsuba as mi

    a = _parser().parse_args(args)
    budget = a.time if a.time is not None else QUICK_TIME if a.quick else DEFAULT_TIME
    if not budget > 0:
        raise ValueError(f"--time must be > 0 seconds, got {budget}")
    if a.seeds < 1:
        raise ValueError(f"--seeds must be >= 1, got {a.seeds}")
    stems = [scene_stem(s.strip()) for s in a.scenes.split(",") if s.strip()]
    methods = split_methods(a.methods)
    for m in methods:
        parse_method(m)  # a malformed spec fails before anything renders
    if not stems or not methods:
        raise ValueError("--scenes and --methods must name at least one each")
    for stem in stems:  # fail on a missing or stale reference before rendering anything
        reference_for(stem, a.res)
    mi.set_variant(a.variant)
    say = None if a.quiet else (lambda m: print(m, file=sys.stderr, flush=True))
    a.out.mkdir(parents=True, exist_ok=True)

    t0 = time.perf_counter()
    results = [run_scene(stem, methods, budget, a.res, a.seed, say, a.seeds) for stem in stems]
    claims = evaluate_claims({r.scene: r.final_errors() for r in results})

    import drjit as dr

    settings = {"scenes": stems, "methods": methods, "time_budget": budget, "res": a.res,
                "max_depth": DEFAULT_MAX_DEPTH, "seed": a.seed, "seeds": a.seeds, "threads": dr.thread_count(),
                "command": " ".join(["segmitsuba bench equal-time", *(args if args is not None else sys.argv[1:])]),
                "date": time.strftime("%Y-%m-%d %H:%M:%S"),
                "timing": "render seconds: sum of the passes (dr.sync_thread), metrics and JIT compilation excluded",
                "ratio": "T_P(e_P) / T_M(e_P), e_P the peer's relMSE at the time budget, T_X(e) the first time the "
                         "running minimum of X's checkpoint errors reaches e (log-log interpolation)"}
    paths = []
    for r in results:
        paths.append(a.out / f"error_vs_time_{r.scene}.png")
        plot_scene(r, paths[-1])
    paths.append(a.out / "results.json")
    paths[-1].write_text(json.dumps(_finite(results_json(results, claims, settings)), indent=2,
                                    default=_json_default))

    lines = [f"equal-time benchmark: {len(stems)} scene(s) x {len(methods)} method(s) x {budget:g} s"
             + (f" x {a.seeds} seeds" if a.seeds > 1 else "") + " at "
             f"{a.res}x{a.res}, {dr.thread_count()} threads, variant {mi.variant()}", ""]
    for r in results:
        lines += [scene_table(r), ""]
    lines += ["claims (relMSE at T):", *(f"  {c}" for c in claims), ""]
    lines += [f"wrote {p}" for p in paths]
    lines.append(f"total {time.perf_counter() - t0:.0f} s")
    return "\n".join(lines)


def main() -> None:
    print(run(), flush=True)


if __name__ == "__main__":
    main()
