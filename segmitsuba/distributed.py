"""Render passes on a Dask cluster: ``segmitsuba render --workers N`` / ``--scheduler ADDRESS``, for scripts too.

Passes are independent given their seeds, so a render is an embarrassingly parallel set of passes whose images
average exactly. :func:`render_distributed` plans the passes as :func:`~segmitsuba.rendering.render_passes`
does (pass ``i`` has seed ``pass_seed(seed, i)``), groups contiguous passes into Dask tasks, and merges the
tasks' sample-weighted sums into the same :class:`~segmitsuba.rendering.RenderResult`:

    import segmitsuba
    from segmitsuba.distributed import render_distributed

    result = render_distributed("scenes/cornell.xml", {"type": "segment_pt"}, spp=256, workers=2)
    result = render_distributed("scenes/cornell.xml", "segment_bdf", time_budget=60,
                                scheduler="tcp://head-node:8786", defines={"res": "512"})

- The scene is shipped, not shared: the XML, its ``<include>``s and every file it references (``filename``
  properties, resolved as Mitsuba does: the scene's folder first) are read on the client, sent once to every
  worker (``client.scatter(broadcast=True)``), written to a temporary folder there and loaded; each worker
  process keeps the loaded scene (and its compiled kernels) for the following tasks. A scene dict (such as
  ``mi.cornell_box()``) is shipped as a dict, its transforms and files included.
- Workers set themselves up: importing this module imports segmitsuba first (libLLVM), then each task sets the
  variant and, if asked, Dr.Jit's thread count.
- A worker that dies loses nothing: Dask re-runs its tasks elsewhere, and the client takes each task's result
  exactly once, so every pass is counted once. Exceptions are retried (``retries``) on other workers.
- A time budget stops submitting tasks that would end after it, and keeps what finished.

Dask (``distributed``) is an optional dependency: ``pip install 'segmitsuba[distributed]'``.
"""

from __future__ import annotations

import atexit
import hashlib
import logging
import math
import os
import pickle
import re
import shutil
import tempfile
import threading
import time
import uuid
import xml.etree.ElementTree as ET
from collections import OrderedDict
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from .rendering import (
    PASS_FRACTION,
    PASS_SAMPLES,
    PASS_SECONDS,
    Pass,
    PassRenderer,
    RenderResult,
    _Interrupt,
    _Progress,
    _sigint,
    average,
    pass_offsets,
    plan_passes,
)

DEFAULT_VARIANT = "llvm_ad_rgb"
INSTALL_HINT = "pip install 'segmitsuba[distributed]'"
#: tasks kept in flight per worker process (one renders, the next waits on the worker: no idle gap)
TASKS_IN_FLIGHT = 2
#: spp mode: aim at this many tasks per worker process (load balance, progress, little work lost on a failure)
TASKS_PER_WORKER = 4
#: ... but at most this many passes per task
MAX_TASK_PASSES = 8
#: how often the client wakes up to check the time budget and Ctrl-C, in seconds
POLL_SECONDS = 0.2


class DistributedError(RuntimeError):
    """A distributed render failed: a task raised (after its retries), or the workers cannot load the scene."""


def require_distributed() -> Any:
    """The ``distributed`` module, or an ImportError that says how to install it."""
    try:
        import distributed
    except ImportError as e:
        raise ImportError(
            f"distributed rendering needs Dask's 'distributed' package ({e}): {INSTALL_HINT}"
        ) from None
    return distributed


# --- shipping the scene ----------------------------------------------------------------------------------


@dataclass
class SceneBundle:
    """A scene as bytes: the XML files and everything they reference, or a scene dict, ready to ship."""

    name: str  #: how reports name the scene (the client-side path, or "dict")
    digest: str  #: content hash: workers cache the loaded scene under it
    main: str = ""  #: XML scenes: the scene file, relative to the bundle's root
    files: dict[str, bytes] = field(default_factory=dict)  #: relative POSIX path -> content
    scene_dict: Any = None  #: dict scenes: the encoded dict (see :func:`_encode`)
    defines: dict[str, str] = field(default_factory=dict)  #: scene parameters to load the XML with

    @property
    def size(self) -> int:
        return sum(len(b) for b in self.files.values())


@dataclass(frozen=True)
class _MiValue:
    """A Mitsuba value of a scene dict (transform, point, colour...) in a picklable form."""

    type_name: str
    data: Any


@dataclass(frozen=True)
class _FileRef:
    """A file of a scene dict, by its path in the bundle."""

    path: str


_PARAM = re.compile(r"\$(\w+)")


def _substitute(text: str, params: Mapping[str, str]) -> str:
    """Mitsuba's ``$name`` substitution (longest names first, so that $res does not eat $resolution)."""
    for name in sorted(params, key=len, reverse=True):
        text = text.replace(f"${name}", str(params[name]))
    return text


def _file_attributes(el: ET.Element) -> list[str]:
    """Attributes of an XML element that name a file: ``filename="..."`` (include, spectrum) or the value of
    a ``<string name="filename" .../>`` property (bitmap, envmap, meshes, volumes...)."""
    attrs = ["filename"] if "filename" in el.attrib else []
    if el.tag == "string" and el.get("name", "").endswith("filename") and "value" in el.attrib:
        attrs.append("value")
    return attrs


def _digest(files: Mapping[str, bytes], *extra: Any) -> str:
    h = hashlib.sha256()
    for path in sorted(files):
        h.update(path.encode() + b"\0" + hashlib.sha256(files[path]).digest())
    h.update(repr(extra).encode())
    return h.hexdigest()


def package_scene(
    scene: str | os.PathLike | Mapping[str, Any], defines: Mapping[str, Any] | None = None
) -> SceneBundle:
    """Read a scene file and every file it needs (or encode a scene dict) into a :class:`SceneBundle`.

    References are resolved as Mitsuba does (after ``$name`` substitution with ``<default>``s and
    ``defines``): relative paths against the scene file's folder first (in ``<include>``d files too), then
    ``<path>`` folders and Mitsuba's file resolver (the current directory). The bundle puts each file where
    Mitsuba on the worker looks first (``<scene folder>/<relative path>``, ``..`` included); absolute paths
    are rewritten to relative ones in the shipped XML. Missing files raise FileNotFoundError here rather than
    on every worker.
    """
    defines = {str(k): str(v) for k, v in (defines or {}).items()}
    if isinstance(scene, Mapping):
        if defines:
            raise ValueError("defines apply to scene files, not to scene dicts")
        return _package_dict(scene)
    if _is_loaded_mitsuba_object(scene):
        raise TypeError("a loaded mi.Scene cannot be shipped to workers: pass the scene file or its dict")
    main = Path(scene).resolve()
    if not main.is_file():
        raise FileNotFoundError(f"scene file '{scene}' does not exist")
    main_dir = main.parent
    search: list[Path] = [main_dir]
    located: dict[Path, Path] = {main: main}  # where the worker will look (client-side path) -> file to read
    contents: dict[Path, bytes] = {}
    rewritten_params: set[str] = set()
    worker_defines = dict(defines)
    parsed: dict[Path, ET.ElementTree] = {}

    def parse(path: Path) -> ET.ElementTree:
        if path not in parsed:
            try:
                parsed[path] = ET.parse(path)
            except ET.ParseError as e:
                raise ValueError(f"cannot parse scene file '{path}': {e}") from None
        return parsed[path]

    # <default>s of every file apply (the first one wins, as in Mitsuba where a repeated default is an error)
    defaults: dict[str, str] = {}

    def resolve(value: str) -> Path | None:
        p = Path(value)
        if p.is_absolute():
            return p if p.is_file() else None
        for base in (*search, *_resolver_paths()):
            if (base / p).is_file():
                return (base / p).resolve()
        return None

    def visit(path: Path, stack: tuple[Path, ...]) -> None:
        if path in stack:
            raise ValueError(f"scene file '{path}' includes itself")
        if path in contents:  # included twice: done already
            return
        contents[path] = b""
        tree = parse(path)
        for el in tree.iter("default"):
            if el.get("name") is not None and el.get("value") is not None:
                defaults.setdefault(el.get("name"), el.get("value"))
        params = {**defaults, **defines}
        changed = False
        for el in tree.iter():
            if el.tag == "path" and el.get("value"):
                search.append((main_dir / _substitute(el.get("value"), params)).resolve())
                continue
            for attr in _file_attributes(el):
                raw = el.get(attr)
                value = _substitute(raw, params)
                if _PARAM.search(value):
                    raise ValueError(f"'{path}': file reference '{raw}' uses an undefined parameter")
                found = resolve(value)
                if found is None:
                    raise FileNotFoundError(f"'{path}' references '{value}', which does not exist (looked in "
                                            f"{main_dir} and the other Mitsuba search paths)")
                if Path(value).is_absolute():
                    # the worker has no such path: point to the shipped copy, relative to the scene's folder
                    el.set(attr, os.path.relpath(found, main_dir))
                    rewritten_params.update(_PARAM.findall(raw))
                    changed = True
                    target = found
                else:
                    target = Path(os.path.normpath(main_dir / value))  # where Mitsuba on the worker looks first
                located.setdefault(target, found)
                if el.tag == "include":
                    visit(found, (*stack, path))
        contents[path] = ET.tostring(tree.getroot(), encoding="utf-8", xml_declaration=True) if changed else b""

    visit(main, ())
    files_abs: dict[Path, bytes] = {}
    for target, source in located.items():
        data = contents.get(source, b"")
        files_abs[target] = data if data else source.read_bytes()
    if rewritten_params:
        texts = [b.decode("utf-8", "replace") for t, b in files_abs.items() if t.suffix.lower() == ".xml"]
        for name in rewritten_params:  # a define used only in a rewritten path: Mitsuba would call it unused
            if name in worker_defines and not any(f"${name}" in t for t in texts):
                del worker_defines[name]
    root = Path(os.path.commonpath([str(p.parent) for p in files_abs]))
    files = {PurePosixPath(*p.relative_to(root).parts).as_posix(): b for p, b in files_abs.items()}
    main_rel = PurePosixPath(*main.relative_to(root).parts).as_posix()
    return SceneBundle(name=str(main), digest=_digest(files, main_rel, sorted(worker_defines.items())),
                       main=main_rel, files=files, defines=worker_defines)


def _resolver_paths() -> list[Path]:
    """The folders of Mitsuba's file resolver (the current directory and Mitsuba's own data)."""
    try:
        import mitsuba as mi

        resolver = mi.file_resolver()
        return [Path(str(resolver[i])) for i in range(len(resolver))]
    except Exception:
        return [Path.cwd()]


def _is_loaded_mitsuba_object(value: Any) -> bool:
    module = type(value).__module__ or ""
    if not (module.startswith("mitsuba") or module.startswith("drjit")):
        return False
    import mitsuba as mi

    return isinstance(value, mi.Object)


def _package_dict(scene: Mapping[str, Any]) -> SceneBundle:
    files: dict[str, bytes] = {}
    by_source: dict[Path, str] = {}

    def ship(path: str) -> _FileRef:
        source = Path(path).resolve()
        if not source.is_file():
            raise FileNotFoundError(f"scene dict references '{path}', which does not exist")
        if source not in by_source:
            by_source[source] = f"{len(by_source)}/{source.name}"
            files[by_source[source]] = source.read_bytes()
        return _FileRef(by_source[source])

    encoded = _encode(scene, ship)
    return SceneBundle(name="dict", digest=_digest(files, pickle.dumps(encoded)), files=files, scene_dict=encoded)


def _encode(value: Any, ship: Callable[[str], _FileRef] | None = None, key: str = "") -> Any:
    """A scene or plugin dict made picklable: Mitsuba transforms/vectors/colours become :class:`_MiValue`,
    ``filename`` strings become shipped :class:`_FileRef`."""
    if isinstance(value, Mapping):
        return {k: _encode(v, ship, str(k)) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_encode(v, ship, key) for v in value)
    if isinstance(value, str):
        return ship(value) if ship is not None and key == "filename" else value
    if value is None or isinstance(value, (bool, int, float, np.ndarray, np.generic)):
        return value
    module = type(value).__module__ or ""
    if module.startswith("mitsuba") or module.startswith("drjit"):
        if _is_loaded_mitsuba_object(value):
            raise TypeError(f"scene dict entry '{key}' is a loaded {type(value).__name__}: it cannot be shipped to "
                            "workers; describe it as a dict")
        name = type(value).__name__
        if hasattr(value, "matrix"):
            return _MiValue(name, np.array(value.matrix, dtype=np.float64).tolist())
        return _MiValue(name, np.array(value, dtype=np.float64).tolist())
    try:
        pickle.dumps(value)
    except Exception as e:
        raise TypeError(f"scene dict entry '{key}' ({type(value).__name__}) cannot be shipped: {e}") from None
    return value


def _decode(value: Any, root: Path) -> Any:
    """Inverse of :func:`_encode` on a worker (the variant is set)."""
    if isinstance(value, dict):
        return {k: _decode(v, root) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_decode(v, root) for v in value)
    if isinstance(value, _FileRef):
        return str(root / value.path)
    if isinstance(value, _MiValue):
        import mitsuba as mi

        return getattr(mi, value.type_name)(value.data)
    return value


# --- the worker side -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Job:
    """What every task of a render needs besides the scene."""

    variant: str
    integrator: Any  #: None (the scene's), or an encoded plugin dict
    sensor: int
    threads: int | None  #: Dr.Jit threads per worker process (None: leave as is)
    detach: bool = False  #: local cluster: keep the worker out of the terminal's Ctrl-C (own process group)


@dataclass
class _Loaded:
    folder: str
    scene: Any
    integrator: Any
    renderer: PassRenderer
    renders: int = 0


#: per worker process: loaded scenes by (digest, variant, integrator, sensor), most recent last
_CACHE: OrderedDict[tuple, _Loaded] = OrderedDict()
_CACHE_SIZE = 2
#: Dr.Jit threads a worker keeps at least: with one, Mitsuba 3.9 deadlocks reading EXR files, and a worker hung
#: for 600 s (no heartbeat) in a CI run of the worker-kill test while rendering with one
MIN_THREADS = 2
#: a worker may run tasks in several threads (--nthreads > 1): renders share the scene's film, so one at a time
_LOCK = threading.Lock()


def _cleanup() -> None:
    for entry in _CACHE.values():
        shutil.rmtree(entry.folder, ignore_errors=True)
    _CACHE.clear()


atexit.register(_cleanup)


def _own_process_group() -> None:
    """Move this worker process out of the terminal's foreground process group: a Ctrl-C there signals the
    whole group, which would kill a local cluster's workers, and Mitsuba's own SIGINT handler would cut their
    running passes short. (A no-op for a process that leads its group already.)"""
    if hasattr(os, "setpgid"):
        try:
            os.setpgid(0, 0)
        except OSError:
            pass


def _setup(job: _Job) -> None:
    """Dr.Jit/Mitsuba on a worker: libLLVM (importing segmitsuba, done by this module), variant, threads."""
    import drjit as dr
    import mitsuba as mi

    if job.detach:  # also after a restart by the nanny (which lives in the client's process)
        _own_process_group()
    if mi.variant() != job.variant:
        if job.variant not in mi.variants():
            raise ValueError(f"Mitsuba variant '{job.variant}' is not available on this worker "
                             f"(available: {', '.join(mi.variants())})")
        mi.set_variant(job.variant)  # segmitsuba registers its integrators for it
    threads = max(MIN_THREADS, job.threads) if job.threads else None
    if threads and int(dr.thread_count()) != threads:
        dr.set_thread_count(threads)


def _load(bundle: SceneBundle, job: _Job) -> _Loaded:
    import mitsuba as mi

    key = (bundle.digest, job.variant, repr(job.integrator), job.sensor)
    if key in _CACHE:
        _CACHE.move_to_end(key)
        return _CACHE[key]

    folder = tempfile.mkdtemp(prefix=f"segmitsuba-scene-{bundle.digest[:12]}-")
    try:
        root = Path(folder)
        for rel, data in bundle.files.items():
            path = root / rel
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(data)
        if bundle.scene_dict is not None:
            scene = mi.load_dict(_decode(bundle.scene_dict, root))
        else:
            scene = mi.load_file(str(root / bundle.main), **bundle.defines)
        if job.integrator is None:
            integrator = scene.integrator()
        else:
            integrator = mi.load_dict(_decode(job.integrator, root))
    except BaseException:
        shutil.rmtree(folder, ignore_errors=True)
        raise
    _CACHE[key] = entry = _Loaded(folder, scene, integrator, PassRenderer(scene, integrator, job.sensor))
    while len(_CACHE) > _CACHE_SIZE:
        _, old = _CACHE.popitem(last=False)
        shutil.rmtree(old.folder, ignore_errors=True)
    return entry


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except Exception:
        return f"pid {os.getpid()}"


def _describe_task(bundle: SceneBundle, job: _Job) -> dict[str, Any]:
    """Load the scene on one worker (cached for its first render) and report what the client plans with."""
    from .rendering import environment

    with _LOCK:
        _setup(job)
        entry = _load(bundle, job)
        sensor = entry.scene.sensors()[job.sensor]
        size = sensor.film().crop_size()
        return {
            "size": (int(size[0]), int(size[1])),
            "sample_count": int(sensor.sampler().sample_count()),
            "integrator": str(entry.integrator),
            "environment": environment(),
            "worker": _worker_name(),
        }


def _render_task(bundle: SceneBundle, job: _Job, passes: list[Pass]) -> dict[str, Any]:
    """Render ``passes`` with the pass engine and return their sample-weighted sum (float64) and counts."""
    with _LOCK:
        _setup(job)
        entry = _load(bundle, job)
        acc: np.ndarray | None = None
        spps, seconds, warm, pools = [], [], [], []
        for p in passes:
            img, n_real, pass_seconds, pass_pools = entry.renderer.render(p)
            acc = img * n_real if acc is None else acc + img * n_real
            spps.append(n_real)
            seconds.append(pass_seconds)
            pools.extend(pass_pools)
            warm.append(entry.renders > 0)  # the first render of a process pays for JIT compilation
            entry.renders += 1
    return {
        "indices": [p.index for p in passes],
        "seeds": [p.seed for p in passes],
        "spp": spps,
        "seconds": seconds,
        "warm": warm,
        "pools": pools,
        "sum": acc,
        "channels": list(entry.renderer.channels or []),
        "worker": _worker_name(),
        "pid": os.getpid(),
    }


# --- the client side -------------------------------------------------------------------------------------


@dataclass
class TaskReport:
    """What the progress callback gets after each finished task."""

    finished: int  #: tasks finished so far
    planned_tasks: int | None  #: total tasks when known in advance (spp mode)
    passes: list[int]  #: indices of the task's passes
    task_spp: int  #: samples per pixel of the task
    task_seconds: float  #: render time of its passes on the worker
    worker: str
    spp: int  #: samples per pixel finished so far
    seconds: float  #: time since the render started
    target_spp: int | None
    time_budget: float | None
    eta: float | None


@dataclass
class DistributedResult(RenderResult):
    """A :class:`RenderResult` with where its passes ran."""

    scheduler: str = ""
    workers: int = 0  #: worker processes connected at the end
    task_passes: list[list[int]] = field(default_factory=list)  #: pass indices of each finished task
    task_workers: list[str] = field(default_factory=list)  #: worker (address) of each finished task
    cancelled_tasks: int = 0  #: tasks submitted but not kept (time budget, Ctrl-C)
    worker_environment: dict[str, Any] = field(default_factory=dict)  #: versions/variant/threads of a worker
    integrator_description: str = ""


class _TaskInterrupt(_Interrupt):
    def __call__(self, signum: int, frame: Any) -> None:
        if self.requested:
            raise KeyboardInterrupt
        self.requested = True
        self._message("interrupt: cancelling the unfinished tasks, keeping the finished ones (Ctrl-C again to "
                      "stop at once)")


class _TaskProgress(_Progress):
    def update(self, r: TaskReport) -> None:  # type: ignore[override]
        planned = f"/{r.planned_tasks}" if r.planned_tasks else ""
        first, last = min(r.passes) + 1, max(r.passes) + 1  # 1-based, as render_passes reports passes
        which = f"pass {first}" if first == last else f"passes {first}-{last}"
        self.show(r.task_spp, r.spp, r.seconds, r.target_spp, r.time_budget, r.eta, f"task {r.finished}",
                  f"task {r.finished}{planned}",
                  f"{which}, {r.task_spp} spp in {r.task_seconds:.2f} s on {r.worker}")


def _cpu_count() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:
        return os.cpu_count() or 1


@contextmanager
def _connect(
    scheduler: Any, workers: int | None, threads: int | None, connect_timeout: float | None
) -> Iterator[tuple[Any, int | None, str, bool]]:
    """A Dask client (and the Dr.Jit threads per worker to ask for): the given one, one connected to a
    scheduler address or scheduler file, or one on a new LocalCluster of ``workers`` processes."""
    distributed = require_distributed()
    if isinstance(scheduler, distributed.Client):
        yield scheduler, threads, f"scheduler {scheduler.scheduler.address}", False
        return
    if scheduler is not None:
        kwargs: dict[str, Any] = {"set_as_default": False}
        if connect_timeout is not None:
            kwargs["timeout"] = connect_timeout
        text = str(scheduler)
        try:
            if text.endswith(".json") and Path(text).is_file():
                client = distributed.Client(scheduler_file=text, **kwargs)
            else:
                client = distributed.Client(text, **kwargs)
        except (OSError, TimeoutError, ValueError) as e:
            raise ConnectionError(f"cannot connect to the Dask scheduler at '{text}': {e}") from None
        try:
            yield client, threads, f"scheduler {client.scheduler.address}", False
        finally:
            client.close()
        return
    if workers is None or workers < 1:
        raise ValueError("give a scheduler (address, scheduler file or Client) or a number of local workers")
    if threads is None:  # Dr.Jit's pool uses every core: share them between the worker processes
        threads = max(MIN_THREADS, _cpu_count() // workers)
    # CRITICAL: closing the cluster races worker heartbeats, which Dask logs as errors with tracebacks; real
    # failures reach the client as task exceptions and are reported in one line
    cluster = distributed.LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                                       dashboard_address=None, silence_logs=logging.CRITICAL)
    try:
        client = distributed.Client(cluster, set_as_default=False)
        try:
            client.run(_own_process_group)  # the nannies (and the scheduler) run in this process
            yield client, threads, f"local cluster at {cluster.scheduler_address}", True
        finally:
            client.close()
    finally:
        cluster.close()


def _encode_integrator(integrator: str | Mapping[str, Any] | None) -> Any:
    if integrator is None:
        return None
    if isinstance(integrator, str):
        return {"type": integrator}
    if isinstance(integrator, Mapping):
        if "type" not in integrator:
            raise ValueError("an integrator dict needs a 'type'")
        return _encode(dict(integrator))
    raise TypeError("integrator: give a plugin name, a plugin dict or None (the scene's integrator); a loaded "
                    "integrator cannot be shipped")


def render_distributed(
    scene: str | os.PathLike | Mapping[str, Any] | SceneBundle,
    integrator: str | Mapping[str, Any] | None = None,
    spp: int | None = None,
    time_budget: float | None = None,
    passes: int | None = None,
    pass_spp: int | None = None,
    seed: int = 0,
    scheduler: Any = None,
    workers: int | None = None,
    variant: str = DEFAULT_VARIANT,
    defines: Mapping[str, Any] | None = None,
    sensor: int = 0,
    threads: int | None = None,
    task_passes: int | None = None,
    retries: int = 2,
    connect_timeout: float | None = None,
    progress: bool = True,
    callback: Callable[[TaskReport], None] | None = None,
    handle_sigint: bool = True,
) -> DistributedResult:
    """Render ``scene`` in passes on a Dask cluster; the result is the exact sample-weighted pass average.

    ``scene``: a scene file (shipped with the files it references; ``defines`` are its ``$name`` parameters),
    a scene dict, or a :class:`SceneBundle` from :func:`package_scene`. ``integrator``: a plugin name or dict
    (default: the scene's own). ``scheduler``: a ``distributed.Client``, a scheduler address
    (``tcp://host:8786``) or a scheduler file (``.json``); or ``workers=N`` starts a LocalCluster of N
    single-threaded worker processes, each with ``threads`` Dr.Jit threads (default: cores / N; at least
    :data:`MIN_THREADS`, as for any worker). ``threads``
    also applies to the workers of a given scheduler (default: leave Dr.Jit's, which uses every core of the
    worker's machine).

    - ``spp``: passes planned as :func:`~segmitsuba.rendering.render_passes` plans them (``passes``,
      ``pass_spp``, or passes of at most :data:`~segmitsuba.rendering.PASS_SAMPLES` samples), but at least two
      per worker process; contiguous passes are grouped into tasks of ``task_passes`` passes (default: about
      :data:`TASKS_PER_WORKER` tasks per worker, at most :data:`MAX_TASK_PASSES` passes each). Pass ``i`` has
      seed ``pass_seed(seed, i)`` wherever it runs, so the same plan gives the same image as a local render.
    - ``time_budget``: one calibration pass per worker, then passes sized for about a tenth of the budget;
      no task is submitted that would end after the budget, tasks still running a while after it are
      cancelled; what finished is kept. With ``spp`` too it also stops there.

    Failures: a worker that dies loses nothing (Dask runs its tasks again elsewhere, each task's result is
    taken once); a task that raises is retried ``retries`` times, then the render raises DistributedError.
    Ctrl-C (``handle_sigint``, main thread) cancels the unfinished tasks and returns the finished ones with
    ``interrupted=True``; before any task finished, or a second Ctrl-C, raises KeyboardInterrupt.
    """
    require_distributed()  # early: a clear message when Dask is missing
    if spp is not None and spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    if time_budget is not None and not time_budget > 0:
        raise ValueError(f"time_budget must be > 0 seconds, got {time_budget}")
    if pass_spp is not None and pass_spp < 1:
        raise ValueError(f"pass_spp must be >= 1, got {pass_spp}")
    if passes is not None and time_budget is not None:
        raise ValueError("passes needs spp (with a time budget the pass sizes adapt to the budget)")
    if task_passes is not None and task_passes < 1:
        raise ValueError(f"task_passes must be >= 1, got {task_passes}")
    if threads is not None and threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    if scheduler is not None and workers is not None:
        raise ValueError("give either a scheduler or a number of local workers, not both")

    if isinstance(scene, SceneBundle):
        if defines:
            raise ValueError("defines are packaged with the scene: pass them to package_scene")
        bundle = scene
    else:
        bundle = package_scene(scene, defines)
    reporter = _TaskProgress(progress, spp, time_budget, desc="render ")
    interrupt = _TaskInterrupt(reporter.message)
    try:
        with _connect(scheduler, workers, threads, connect_timeout) as (client, threads_, where, local):
            return _run(client, where, bundle, integrator, spp, time_budget, passes, pass_spp, seed,
                        variant, sensor, threads_, task_passes, retries, reporter, interrupt, callback,
                        handle_sigint, local)
    finally:
        reporter.close()


def _run(
    client: Any, where: str, bundle: SceneBundle, integrator: Any, spp: int | None,
    time_budget: float | None, passes: int | None, pass_spp: int | None, seed: int, variant: str, sensor: int,
    threads: int | None, task_passes: int | None, retries: int, reporter: _TaskProgress, interrupt: _Interrupt,
    callback: Callable[[TaskReport], None] | None, handle_sigint: bool, local: bool,
) -> DistributedResult:
    job = _Job(variant=variant, integrator=_encode_integrator(integrator), sensor=sensor, threads=threads,
               detach=local)
    token = uuid.uuid4().hex[:10]
    say = reporter.message if reporter.enabled else (lambda _m: None)

    slots_checked = 0.0
    slots = 0

    def worker_count(force: bool = False) -> int:
        nonlocal slots, slots_checked
        if force or time.monotonic() - slots_checked > 2.0:
            slots = len(client.nthreads())  # one render at a time per worker process (see _LOCK)
            slots_checked = time.monotonic()
        return slots

    if worker_count(force=True) == 0:
        say(f"waiting for Dask workers to connect to {where}")
        client.wait_for_workers(1)
        worker_count(force=True)
    start = time.perf_counter()
    say(f"dask: {where}, {slots} worker{'s' if slots != 1 else ''}"
        + (f" ({threads} Dr.Jit thread{'s' if threads != 1 else ''} each)" if threads else "")
        + f"; shipping {bundle.name} ({len(bundle.files)} file{'s' if len(bundle.files) != 1 else ''}, "
        f"{bundle.size / 1e6:.2f} MB)")
    bundle_future = client.scatter(bundle, broadcast=True, hash=False)
    describe = client.submit(_describe_task, bundle_future, job, key=f"segmitsuba-describe-{token}", pure=False)
    try:
        info = describe.result()
    except Exception as e:
        raise DistributedError(f"the worker cannot load the scene or integrator: {e}") from e
    width, height = info["size"]
    pixels = width * height
    if spp is None and time_budget is None:
        spp = info["sample_count"]
    max_pass_spp = pass_spp if pass_spp is not None else max(1, PASS_SAMPLES // max(1, pixels))

    # --- what to submit: the planned tasks (spp mode), or tasks sized on the fly (time mode)
    planned: list[list[Pass]] = []
    if time_budget is None:
        plan = plan_passes(spp, pixels, passes, pass_spp)
        if passes is None and pass_spp is None and len(plan) < 2 * slots:
            plan = plan_passes(spp, pixels, passes=min(spp, 2 * slots))  # work for every worker
        per_task = task_passes or max(1, min(MAX_TASK_PASSES, math.ceil(len(plan) / (TASKS_PER_WORKER * slots))))
        items = [Pass.of(seed, i, n, o) for i, (n, o) in enumerate(zip(plan, pass_offsets(plan), strict=True))]
        planned = [items[i:i + per_task] for i in range(0, len(items), per_task)]
        planned.reverse()  # popped from the end
        target_pass_seconds = 0.0
        planned_tasks: int | None = len(planned)
    else:
        target_pass_seconds = min(max(time_budget * PASS_FRACTION, PASS_SECONDS[0]), PASS_SECONDS[1])
        planned_tasks = None

    pending: dict[Any, list[Pass]] = {}
    next_index = 0
    submitted_spp = 0
    submitted_tasks = 0
    exhausted = False
    rate: float | None = None  # seconds per spp of one worker
    warm_seconds = warm_spp = all_seconds = all_spp = 0.0
    last_task_seconds = 0.0

    acc: np.ndarray | None = None
    channels: list[str] = []
    done = 0
    finished = 0
    records: list[tuple[int, int, int, float]] = []  # (index, seed, spp, seconds) of every kept pass
    pools: list[dict[str, Any]] = []
    task_passes_done: list[list[int]] = []
    task_workers: list[str] = []
    counted: set[int] = set()
    stop_reason = "spp"

    def next_task() -> list[Pass] | None:
        """The next task's passes, None when none now; sets ``exhausted`` when none ever."""
        nonlocal next_index, exhausted
        if time_budget is None:
            if not planned:
                exhausted = True
                return None
            return planned.pop()
        left = spp - submitted_spp if spp is not None else None
        if left is not None and left <= 0:
            exhausted = True
            return None
        elapsed = time.perf_counter() - start
        if rate is None:  # calibration: one small pass per worker, which also pays for JIT compilation
            if submitted_tasks >= max(1, worker_count()):
                return None
            if elapsed >= time_budget and submitted_tasks > 0:
                exhausted = True
                return None
            n = max(1, min(max_pass_spp, 2**16 // max(1, pixels)))
        else:
            waves_ahead = len(pending) // max(1, worker_count())
            fit = int((time_budget - elapsed - waves_ahead * last_task_seconds) / rate)
            if fit < 1:
                if waves_ahead == 0:
                    exhausted = True
                return None
            n = max(1, min(int(target_pass_seconds / rate), max_pass_spp, fit))
        if left is not None:
            n = min(n, left)
        index = next_index
        next_index += 1
        return [Pass.of(seed, index, n, submitted_spp)]  # passes are created in index order

    def cancel_pending() -> int:
        count = len(pending)
        if pending:
            client.cancel(list(pending))
            pending.clear()
        return count

    cancelled = 0
    resubmitted: dict[int, int] = {}  # per task (its first pass): times submitted again after a lost bundle
    finished_event = threading.Event()
    try:
        with _sigint(interrupt, handle_sigint):
            while True:
                while not exhausted and not interrupt.requested and len(pending) < TASKS_IN_FLIGHT * max(
                    1, worker_count()
                ):
                    task = next_task()
                    if task is None:
                        break
                    first, last = task[0].index, task[-1].index
                    future = client.submit(_render_task, bundle_future, job, task, pure=False, retries=retries,
                                           key=f"segmitsuba-passes-{first}-{last}-{token}")
                    pending[future] = task
                    future.add_done_callback(lambda _f: finished_event.set())
                    submitted_tasks += 1
                    submitted_spp += sum(p.spp for p in task)
                if not pending:
                    if exhausted or time_budget is None or interrupt.requested:
                        break
                    time.sleep(POLL_SECONDS)  # nothing to submit yet (cannot last: no task is running)
                    continue
                finished_event.wait(POLL_SECONDS)  # wakes up when a task ends, or to check time and Ctrl-C
                finished_event.clear()
                if interrupt.requested and done > 0:  # before taking results: none finished after Ctrl-C
                    cancelled += cancel_pending()
                    break
                for future in [f for f in pending if f.done()]:
                    task = pending.pop(future)
                    try:
                        res = future.result()
                    except Exception as e:
                        # A killed worker can take the scene bundle's registered copies with it: the scheduler
                        # then cancels the tasks that depend on it ("lost dependencies") though nothing was
                        # cancelled here. Ship the bundle again and resubmit (same passes and seeds: counted once).
                        tries = resubmitted.get(task[0].index, 0)
                        if type(e).__name__ == "FutureCancelledError" and tries < retries:
                            resubmitted[task[0].index] = tries + 1
                            bundle_future = client.scatter(bundle, broadcast=True, hash=False)
                            again = client.submit(_render_task, bundle_future, job, task, pure=False,
                                                  retries=retries, key=f"{future.key}-again{tries + 1}")
                            pending[again] = task
                            again.add_done_callback(lambda _f: finished_event.set())
                            continue
                        cancelled += cancel_pending()
                        hint = " (it crashed its workers: out of memory?)" if type(e).__name__ == "KilledWorker" else ""
                        raise DistributedError(f"task for passes {task[0].index}-{task[-1].index} failed{hint}: "
                                               f"{type(e).__name__}: {e}") from e
                    for i in res["indices"]:
                        if i in counted:  # cannot happen: each task's result is taken once
                            raise DistributedError(f"pass {i} was returned twice")
                        counted.add(i)
                    if acc is None:
                        acc, channels = res["sum"], res["channels"]
                    elif res["sum"].shape != acc.shape:
                        raise DistributedError(f"task images differ in shape: {res['sum'].shape} vs {acc.shape}")
                    else:
                        acc = acc + res["sum"]
                    task_spp = int(sum(res["spp"]))
                    done += task_spp
                    finished += 1
                    records.extend(zip(res["indices"], res["seeds"], res["spp"], res["seconds"], strict=True))
                    pools.extend(res["pools"])
                    task_passes_done.append(list(res["indices"]))
                    task_workers.append(res["worker"])
                    for s, n, warm in zip(res["seconds"], res["spp"], res["warm"], strict=True):
                        all_seconds, all_spp = all_seconds + s, all_spp + n
                        if warm:
                            warm_seconds, warm_spp = warm_seconds + s, warm_spp + n
                    rate = warm_seconds / warm_spp if warm_spp else all_seconds / all_spp
                    last_task_seconds = rate * task_spp
                    elapsed = time.perf_counter() - start
                    if time_budget is None:
                        eta = rate * max(0, spp - done) / max(1, worker_count())
                    else:
                        eta = max(0.0, time_budget - elapsed)
                        if spp is not None:
                            eta = min(eta, rate * max(0, spp - done) / max(1, worker_count()))
                    report = TaskReport(finished, planned_tasks, list(res["indices"]), task_spp,
                                        float(sum(res["seconds"])), res["worker"], done, elapsed, spp,
                                        time_budget, eta)
                    reporter.update(report)
                    if callback is not None:
                        callback(report)
                if interrupt.requested and done > 0:
                    cancelled += cancel_pending()
                    break
                if time_budget is not None and time.perf_counter() - start >= time_budget:
                    exhausted = True  # and tasks still running well after the budget are given up
                    if done > 0 and time.perf_counter() - start >= time_budget + max(1.0, 2 * last_task_seconds):
                        cancelled += cancel_pending()
        if interrupt.requested:
            stop_reason = "interrupt"
        elif time_budget is not None and not (spp is not None and done >= spp):
            stop_reason = "time"
    except KeyboardInterrupt:
        cancelled += cancel_pending()
        if acc is None:
            raise
        stop_reason = "interrupt"
    finally:
        if pending:
            cancel_pending()
        try:
            client.cancel([bundle_future, describe])
        except Exception:
            pass

    if acc is None:
        if interrupt.requested:
            raise KeyboardInterrupt
        raise DistributedError("no task finished")
    wall = time.perf_counter() - start
    if stop_reason == "interrupt":
        reporter.message(f"interrupt: cancelled {cancelled} unfinished task{'s' if cancelled != 1 else ''}")
    records.sort()
    return DistributedResult(
        **average(acc, done, channels),
        spp=done,
        passes=len(records),
        seconds=wall,
        interrupted=stop_reason == "interrupt",
        stop_reason=stop_reason,
        seeds=[r[1] for r in records],
        pass_spp=[r[2] for r in records],
        pass_seconds=[r[3] for r in records],
        pools=sorted(pools, key=lambda pool: pool["spp_offset"]),
        scheduler=where,
        workers=worker_count(force=True),
        task_passes=task_passes_done,
        task_workers=task_workers,
        cancelled_tasks=cancelled,
        worker_environment=info["environment"],
        integrator_description=info["integrator"],
    )
