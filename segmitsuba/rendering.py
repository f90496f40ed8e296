"""Progressive rendering in passes: the loop behind ``segmitsuba render``, for scripts and notebooks too.

A render is split into passes of ``mi.render`` calls, each with its own seed; the result is the exact
sample-weighted average of the passes. Passes bound the memory of a wavefront (one lane per sample), show
progress, let a time budget be honoured, and let Ctrl-C keep the passes finished so far.

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

#: samples (image pixels x spp) per pass in spp mode: bounds a pass's wavefront memory (one lane per sample)
#: and keeps passes short enough for progress and Ctrl-C
PASS_SAMPLES = 2**20
#: time mode: a pass aims at this fraction of the budget (so Ctrl-C and the budget act promptly) ...
PASS_FRACTION = 1 / 10
#: ... within these bounds, in seconds
PASS_SECONDS = (0.25, 10.0)


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


@dataclass
class RenderResult:
    """A finished (or interrupted) render: the sample-weighted average of its passes."""

    image: np.ndarray  #: H x W x C float32
    channels: list[str]  #: names of the C channels, as the film develops them (R, G, B[, A], AOVs...)
    spp: int  #: samples per pixel in the image (sum over passes)
    passes: int
    seconds: float  #: wall time of the passes (JIT compilation included)
    interrupted: bool  #: stopped by Ctrl-C before the planned spp / time budget was reached
    stop_reason: str  #: "spp", "time" or "interrupt"
    seeds: list[int] = field(default_factory=list)  #: seed of each pass
    pass_spp: list[int] = field(default_factory=list)  #: spp of each pass
    pass_seconds: list[float] = field(default_factory=list)


def average(acc: np.ndarray, samples: int, channels: list[str]) -> dict[str, Any]:
    """The image and channel names of a sample-weighted sum of passes (fields of :class:`RenderResult`)."""
    return {"image": (acc / samples).astype(np.float32),
            "channels": channels if len(channels) == acc.shape[2] else default_channels(acc.shape[2])}


def pass_seed(seed: int, index: int) -> int:
    """Seed of pass ``index``: pass 0 uses ``seed`` itself (a one-pass render equals ``mi.render(seed=seed)``),
    later passes a 32-bit hash of (seed, index) so that runs with nearby seeds do not share passes."""
    if index == 0:
        return seed & 0xFFFFFFFF
    h = (seed * 0x9E3779B1 + index * 0x85EBCA77 + 0x165667B1) & 0xFFFFFFFF
    h ^= h >> 16
    h = (h * 0x85EBCA6B) & 0xFFFFFFFF
    h ^= h >> 13
    h = (h * 0xC2B2AE35) & 0xFFFFFFFF
    return h ^ (h >> 16)


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
    if not enabled or threading.current_thread() is not threading.main_thread():
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
) -> RenderResult:
    """Render ``scene`` in passes and return the sample-weighted average of the finished passes.

    - ``spp`` only: exactly ``spp`` samples per pixel, split into ``passes`` passes, or passes of at most
      ``pass_spp``, or (default) passes of at most :data:`PASS_SAMPLES` samples. Reproducible for a seed.
    - ``time_budget`` (seconds): passes until the next one would overrun the budget; pass sizes adapt to the
      measured speed (the last pass shrinks to fit), so the render ends within about 10% + one pass of the
      budget. With ``spp`` too, it also stops there. Always at least one pass.
    - neither: the sensor's sampler sample count, as ``mi.render`` does.

    Samplers that round sample counts (``stratified``: squares, ...) take more samples per pass than asked;
    the average is weighted by, and ``spp`` counts, the samples really taken.

    ``integrator`` defaults to the scene's. Ctrl-C (when ``handle_sigint`` and in the main thread) stops after
    the running pass and returns what is finished with ``interrupted=True``; a second Ctrl-C, or Ctrl-C before
    any pass has finished, raises KeyboardInterrupt. ``progress`` prints per-pass progress to stderr;
    ``callback`` gets a :class:`PassReport` after each pass.
    """
    import drjit as dr  # noqa: F401  (after segmitsuba has configured libLLVM)
    import mitsuba as mi

    if spp is not None and spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if pass_spp is not None and pass_spp < 1:
        raise ValueError(f"pass_spp must be >= 1, got {pass_spp}")
    if integrator is None:
        integrator = scene.integrator()
    sensor_obj = scene.sensors()[sensor] if isinstance(sensor, int) else sensor
    pixels = _film_pixels(sensor_obj)
    max_pass_spp = pass_spp if pass_spp is not None else max(1, PASS_SAMPLES // max(1, pixels))
    if spp is None and time_budget is None:
        spp = int(sensor_obj.sampler().sample_count())

    plan: list[int] | None = None
    if time_budget is None:
        plan = plan_passes(spp, pixels, passes, pass_spp)
        target_pass_seconds = 0.0
    else:
        target_pass_seconds = min(max(time_budget * PASS_FRACTION, PASS_SECONDS[0]), PASS_SECONDS[1])

    reporter = _Progress(progress, spp, time_budget, desc="render ")
    interrupt = _Interrupt(reporter.message)

    acc: np.ndarray | None = None
    channels: list[str] = []
    from_bitmap = False
    seeds: list[int] = []
    sizes: list[int] = []
    durations: list[float] = []
    done = 0
    wall = 0.0
    stop_reason = "spp"
    start = time.perf_counter()

    counts: dict[int, int] = {}

    def effective(n: int) -> int:
        if n not in counts:
            counts[n] = sampler_spp(sensor_obj, n)
        return counts[n]

    def next_pass_spp(index: int, elapsed: float) -> int:
        """Size of pass ``index``, or 0 to stop."""
        if plan is not None:
            return plan[index] if index < len(plan) else 0
        left = spp - done if spp is not None else None
        if left is not None and left <= 0:
            return 0
        if index == 0:  # calibrate with a small pass: it also pays for JIT compilation
            n = max(1, min(max_pass_spp, 2**16 // max(1, pixels)))
        else:
            # seconds per spp: the first pass includes compilation, so prefer the ones after it
            tail = slice(1, None) if len(sizes) > 1 else slice(0, None)
            rate = sum(durations[tail]) / sum(sizes[tail])
            remaining = time_budget - elapsed
            n = min(int(target_pass_seconds / rate), max_pass_spp)
            fit = int(remaining / rate)
            if fit < 1:
                return 0
            n = max(1, min(n, fit))
        return min(n, left) if left is not None else n

    try:
        with _sigint(interrupt, handle_sigint):
            index = 0
            while True:
                elapsed = time.perf_counter() - start
                n = next_pass_spp(index, elapsed)
                if n == 0:
                    stop_reason = "spp" if plan is not None or (spp is not None and done >= spp) else "time"
                    break
                s = pass_seed(seed, index)
                t0 = time.perf_counter()
                tensor = mi.render(scene, integrator=integrator, sensor=sensor, spp=n, seed=s)
                img = np.array(tensor, dtype=np.float64)
                n = effective(n)  # the samples the pass really took (weights the average)
                if index == 0:
                    # channel names of the developed film; with nested AOV integrators mi.render's tensor
                    # drops channels that the film's bitmap keeps, so then take the bitmap itself
                    bitmap = sensor_obj.film().bitmap()
                    channels = [f.name for f in bitmap.struct_()]
                    from_bitmap = len(channels) != (img.shape[2] if img.ndim == 3 else 1)
                if from_bitmap:
                    img = np.array(sensor_obj.film().bitmap(), dtype=np.float64)
                if img.ndim == 2:
                    img = img[..., None]
                t1 = time.perf_counter()
                # commit in one statement, so that a second Ctrl-C cannot leave the record half updated
                acc, done, seeds, sizes, durations, wall = (
                    img * n if acc is None else acc + img * n, done + n,
                    [*seeds, s], [*sizes, n], [*durations, t1 - t0], t1 - start,
                )
                elapsed = wall
                rate = sum(durations[1:]) / sum(sizes[1:]) if len(sizes) > 1 else durations[0] / sizes[0]
                if plan is not None:
                    eta = rate * max(0, sum(plan[index + 1:]))
                else:
                    eta = max(0.0, time_budget - elapsed)
                    if spp is not None:
                        eta = min(eta, rate * max(0, spp - done))
                report = PassReport(index, n, t1 - t0, done, elapsed, spp, time_budget,
                                    len(plan) if plan is not None else None, eta)
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
        **average(acc, done, channels),
        spp=done,
        passes=len(sizes),
        seconds=wall,
        interrupted=stop_reason == "interrupt",
        stop_reason=stop_reason,
        seeds=seeds,
        pass_spp=sizes,
        pass_seconds=durations,
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
