"""The pass engine: every way of rendering (``segmitsuba render``, ``compare``, references, benchmarks,
notebooks, Dask tasks) renders through it.

A render is split into passes of ``mi.render`` calls; the result is the exact sample-weighted average of the
passes. Passes bound the memory of a wavefront (one lane per sample), show progress, let a time budget be
honoured, and let Ctrl-C keep the passes finished so far. Each pass knows its place in the whole render
(:class:`Pass`: its global index, its seed ``pass_seed(seed, index)`` and the samples per pixel before it), and
:class:`PassRenderer` tells the integrator, so that a filter's kernel follows the render rather than the call
(:mod:`segmitsuba.schedule`).

    import segmitsuba
    import mitsuba as mi
    from segmitsuba.rendering import render_passes

    mi.set_variant("llvm_ad_rgb")
    scene = mi.load_dict(mi.cornell_box())
    result = render_passes(scene, mi.load_dict({"type": "segment_pt"}), time_budget=10)
    print(result.spp, result.passes, result.image.shape)
"""

from __future__ import annotations

import math
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .imageio import default_channels
from .schedule import pass_seed

#: samples (image pixels x spp) per pass in spp mode: bounds a pass's wavefront memory (one lane per sample)
#: and keeps passes short enough for progress and Ctrl-C
PASS_SAMPLES = 2**20
#: time mode: a pass aims at this fraction of the budget (so Ctrl-C and the budget act promptly) ...
PASS_FRACTION = 1 / 10
#: ... within these bounds, in seconds
PASS_SECONDS = (0.25, 10.0)
#: seed of the untimed warm-up pass (outside any render's passes)
WARMUP_SEED = 0xFFFFFFF0


@dataclass(frozen=True)
class Pass:
    """One pass of a render: where it lies in the whole render, wherever it is rendered."""

    index: int  #: global 0-based index in the render
    spp: int  #: samples per pixel asked for
    spp_offset: int  #: samples per pixel of the passes before it (asked for, in index order)
    seed: int  #: ``pass_seed(render seed, index)``
    render_seed: int | None = None  #: the render's seed (None: a pass outside any render)

    @classmethod
    def of(cls, seed: int, index: int, spp: int, spp_offset: int) -> Pass:
        return cls(index, spp, spp_offset, pass_seed(seed, index), seed)


def pass_offsets(sizes: list[int]) -> list[int]:
    """Samples per pixel before each pass of a plan."""
    return [sum(sizes[:i]) for i in range(len(sizes))]


@dataclass
class PassReport:
    """What the progress callback gets after each finished pass."""

    index: int  #: 0-based index of the pass just finished
    pass_spp: int  #: samples per pixel of that pass
    pass_seconds: float
    spp: int  #: samples per pixel finished so far
    seconds: float  #: time since the render started
    target_spp: int | None  #: the spp aimed at, if any
    time_budget: float | None
    planned_passes: int | None  #: total passes when known in advance (spp mode)
    eta: float | None  #: estimated seconds left
    #: the running image (the average of the passes so far, H x W x C), computed when called
    image: Callable[[], np.ndarray] | None = None


@dataclass
class RenderResult:
    """A finished (or interrupted) render: the sample-weighted average of its passes."""

    image: np.ndarray  #: H x W x C float32
    channels: list[str]  #: names of the C channels, as the film develops them (R, G, B[, A], AOVs...)
    spp: int  #: samples per pixel in the image (sum over passes)
    passes: int
    seconds: float  #: rendering time: the passes' synchronized times (JIT compilation included)
    interrupted: bool  #: stopped by Ctrl-C before the planned spp / time budget was reached
    stop_reason: str  #: "spp", "time" or "interrupt"
    seeds: list[int] = field(default_factory=list)  #: seed of each pass
    pass_spp: list[int] = field(default_factory=list)  #: spp of each pass
    pass_seconds: list[float] = field(default_factory=list)
    #: the integrator's pools, for filters (``last_stats["pools"]`` of every pass: spp offset, spp, seed,
    #: kernel size), in render order
    pools: list[dict[str, Any]] = field(default_factory=list)
    warmup_seconds: float = 0.0  #: the untimed warm-up pass (0 without one)


def average(acc: np.ndarray, samples: int, channels: list[str]) -> dict[str, Any]:
    """The image and channel names of a sample-weighted sum of passes (fields of :class:`RenderResult`)."""
    return {"image": (acc / samples).astype(np.float32),
            "channels": channels if len(channels) == acc.shape[2] else default_channels(acc.shape[2])}


def plan_passes(spp: int, pixels: int, passes: int | None = None, pass_spp: int | None = None) -> list[int]:
    """Split ``spp`` into balanced passes: ``passes`` of them, or passes of at most ``pass_spp``, or (default)
    passes of at most :data:`PASS_SAMPLES` samples. Deterministic, so a seed reproduces the image."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if passes is None:
        cap = pass_spp if pass_spp is not None else max(1, PASS_SAMPLES // max(1, pixels))
        if cap < 1:
            raise ValueError(f"pass_spp must be >= 1, got {cap}")
        passes = math.ceil(spp / cap)
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes}")
    passes = min(passes, spp)
    base, extra = divmod(spp, passes)
    return [base + (1 if i < extra else 0) for i in range(passes)]


class _Interrupt:
    """SIGINT while rendering: the first Ctrl-C asks to stop after the running pass (a pass cannot be cut
    short: Dr.Jit runs it in native code and Python only sees the signal when it returns); a second one
    raises KeyboardInterrupt."""

    def __init__(self, message: Callable[[str], None]):
        self.requested = False
        self._message = message

    def __call__(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        self._message("interrupt: stopping after the current pass (Ctrl-C again to stop at once)")


@contextmanager
def _sigint(handler: _Interrupt, enabled: bool) -> Iterator[None]:
    # a process that ignores SIGINT (nohup, a shell's background job) keeps ignoring it, as Python does
    if (not enabled or threading.current_thread() is not threading.main_thread()
            or signal.getsignal(signal.SIGINT) is signal.SIG_IGN):
        yield
        return
    previous = signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


class _Progress:
    """Per-pass progress on stderr: a tqdm bar on a terminal, one line per pass otherwise (logs, pipes)."""

    def __init__(self, enabled: bool, target_spp: int | None, time_budget: float | None, desc: str):
        self.enabled = enabled
        self.bar = None
        self.time_mode = time_budget is not None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            if self.time_mode:
                fmt = "{desc}{percentage:3.0f}%|{bar}| {n:.1f}/{total:.1f} s [{elapsed}<{remaining}{postfix}]"
                self.bar = tqdm(total=time_budget, desc=desc, bar_format=fmt, file=sys.stderr, leave=True)
            else:
                fmt = "{desc}{percentage:3.0f}%|{bar}| {n}/{total} spp [{elapsed}<{remaining}{postfix}]"
                self.bar = tqdm(total=target_spp, desc=desc, bar_format=fmt, file=sys.stderr, leave=True)

    def message(self, text: str) -> None:
        if self.bar is not None:
            self.bar.write(text, file=sys.stderr)
        else:
            print(text, file=sys.stderr, flush=True)

    def update(self, r: PassReport) -> None:
        planned = f"/{r.planned_passes}" if r.planned_passes else ""
        self.show(r.pass_spp, r.spp, r.seconds, r.target_spp, r.time_budget, r.eta, f"pass {r.index + 1}",
                  f"pass {r.index + 1}{planned}", f"pass {r.pass_spp} spp in {r.pass_seconds:.2f} s")

    def show(self, step_spp: int, spp: int, seconds: float, target_spp: int | None, time_budget: float | None,
             eta: float | None, short: str, counter: str, detail: str) -> None:
        """One step (a pass, or a distributed task) finished: ``short`` labels the bar's postfix, ``counter``
        and ``detail`` the line printed when there is no terminal."""
        if not self.enabled:
            return
        if self.bar is not None:
            if self.time_mode:
                self.bar.update(min(seconds, self.bar.total) - self.bar.n)
                self.bar.set_postfix_str(f"{short}, {spp} spp", refresh=True)
            else:
                self.bar.update(step_spp)
                self.bar.set_postfix_str(counter, refresh=True)
            return
        done = f"{spp}" + (f"/{target_spp}" if target_spp and not time_budget else "") + " spp"
        elapsed = f"{seconds:.1f}" + (f"/{time_budget:g}" if time_budget else "") + " s"
        left = f", ETA {eta:.1f} s" if eta is not None else ""
        self.message(f"{counter}: {done}, {elapsed} ({detail}){left}")

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _film_pixels(sensor: Any) -> int:
    film = sensor.film()
    size = film.crop_size()
    return int(size[0]) * int(size[1])


def sampler_spp(sensor: Any, n: int) -> int:
    """Samples per pixel a pass asking for ``n`` really takes: samplers may round the count (stratified: the
    next square, multijitter, ...), so ask a clone of the sensor's sampler."""
    try:
        probe = sensor.sampler().clone()
        probe.set_sample_count(n)
        return int(probe.sample_count())
    except Exception:
        return n


class PassRenderer:
    """Renders passes of one render of ``scene`` with ``integrator``: one ``mi.render`` call per :class:`Pass`,
    with the pass's seed, after telling an integrator whose kernel follows the render (it has ``spp_offset``:
    segmitsuba's filters) where the pass lies. Returns float64 images with the film's channels."""

    def __init__(self, scene: Any, integrator: Any, sensor: int | Any = 0):
        self.scene = scene
        self.integrator = integrator
        self.sensor = sensor
        self.sensor_obj = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
        self.follows_render = hasattr(integrator, "spp_offset")
        self.channels: list[str] | None = None
        self._from_bitmap = False
        self._counts: dict[int, int] = {}

    def effective_spp(self, n: int) -> int:
        """Samples a pass asking for ``n`` really takes (:func:`sampler_spp`), cached."""
        if n not in self._counts:
            self._counts[n] = sampler_spp(self.sensor_obj, n)
        return self._counts[n]

    def render(self, p: Pass) -> tuple[np.ndarray, int, float, list[dict[str, Any]]]:
        """``(image H x W x C, samples per pixel really taken, seconds, pools)`` of pass ``p``; the seconds are
        synchronized (``dr.sync_thread``) and include the image's transfer to NumPy."""
        import drjit as dr
        import mitsuba as mi

        previous = (self.integrator.spp_offset, getattr(self.integrator, "render_seed", None)) \
            if self.follows_render else None
        dr.sync_thread()
        t0 = time.perf_counter()
        try:
            if self.follows_render:
                self.integrator.spp_offset = p.spp_offset
                self.integrator.render_seed = p.render_seed
            tensor = mi.render(self.scene, integrator=self.integrator, sensor=self.sensor, spp=p.spp, seed=p.seed)
            img = np.array(tensor, dtype=np.float64)
        finally:
            if self.follows_render:
                self.integrator.spp_offset, self.integrator.render_seed = previous
        if self.channels is None:
            # channel names of the developed film; with nested AOV integrators mi.render's tensor drops
            # channels that the film's bitmap keeps, so then take the bitmap itself
            self.channels = [f.name for f in self.sensor_obj.film().bitmap().struct_()]
            self._from_bitmap = len(self.channels) != (img.shape[2] if img.ndim == 3 else 1)
        if self._from_bitmap:
            img = np.array(self.sensor_obj.film().bitmap(), dtype=np.float64)
        if img.ndim == 2:
            img = img[..., None]
        seconds = time.perf_counter() - t0
        pools = list(getattr(self.integrator, "last_stats", {}).get("pools", [])) if self.follows_render else []
        return img, self.effective_spp(p.spp), seconds, pools

    def warm_up(self) -> float:
        """One untimed 1-spp pass outside the render (it pays for JIT compilation); returns its seconds."""
        _img, _n, seconds, _pools = self.render(Pass(0, 1, 0, WARMUP_SEED))
        self.channels = None
        return seconds


def render_passes(
    scene: Any,
    integrator: Any = None,
    spp: int | None = None,
    time_budget: float | None = None,
    passes: int | None = None,
    pass_spp: int | None = None,
    seed: int = 0,
    sensor: int | Any = 0,
    progress: bool = True,
    callback: Callable[[PassReport], None] | None = None,
    handle_sigint: bool = True,
    growth: str = "even",
    warmup: bool = False,
) -> RenderResult:
    """Render ``scene`` in passes and return the sample-weighted average of the finished passes.

    - ``spp`` only: exactly ``spp`` samples per pixel, split into ``passes`` passes, or passes of at most
      ``pass_spp``, or (default) passes of at most :data:`PASS_SAMPLES` samples. Reproducible for a seed.
    - ``time_budget`` (seconds of rendering: the passes' synchronized times, callbacks not counted): passes
      until the next one would overrun the budget, sized from the measured speed (the last pass shrinks to
      fit), so the render ends within about 10% + one pass of the budget. ``growth="even"``: a small
      calibration pass, then passes of about a tenth of the budget; ``"doubling"``: each pass doubles the spp
      so far (1, 1, 2, 4, ... spp: checkpoints evenly spread on a log time axis, for ``compare``). With
      ``spp`` too, it also stops there. Always at least one pass.
    - neither: the sensor's sampler sample count, as ``mi.render`` does.

    Pass ``i`` has seed ``pass_seed(seed, i)`` and is told the spp before it (:class:`PassRenderer`), so a
    filter's kernel schedule is that of the whole render however it is split. Samplers that round sample
    counts (``stratified``: squares, ...) take more samples per pass than asked; the average is weighted by,
    and ``spp`` counts, the samples really taken. ``warmup`` renders one untimed 1-spp pass first (not in the
    image), so that JIT compilation is not counted.

    ``integrator`` defaults to the scene's. Ctrl-C (when ``handle_sigint`` and in the main thread) stops after
    the running pass and returns what is finished with ``interrupted=True``; a second Ctrl-C, or Ctrl-C before
    any pass has finished, raises KeyboardInterrupt. ``progress`` prints per-pass progress to stderr;
    ``callback`` gets a :class:`PassReport` after each pass.
    """
    import drjit as dr  # noqa: F401  (after segmitsuba has configured libLLVM)

    if spp is not None and spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if pass_spp is not None and pass_spp < 1:
        raise ValueError(f"pass_spp must be >= 1, got {pass_spp}")
    if growth not in ("even", "doubling"):
        raise ValueError(f"growth must be 'even' or 'doubling', got {growth!r}")
    if integrator is None:
        integrator = scene.integrator()
    renderer = PassRenderer(scene, integrator, sensor)
    pixels = _film_pixels(renderer.sensor_obj)
    max_pass_spp = pass_spp if pass_spp is not None else max(1, PASS_SAMPLES // max(1, pixels))
    if spp is None and time_budget is None:
        spp = int(renderer.sensor_obj.sampler().sample_count())

    plan: list[int] | None = None
    if time_budget is None:
        plan = plan_passes(spp, pixels, passes, pass_spp)
        target_pass_seconds = 0.0
    else:
        target_pass_seconds = min(max(time_budget * PASS_FRACTION, PASS_SECONDS[0]), PASS_SECONDS[1])

    reporter = _Progress(progress, spp, time_budget, desc="render ")
    interrupt = _Interrupt(reporter.message)

    acc: np.ndarray | None = None
    seeds: list[int] = []
    sizes: list[int] = []
    durations: list[float] = []
    pools: list[dict[str, Any]] = []
    done = 0  # samples per pixel taken
    asked = 0  # samples per pixel asked for: the spp offset of the next pass
    rendered = 0.0  # seconds of rendering
    stop_reason = "spp"
    warmup_seconds = renderer.warm_up() if warmup else 0.0

    def rate() -> float:
        """Seconds per spp for sizing the next pass: the last pass (the most like the next one), or the mean
        of the passes after the first (which pays for compilation) if that is slower, so that noise on a shared
        machine does not overrun the budget."""
        last = durations[-1] / sizes[-1]
        return max(last, sum(durations[1:]) / sum(sizes[1:])) if len(sizes) > 1 else last

    def next_pass_spp(index: int) -> int:
        """Size of pass ``index``, or 0 to stop."""
        if plan is not None:
            return plan[index] if index < len(plan) else 0
        left = spp - done if spp is not None else None
        if left is not None and left <= 0:
            return 0
        if index == 0:  # calibrate with a small pass: it also pays for JIT compilation without warm-up
            n = 1 if growth == "doubling" else max(1, min(max_pass_spp, 2**16 // max(1, pixels)))
        else:
            if rendered >= time_budget:
                return 0
            per_spp = rate()
            wanted = max(done, 1) if growth == "doubling" else int(target_pass_seconds / per_spp)
            fit = int((time_budget - rendered) / per_spp)
            if fit < 1:
                return 0
            n = max(1, min(wanted, max_pass_spp, fit))
        return min(n, left) if left is not None else n

    try:
        with _sigint(interrupt, handle_sigint):
            index = 0
            while True:
                n = next_pass_spp(index)
                if n == 0:
                    stop_reason = "spp" if plan is not None or (spp is not None and done >= spp) else "time"
                    break
                p = Pass.of(seed, index, n, asked)
                img, n_real, seconds, pass_pools = renderer.render(p)
                # commit in one statement, so that a second Ctrl-C cannot leave the record half updated
                acc, done, asked, seeds, sizes, durations, pools, rendered = (
                    img * n_real if acc is None else acc + img * n_real, done + n_real, asked + n,
                    [*seeds, p.seed], [*sizes, n_real], [*durations, seconds], [*pools, *pass_pools],
                    rendered + seconds,
                )
                if plan is not None:
                    eta = rate() * max(0, sum(plan[index + 1:]))
                else:
                    eta = max(0.0, time_budget - rendered)
                    if spp is not None:
                        eta = min(eta, rate() * max(0, spp - done))
                total, count = acc, done
                report = PassReport(index, n_real, seconds, done, rendered, spp, time_budget,
                                    len(plan) if plan is not None else None, eta,
                                    image=lambda total=total, count=count: total / count)
                reporter.update(report)
                if callback is not None:
                    callback(report)
                index += 1
                if interrupt.requested:
                    stop_reason = "interrupt"
                    break
    except KeyboardInterrupt:
        if acc is None:
            raise
        stop_reason = "interrupt"
    finally:
        reporter.close()

    if acc is None:  # cannot happen: every mode renders at least one pass
        raise RuntimeError("render_passes: no pass was rendered")
    return RenderResult(
        **average(acc, done, renderer.channels or []),
        spp=done,
        passes=len(sizes),
        seconds=rendered,
        interrupted=stop_reason == "interrupt",
        stop_reason=stop_reason,
        seeds=seeds,
        pass_spp=sizes,
        pass_seconds=durations,
        pools=pools,
        warmup_seconds=warmup_seconds,
    )


def environment() -> dict[str, Any]:
    """Versions and backend of this process: package versions, variant, libLLVM, threads."""
    import drjit as dr
    import mitsuba as mi

    from . import __version__

    env: dict[str, Any] = {
        "segmitsuba_version": __version__,
        "mitsuba_version": mi.__version__,
        "drjit_version": dr.__version__,
        "python_version": sys.version.split()[0],
        "variant": mi.variant() or "",
        "threads": int(dr.thread_count()),
    }
    if dr.has_backend(dr.JitBackend.LLVM):
        env["llvm_version"] = ".".join(str(v) for v in dr.detail.llvm_version())
    env["libllvm_path"] = os.environ.get("DRJIT_LIBLLVM_PATH", "")
    return env
