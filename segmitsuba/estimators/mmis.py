"""Recursive marginal-MIS estimation over a pool of segments (docs/maths.md §4).

For every query segment ``s`` whose end ``y_s`` has a non-delta BSDF:

    L̂(s) = T_s · ( Le(s) + Σ_{s' : |x' - y_s| < r} K f_r(s, s') L̂(s') / D(s') + private children )

``D(s')`` is the balance denominator: the densities of *every* sampled technique that could have produced
``s'`` — camera segments ending within ``r`` of ``x'`` (BSDF sampling at their end), light segments starting
within ``r`` of ``y'`` (adjoint BSDF sampling, converted to the ``(x', ω')`` measure by ``cos_x'/cos_y'``) and
the emission technique (``N_e`` light sub-paths), and with next-event segments the emitter sample of every camera
technique. The techniques are data (:data:`TECHNIQUES`), summed by one function (``MMISEstimator._density``)
through each kernel's ``technique_sum`` and ``technique_count`` (docs/maths.md §4.2).
Each technique carries its Russian-roulette survival probability, including techniques whose child was
killed; with private glossy vertices (docs/maths.md §4.8) the techniques at glossy vertices make no sources
and leave every ``D``. ``D`` and the edge weights do not depend on ``L̂``: they are computed once per pass,
and the recursion is solved by ``iterations`` sparse matrix-vector products. Delta emitters' segments can
come from the emission technique only, so their ``D`` is that term alone
(its delta factors cancel against the emitted weight).

**Lambertian sums** (cluster kernel; docs/maths.md §6). A Lambertian technique's density is
``w_t max(0, n_t·ω')/π``. Where every ``n_t·ω'`` of a cluster's Lambertian techniques has one sign, their sum is
``max(0, N_C·ω')/π`` with ``N_C = Σ w_t n_t``: one dot product instead of one BSDF evaluation per pair. That
holds whenever ``|n̄·ω'| >= sin θ`` (``n̄`` their mean normal, ``θ`` their largest angle to it): always on a
flat patch, and for all but grazing directions on a curved one; the grazing band is summed explicitly.
Likewise a Lambertian receiver gathers ``K (ρ/π) n_s·V_C`` with ``V_C = Σ_{s'} ω' L̂(s')/D(s')`` summed once
per cluster and iteration over the sources in front of ``n̄``, when those are all on the receiver's side and the
others all behind it (checked per receiver; always true on a flat patch); a receiver tilted from ``n̄`` by a
little (two planes in one cluster) lists the grazing band of sources explicitly and takes ``V_C`` for the rest.
Both are exact, not approximations; glossy receivers and techniques keep explicit edges and loops.
This turns the ``O(m²)`` work of a cluster of ``m`` segments into ``O(m)`` where it applies.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi

from ..grid import (
    ClusterGrid,
    RadiusGrid,
    counting_sort,
    random_offset,
    reduce_runs,
    run_pieces,
    scatter_sorted_runs,
)
from ..population import (
    CAMERA,
    INVALID,
    LIGHT,
    NEXT_EVENT,
    SegmentPool,
    Surface,
    _cat,
    emitter_sample_of,
    photon_to_next_event,
    point_interaction,
    reflects,
    technique_records,
)
from ..samplers.walk import glossy_vertex

#: the mode of every scatter-reduction of a pass: Local pre-reduces within a SIMD packet, while Auto gives small
#: targets a copy per thread and bakes their size, different in every pool, into the kernel (as grid/hashgrid.py)
REDUCE = dr.ReduceMode.Local
#: half-width of the grazing band |n̄·ω'| < BAND that a Lambertian receiver tilted from its cluster's mean normal
#: n̄ by up to atan(BAND) gathers explicitly, the rest through V_C (docs/maths.md §6.3)
LAMBERTIAN_BAND = 0.25
#: bins of ``|n̄·ω'|`` in ``[0, BAND)`` that a cluster's band list is sorted by: a banded receiver tilted by ``θ``
#: lists only the bins up to ``tan θ`` (docs/maths.md §6.3); fewer where clusters x bins would exceed
#: :data:`BAND_CELLS` (tiny kernels), so that the offsets stay small
BAND_BINS = 64
BAND_CELLS = 1 << 22
#: the longest segment span (rays) from which the solve keeps levels (``_RayLevels``); below, every query spans
#: one ray and reads the last level
RAY_LEVELS_FROM = 2


@dataclass(frozen=True)
class Technique:
    """One way a pool's segments are sampled (docs/maths.md §3), with the form of its density (``density``):

    * ``"bsdf"``: at a vertex that a walk of ``kind`` reached, the BSDF sampled in ``mode`` (``"radiance"`` or
      ``"importance"``) gives the next segment; ``K Σ_t q_t pdf_t(ω)`` over the records ``t`` near the end;
    * ``"emission"``: the ``N_e`` light sub-paths start on an emitter (closed form, ``N_e p_e cos_x``);
    * ``"next_event"``: every record of ``records`` draws one emitter sample from its vertex (§3.5);
      ``K n p_e(ω)`` with ``n`` the records near the end.

    A segment it produces has its ``end`` at the technique's vertex (a camera walk's segment leaves it at ``x``
    toward the light side, a light walk's at ``y``); a technique record is the record of the segment that
    arrived there, whose own end there is the other one (:attr:`own`)."""

    name: str
    kind: int
    end: str
    density: str = "bsdf"
    mode: str = "radiance"
    #: it makes segments through a mixed vertex's delta lobe (absorbed, §2.3): a camera walk never goes on there
    absorbed: bool = True
    #: it makes straight segments (no delta vertex inside); light walks that keep only delta chains past their
    #: first segment make none (§2.5)
    straight: bool = True
    #: it makes only straight segments ending on an emitter surface that reflects nothing, and carries their
    #: emission alone (§3.5)
    emission_only: bool = False
    #: the technique whose records it starts from (None: its own)
    of: str | None = None

    @property
    def own(self) -> str:
        return "y" if self.end == "x" else "x"

    @property
    def records(self) -> str:
        """The name of the records it starts from (the keys of a kernel's ``techniques``)."""
        return self.of or self.name


#: every technique of a pool, iterated by ``MMISEstimator._density`` for ``D`` through each kernel's
#: ``technique_sum`` and ``technique_count`` (docs/maths.md §4.2); ``next_event`` runs only with
#: ``next_event_segments``
TECHNIQUES = (Technique("camera", CAMERA, "x", absorbed=False),
              Technique("light", LIGHT, "y", mode="importance"),
              Technique("emission", LIGHT, "y", density="emission"),
              Technique("next_event", CAMERA, "x", density="next_event", absorbed=False, emission_only=True,
                        of="camera"))


@dataclass
class Ends:
    """Segments whose technique densities are wanted, by their two ends in camera orientation: ``x`` with its
    geometric normal and direction toward ``y``, and ``y`` likewise; ``*_known``: the end is a point of the
    scene; ``cid_*``: its cluster (cluster kernel; None: looked up)."""

    x: mi.Point3f
    nx: mi.Normal3f
    wx: mi.Vector3f
    y: mi.Point3f
    ny: mi.Normal3f
    dy: mi.Vector3f
    x_known: mi.Bool
    y_known: mi.Bool
    absorbed: mi.Bool | None = None  #: through a mixed vertex's delta lobe, absorbed (None: none is)
    straight: mi.Bool | None = None  #: no delta vertex inside (None: every one is straight)
    cid_x: mi.UInt32 | None = None
    cid_y: mi.UInt32 | None = None
    #: from a delta emitter (None: none is): no BSDF technique makes them; ``D`` is in the units of a photon
    #: (its delta factors cancel against the emitted weight)
    delta: mi.Bool | None = None
    #: what a next-event technique could have made (§3.5): straight segments whose ``y`` lies on an emitter that
    #: reflects nothing, with the emitter sample reaching it (``emitter_sample``) and, for delta emitters, the
    #: next-event density over the photon one (``delta_ratio``, 0 where there is none); None: no segment
    emits: mi.Bool | None = None
    emitter_sample: mi.DirectionSample3f | None = None
    delta_ratio: mi.Float | None = None

    def at(self, end: str):
        """(point, normal, direction leaving it, known, cluster) of end ``end``."""
        if end == "x":
            return self.x, self.nx, self.wx, self.x_known, self.cid_x
        return self.y, self.ny, self.dy, self.y_known, self.cid_y


def _density_body(pool: SegmentPool, tech: Technique, query_wo, ctx: mi.BSDFContext):
    """Loop body adding ``q_t pdf_t(query_wo)`` of technique record ``j`` of ``tech``, whose BSDF lives on its
    walk-arrival surface (``pool.surf``), seen from the direction back along its walk there."""
    q = pool.q
    tech_wi = pool.wx if tech.own == "x" else pool.dy

    def body(state, j, row=None):
        s = pool.walk_surface(j)
        si = s.interaction(dr.gather(mi.Vector3f, tech_wi, j))
        wo = query_wo if row is None else dr.gather(mi.Vector3f, query_wo, row)
        pdf = si.bsdf().pdf(ctx, si, si.to_local(wo))
        return state + dr.gather(mi.Float, q, j) * pdf

    return body


def _lumped_body(records: mi.Float, query_wo: mi.Vector3f):
    """:func:`_density_body` of the lumped (Lambertian) records, ``q_t w_t max(0, n_t·ω)/π``, from their packed
    ``(n_t, q_t w_t)`` (:attr:`ClusterSums.records`): one 16-byte read per record instead of its surface and BSDF."""

    def body(state, j, row):
        v = dr.gather(mi.Array4f, records, j)
        wo = dr.gather(mi.Vector3f, query_wo, row)
        return state + dr.maximum(0, v.x * wo.x + v.y * wo.y + v.z * wo.z) * v.w * dr.inv_pi

    return body


class _ClusterKernel:
    """The cluster kernel (docs/maths.md §5.2): jittered voxels × normal bins over every segment end of the pass;
    two ends interact when they share a cluster, with ``K = 1 / A(C)``.

    Every end but one kind is a walk vertex of the pool (``pool.surf``): a camera segment's ``y`` and a light
    segment's ``x`` are their own records, a camera segment's ``x`` and a light segment's ``y`` their parent's.
    So the grid clusters each walk vertex once, plus the emitter points of first light segments, and the ends
    take their vertex's cluster: half the points of clustering both ends of every segment, the same clusters."""

    def __init__(self, pool: SegmentPool, h: float, seed: int, x_ok: mi.Bool, y_ok: mi.Bool,
                 techniques: dict | None = None, lambertian_sums: bool = False):
        n = pool.size
        #: the records that techniques start from, by name (:attr:`Technique.records`)
        self.techniques = techniques or {}
        #: the Lambertian techniques summed per cluster (docs/maths.md §6), or None
        self.sums: ClusterSums | None = None
        self._technique_lists: dict = {}
        #: the solve's cluster sums scatter by cluster, or reduce their runs in pieces
        self.scatter_sums = scatter_sorted_runs(mi.Float)
        #: every segment, stably sorted by the cluster of its x or y end, and those clusters in that order (the
        #: sentinel ``clusters`` for an end in none): :meth:`cluster_lists`
        self._sorted: dict[str, tuple[mi.UInt32, mi.UInt32]] = {}
        is_cam = pool.kind == CAMERA
        first_light = ~is_cam & (pool.parent == INVALID)  # y on the emitter: no walk record holds it
        on_emitter = dr.compress(first_light & y_ok)
        m = dr.width(on_emitter)
        points = mi.Point3f(_cat([pool.surf.p, dr.gather(mi.Point3f, pool.y, on_emitter)]))
        normals = mi.Vector3f(_cat([pool.surf.n, dr.gather(mi.Normal3f, pool.ny, on_emitter)]))
        active = _cat([pool.surf.valid, dr.full(mi.Bool, True, m)])
        dr.eval(points, normals, active)  # read by several of the grid's kernels: written once, in order
        # each point is a surface point once: all of them bound where the surface ends inside a voxel
        self.grid = ClusterGrid(points, normals, h, random_offset(h, seed), active=active, extent_points=active)
        cid = self.grid.cluster_id
        rank = dr.full(mi.UInt32, INVALID, n)
        if m:
            dr.scatter(rank, dr.arange(mi.UInt32, m) + dr.opaque(mi.UInt32, n), on_emitter)
        own = dr.arange(mi.UInt32, n)
        # a next-event segment starts at its parent's arrival, as a camera segment, and ends on an emitter that
        # no walk vertex holds: looked up in the grid
        nee = pool.kind == NEXT_EVENT
        x_vertex = dr.select(is_cam | nee, pool.parent, own)
        y_vertex = dr.select(is_cam, own, dr.select(first_light, rank, pool.parent))
        self.cid_x = dr.select(x_ok, dr.gather(mi.UInt32, cid, x_vertex, x_ok), INVALID)
        self.cid_y = dr.select(y_ok & ~nee, dr.gather(mi.UInt32, cid, y_vertex, y_ok & ~nee), INVALID)
        if pool.next_event_count:
            self.cid_y = dr.select(nee, self.grid.cluster_of(pool.y, pool.ny, nee & y_ok), self.cid_y)
        self.clusters = self.grid.num_clusters
        # a pool without any surface point (every camera ray left the scene) has no cluster: one unused entry
        # then keeps the masked gathers off empty arrays
        self.inv_area = dr.rcp(dr.maximum(self.grid.area, 1e-30)) if self.clusters else dr.zeros(mi.Float, 1)
        dr.eval(self.cid_x, self.cid_y, self.inv_area)
        #: segment ends in each cluster
        # Segment ends in each cluster, counted in the order of each end's sort: neighbouring lanes then mostly
        # count into one cluster, and a local reduction leaves about one atomic per SIMD packet (in segment order
        # it left one per lane, or a copy of the counts per thread, 3-5x slower)
        members = dr.zeros(mi.UInt32, self.clusters + 1)
        for end, cid in (("x", self.cid_x), ("y", self.cid_y)):
            key = dr.select(cid != INVALID, cid, dr.opaque(mi.UInt32, self.clusters))  # opaque: no recompiles
            self._sorted[end] = counting_sort(key, max(self.clusters, 1).bit_length(), with_keys=True)
            sorted_cid = self._sorted[end][1]
            # the ends in no cluster (one long run of the sentinel) are left out rather than counted into a spare
            # entry: one atomic per SIMD packet on one address fewer (0.23 -> 0.17 ms on Cornell's 1.1M x ends)
            dr.scatter_reduce(dr.ReduceOp.Add, members, mi.UInt32(1), sorted_cid,
                              sorted_cid != dr.opaque(mi.UInt32, self.clusters), mode=REDUCE)
        dr.eval(members)
        self.members = dr.reshape(mi.UInt32, members, self.clusters, shrink=True) if self.clusters else \
            dr.zeros(mi.UInt32, 1)
        if lambertian_sums and self.clusters and techniques:
            self.sums = self.lambertian_clusters(pool, techniques["camera"], techniques["light"])

    def cluster_lists(self, end: str, active: mi.Bool) -> tuple[mi.UInt32, mi.UInt32]:
        """The ``active`` segments grouped by the cluster of their ``end`` (``"x"`` or ``"y"``): ``(offsets[C + 1],
        members)``, each cluster's members in index order. Every list of a pass is filtered from one stable sort
        of all segments by that end's cluster (a radix sort of one or two passes): a stable sort of a subset
        is the sorted whole with the others left out (docs/maths.md §5.2)."""
        cid = self.cid_x if end == "x" else self.cid_y
        clusters = self.clusters
        everything, sorted_cid = self._sorted[end]
        ok = dr.gather(mi.Bool, active & (cid != INVALID), everything)  # in sorted order
        dr.eval(ok)
        counts = dr.zeros(mi.UInt32, clusters + 1)
        dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), sorted_cid, ok, mode=REDUCE)
        offsets = dr.prefix_sum(counts)
        members = dr.gather(mi.UInt32, everything, dr.compress(ok))
        if dr.width(members) == 0:
            members = dr.zeros(mi.UInt32, 1)  # read by masked gathers only: kept off an empty array
        dr.eval(offsets, members)
        return offsets, members

    def sorted_reduce(self, end: str, ops: tuple, inits: tuple, value: mi.Float, masks: tuple) -> list:
        """Per cluster of each segment's ``end``, ``ops[k]`` (from ``inits[k]``) over the ``value`` of the segments
        in ``masks[k]``: in the order of the sort by that end's cluster, where neighbouring lanes reduce into one
        cluster (see :meth:`cluster_lists`)."""
        everything, sorted_cid = self._sorted[end]
        value = dr.gather(mi.Float, value, everything)
        out = []
        for op, init, mask in zip(ops, inits, masks, strict=True):
            target = dr.full(mi.Float, init, self.clusters + 1)
            dr.scatter_reduce(op, target, value, sorted_cid, dr.gather(mi.Bool, mask, everything),
                              mode=REDUCE)
            out.append(target)
        dr.eval(out)
        return [dr.reshape(mi.Float, t, max(self.clusters, 1), shrink=True) for t in out]

    def band_lists(self, pool: SegmentPool, lumped: Lumped) -> tuple[mi.UInt32, mi.UInt32, int]:
        """The grazing-band sources (``lumped.band_sources``) grouped by the cluster of their start and, within
        it, by the bin of ``|n̄·ω'|`` (``bins`` bins of ``[0, BAND)``, :data:`BAND_BINS` or fewer):
        ``(offsets[C · bins + 1], members, bins)``, so that the sources of cluster ``c`` with ``|n̄·ω'|`` below the
        upper edge of bin ``b`` are ``members[offsets[c · bins] : offsets[c · bins + b + 1]]``."""
        clusters = max(self.clusters, 1)
        bins = BAND_BINS
        if clusters * bins > BAND_CELLS:  # the largest power of two that fits (1: a cluster's whole band)
            bins = 1 << max(0, (BAND_CELLS // clusters).bit_length() - 1)
        cid = self.cid_x
        index = dr.compress(lumped.band_sources & (cid != INVALID))
        along = dr.abs(dr.dot(dr.gather(mi.Vector3f, lumped.mean, dr.gather(mi.UInt32, cid, index)),
                              dr.gather(mi.Vector3f, pool.wx, index)))
        per_bin = dr.opaque(mi.UInt32, bins)  # a kernel constant would compile anew where it changes
        bin_ = dr.minimum(mi.UInt32(along * (mi.Float(per_bin) / LAMBERTIAN_BAND)), per_bin - 1)
        key = dr.gather(mi.UInt32, cid, index) * per_bin + bin_
        cells = clusters * bins
        dr.eval(key)
        counts = dr.zeros(mi.UInt32, cells + 1)
        dr.scatter_reduce(dr.ReduceOp.Add, counts, mi.UInt32(1), key, mode=REDUCE)
        offsets = dr.prefix_sum(counts)
        members = dr.gather(mi.UInt32, index, counting_sort(key, cells.bit_length()))
        if dr.width(members) == 0:
            members = dr.zeros(mi.UInt32, 1)  # read by masked gathers only: kept off an empty array
        dr.eval(offsets, members)
        return offsets, members, bins

    def kernel_of(self, cid: mi.UInt32, active: mi.Bool) -> mi.Float:
        ok = active & (cid != INVALID)
        return dr.select(ok, dr.gather(mi.Float, self.inv_area, cid, ok), 0)

    def _lists(self, tech: Technique, lumped: bool):
        """The records of ``tech`` grouped by the cluster of their own end: those counted through the Lambertian
        sums (``lumped``) or the others (built once per pass)."""
        key = (tech.records, lumped)
        if key not in self._technique_lists:
            mask = self.techniques[tech.records]
            if self.sums is not None:
                mask = mask & (self.sums.techniques if lumped else ~self.sums.techniques)
            self._technique_lists[key] = self.cluster_lists(tech.own, mask)
        return self._technique_lists[key]

    def technique_sum(self, tech: Technique, body, point: mi.Point3f, normal: mi.Normal3f, wo: mi.Vector3f,
                      cid: mi.UInt32 | None, active: mi.Bool) -> mi.Float:
        """``K Σ_t q_t pdf_t(ω)`` over the records ``t`` of ``tech`` in the cluster of each lane's end
        (``cid``, or that of ``point``, ``normal``), ``body`` adding one ``q_t pdf_t(wo)``: explicit for the records
        that are not lumped; for the lumped ones ``max(0, N·ω)/π`` where every ``n_t·ω`` has one sign
        (``|n̄·ω| >= sin``), else explicit too (directions grazing a curved cluster)."""
        n = dr.width(active)
        if cid is None:
            cid = self.grid.cluster_of(point, normal, active)
        total = dr.zeros(mi.Float, n)
        if not dr.any(self.techniques[tech.records]):
            return total
        total = self.reduce(self._lists(tech, False), cid, body, total, active)
        sums = self.sums
        if sums is not None:
            ok = active & (cid != INVALID)
            along = dr.dot(dr.gather(mi.Vector3f, sums.mean, cid, ok), wo)
            sin = dr.gather(mi.Float, sums.sin, cid, ok)
            one_sign = ok & (dr.abs(along) >= sin)
            vec = dr.gather(mi.Vector3f, sums.cam if tech.kind == CAMERA else sums.light, cid, one_sign)
            total += dr.select(one_sign & (along > 0), dr.maximum(0, dr.dot(vec, wo)) / dr.pi, 0)
            band = ok & ~one_sign
            if dr.any(band):
                total = self.reduce(self._lists(tech, True), cid, _lumped_body(sums.records, wo), total, band)
        return total * self.kernel_of(cid, active)

    def technique_count(self, tech: Technique, point: mi.Point3f, normal: mi.Normal3f, cid: mi.UInt32 | None,
                        active: mi.Bool) -> mi.Float:
        """``K`` times the number of records of ``tech`` in the cluster of each lane's end (``cid``, or that of
        ``point``, ``normal``): the next-event techniques of a kernel domain (docs/maths.md §3.5)."""
        if cid is None:
            cid = self.grid.cluster_of(point, normal, active)
        key = ("count", tech.records)
        if key not in self._technique_lists:
            own = self.cid_x if tech.own == "x" else self.cid_y
            on = self.techniques[tech.records] & (own != INVALID)
            counts = per_cluster(dr.ReduceOp.Add, mi.UInt32, 0, mi.UInt32(1), own, on, max(self.clusters, 1))
            dr.eval(counts)
            self._technique_lists[key] = counts
        ok = active & (cid != INVALID)
        count = mi.Float(dr.gather(mi.UInt32, self._technique_lists[key], cid, ok))
        return dr.select(ok, count, 0) * self.kernel_of(cid, active)

    def reduce(self, lists, row_cid: mi.UInt32, body, state, active: mi.Bool):
        """``state = body(state, j, row)`` for every listed member ``j`` of each row's cluster, over the rows that
        have any; ``body`` adds to ``state``. The rows' lists run in pieces of at most
        :data:`~segmitsuba.grid.hashgrid.RUN_PIECE` members, one lane each, summed into their row: balanced
        lanes, and all threads busy where few rows have long lists (a lane per row left one thread busy)."""
        offsets, order = lists
        ok = active & (row_cid != INVALID)
        n = dr.width(ok)
        begin = dr.gather(mi.UInt32, offsets, row_cid, ok)
        end = dr.gather(mi.UInt32, offsets, row_cid + 1, ok)
        rows = dr.compress(ok & (end > begin))
        out = dr.zeros(type(state), n) + state
        if dr.width(rows) == 0:
            # in memory, as when some row has members: a literal would fuse into what follows as a constant,
            # a kernel of its own that pools with and without members here would each compile
            dr.make_opaque(out)
            return out
        run, start, stop = run_pieces(dr.gather(mi.UInt32, begin, rows), dr.gather(mi.UInt32, end, rows))
        # lanes reading the same piece of one list side by side: a SIMD packet then reads one member (the same
        # BSDF) at a time
        same = counting_sort(start, max(dr.width(order), 1).bit_length())
        run, start, stop = (dr.gather(mi.UInt32, a, same) for a in (run, start, stop))
        lane_row = dr.gather(mi.UInt32, rows, run)

        def step(i, st):
            return i + 1, body(st, dr.gather(mi.UInt32, order, i), lane_row)

        _, partial = dr.while_loop((start, dr.zeros(type(state), dr.width(run))), lambda i, st: i < stop, step,
                                   label="cluster members")
        dr.scatter_reduce(dr.ReduceOp.Add, out, partial, lane_row, mode=REDUCE)
        dr.eval(out)
        return out

    def system(self, estimator: MMISEstimator, pool: SegmentPool, gatherable: mi.Bool, query: mi.Bool,
               x_ok: mi.Bool, denom: mi.Float) -> MMISSystem:
        """The edges of every query: the sources (``gatherable``, ``D > 0``) starting in the cluster of its end,
        or, for Lambertian receivers, the cluster's sum ``V_C`` and its grazing band (docs/maths.md §6.3)."""
        n, sums = pool.size, self.sums
        source = gatherable & (denom > 0) & (self.cid_x != INVALID)
        q_ok = query & (self.cid_y != INVALID)
        kernel = self.kernel_of(self.cid_y, q_ok)
        lumped = self.lumped_receivers(estimator.ctx_radiance, pool, source, q_ok, kernel, denom) \
            if sums is not None else None
        listed = q_ok & ~lumped.query if lumped is not None else q_ok

        # Edges: every gatherable segment starting in the cluster of the query's end (explicit queries), or only
        # those in the grazing band of the cluster (banded receivers, docs/maths.md §6.3).
        members_off, members = self.cluster_lists("x", source)
        banded = lumped.banded if lumped is not None and dr.any(lumped.banded) else None
        has_edges = listed if banded is None else listed | banded
        c = dr.select(has_edges, self.cid_y, 0)
        # each row's range in one list of members: its cluster's, or (banded) its cluster's band after them
        lists = members
        begin, end = dr.gather(mi.UInt32, members_off, c), dr.gather(mi.UInt32, members_off, c + 1)
        if banded is not None:
            band_off, band_members, bins = self.band_lists(pool, lumped)
            per_bin = dr.opaque(mi.UInt32, bins)
            after = dr.opaque(mi.UInt32, dr.width(members))
            lists = _cat([members, band_members])
            # a receiver tilted by θ from n̄ has n_s·ω' of the sign of n̄·ω' wherever |n̄·ω'| > tan θ: there its
            # band edge would be exactly 0, so it lists the bins up to tan θ alone (widened a little for rounding)
            cos_t = dr.minimum(dr.dot(lumped.normal, dr.gather(mi.Vector3f, lumped.mean, c, banded)), 1.0)
            tan_t = dr.safe_sqrt(1 - dr.square(cos_t)) / dr.maximum(cos_t, 1e-6) * 1.001 + 1e-5
            top = dr.minimum(mi.UInt32(dr.minimum(tan_t / LAMBERTIAN_BAND, 1.0) * mi.Float(per_bin)) + 1, per_bin)
            first = c * per_bin
            begin = dr.select(banded, after + dr.gather(mi.UInt32, band_off, first, banded), begin)
            end = dr.select(banded, after + dr.gather(mi.UInt32, band_off, first + top, banded), end)
        counts = dr.select(has_edges, end - begin, 0)
        offsets = dr.prefix_sum(_cat([counts, mi.UInt32(0)]))
        total = int(dr.gather(mi.UInt32, offsets, dr.opaque(mi.UInt32, n))[0]) if n else 0
        rows, cols = None, dr.zeros(mi.UInt32, total)
        if total:
            # one lane per edge: the k-th edge of query r is the k-th member of r's range
            rows = edge_rows(offsets, has_edges, n, total)
            k = dr.arange(mi.UInt32, total) - dr.gather(mi.UInt32, offsets, rows)
            cols = dr.gather(mi.UInt32, lists, dr.gather(mi.UInt32, begin, rows) + k)
            dr.eval(cols)
        if total and banded is not None:
            # A banded receiver is Lambertian, f_r = ρ/π max(0, n_s·ω'), and its V_C term already holds
            # K ρ/π n_s·ω' / D of its front sources: its edges carry K ρ/π (max(0, n_s·ω') - [front] n_s·ω') / D
            # (its V_C term is wrong only inside the band), without a BSDF evaluation. The other rows' edges
            # evaluate their BSDF.
            in_band = dr.gather(mi.Bool, banded, rows)
            # a source's ω' and D (negative: a front source) in one packed copy, one random read per edge
            source_wd = dr.gather(mi.Array4f, pack_vector(pool.wx, dr.select(lumped.front, -denom, denom)), cols,
                                  in_band)
            cos = dr.dot(dr.gather(mi.Vector3f, lumped.normal, rows, in_band),
                         mi.Vector3f(source_wd.x, source_wd.y, source_wd.z))
            front = in_band & (source_wd.w < 0)
            weights = dr.select(in_band, dr.gather(mi.Spectrum, lumped.factor, rows, in_band)
                                * ((dr.maximum(cos, 0) - dr.select(front, cos, 0)) / dr.abs(source_wd.w)), 0)
            dr.eval(weights)  # in one kernel: the scatter below would evaluate each channel apart
            listed_edges = dr.compress(~in_band)
            if dr.width(listed_edges):
                rows_l = dr.gather(mi.UInt32, rows, listed_edges)
                dr.scatter(weights, estimator._edge_weights(pool, dr.gather(mi.UInt32, cols, listed_edges), rows_l,
                                                            denom, dr.gather(mi.Float, kernel, rows_l)),
                           listed_edges)
            dr.eval(weights)
        else:
            weights = estimator._edge_weights(pool, cols, rows, denom, dr.gather(mi.Float, kernel, rows) if total
                                              else kernel)

        receiver_cluster = None
        if lumped is not None:
            def receiver_cluster(p, n_geo, normal, lam, unlit, active):
                # the test of lumped_receivers (no band): the receiver gathers its cluster exactly through V_C
                cid = self.grid.cluster_of(p, n_geo, active)
                ok = active & lam & (cid != INVALID)
                fits, _, _ = _gathers_through_sum(normal, cid, lumped.mean, lumped.least, lumped.most, ok)
                fits |= ok & unlit
                return cid, fits, self.kernel_of(cid, fits)

        return MMISSystem(offsets=offsets, cols=cols, weights=weights, denominator=denom, rows=rows,
                          gatherable=gatherable, query=has_edges, kernel=kernel, lumped=lumped,
                          source_kernel=self.kernel_of(self.cid_x, x_ok),
                          segment_density=estimator._segment_density(pool, self, self.cid_y),
                          receiver_cluster=receiver_cluster,
                          domain_count=dr.gather(mi.UInt32, self.members, self.cid_y, self.cid_y != INVALID),
                          sparse_count=4)

    def lambertian_clusters(self, pool: SegmentPool, cam_tech: mi.Bool, light_tech: mi.Bool) -> ClusterSums:
        """Lambertian techniques summed per cluster (see the module docstring): their mean normal ``n̄``, the
        sine of their largest deviation from it, and ``Σ q_t w_t n_t`` for camera and for light techniques."""
        C = self.clusters
        is_cam = pool.kind == CAMERA
        wi = dr.select(is_cam, pool.dy, pool.wx)  # as in _density_body: the technique's arrival direction
        cid = dr.select(is_cam, self.cid_y, self.cid_x)
        lam, normal, w = _lambertian(pool.surf, wi, (cam_tech | light_tech) & (cid != INVALID))
        lit = lam & (w > 0)  # the unlit side of a one-sided BSDF has density 0: lumped, but not a normal
        # Summed per cluster in the grid's order: a record's cluster is that of its own walk vertex, a grid point,
        # so each record writes its (n_t, q_t w_t) and its bits to that point's place in cluster order (writes at
        # random do not wait) and the sums read them in order (docs/maths.md §4.4).
        n = pool.size
        packed = pack_vector(normal, w * pool.q)
        bits = (dr.select(lit, mi.UInt32(1), 0) | dr.select(lam & cam_tech, mi.UInt32(2), 0)
                | dr.select(lam & light_tech, mi.UInt32(4), 0))
        grid = self.grid
        places = grid.count  # grid points past the pool's records (emitter points) are no technique: bits 0
        ordered = dr.empty(mi.Float, 4 * places)
        ordered_bits = dr.zeros(mi.UInt32, places)
        place = dr.gather(mi.UInt32, grid.rank, dr.arange(mi.UInt32, n), lam)
        dr.scatter(ordered, mi.Array4f(normal.x, normal.y, normal.z, w * pool.q), place, lam)
        dr.scatter(ordered_bits, bits, place, lam)
        dr.eval(packed, ordered, ordered_bits)

        def record(i):
            v = dr.gather(mi.Array4f, ordered, i)
            return mi.Vector3f(v.x, v.y, v.z), v.w, dr.gather(mi.UInt32, ordered_bits, i)

        if self.scatter_sums:
            k = dr.arange(mi.UInt32, places)
            nrm, wq, b = record(k)
            nsum = dr.zeros(mi.Vector3f, C)
            dr.scatter_reduce(dr.ReduceOp.Add, nsum, nrm, grid.sorted_cluster, (b & 1) != 0, mode=REDUCE)
            mean = dr.normalize(nsum)
            dr.eval(mean)
            least, sum_cam, sum_light = dr.full(mi.Float, 1.0, C), dr.zeros(mi.Vector3f, C), dr.zeros(mi.Vector3f, C)
            cluster = grid.sorted_cluster
            dr.scatter_reduce(dr.ReduceOp.Min, least, dr.dot(nrm, dr.gather(mi.Vector3f, mean, cluster)), cluster,
                              (b & 1) != 0, mode=REDUCE)
            dr.scatter_reduce(dr.ReduceOp.Add, sum_cam, nrm * wq, cluster, (b & 2) != 0, mode=REDUCE)
            dr.scatter_reduce(dr.ReduceOp.Add, sum_light, nrm * wq, cluster, (b & 4) != 0, mode=REDUCE)
        else:
            pieces = run_pieces(grid.offsets)

            def normals(i):
                nrm, _, b = record(i)
                return (dr.select((b & 1) != 0, nrm, 0),)

            nsum = reduce_runs(normals, (mi.Vector3f,), pieces, C)[0]
            mean = dr.normalize(nsum)
            dr.eval(mean)
            lane_mean = dr.gather(mi.Vector3f, mean, pieces[0])

            def spread_and_sums(i):
                nrm, wq, b = record(i)
                return (dr.select((b & 1) != 0, dr.dot(nrm, lane_mean), 1.0),
                        dr.select((b & 2) != 0, nrm * wq, 0), dr.select((b & 4) != 0, nrm * wq, 0))

            least, sum_cam, sum_light = reduce_runs(spread_and_sums, (mi.Float, mi.Vector3f, mi.Vector3f), pieces, C,
                                                    ops=(dr.ReduceOp.Min, dr.ReduceOp.Add, dr.ReduceOp.Add))
        least = dr.minimum(least, 1.0)
        # clusters whose normals stay within 60° of their mean (normal bins already bound them)
        usable = (least > 0.5) & (dr.squared_norm(nsum) > 0)
        lumped = lam & (dr.gather(mi.Bool, usable, cid, lam) | ~lit)
        # a cluster that is not usable lumps only unlit techniques, whose w is 0
        sum_cam, sum_light = dr.select(usable, sum_cam, 0), dr.select(usable, sum_light, 0)
        sums = ClusterSums(techniques=lumped, mean=dr.select(usable, mean, 0),
                           sin=dr.select(usable, dr.safe_sqrt(1 - dr.square(dr.minimum(least, 1))), 2.0),
                           cam=sum_cam, light=sum_light, records=packed)
        dr.eval(sums.techniques, sums.mean, sums.sin, sums.cam, sums.light)
        return sums

    def lumped_receivers(self, ctx: mi.BSDFContext, pool: SegmentPool, source: mi.Bool, query: mi.Bool,
                         kernel: mi.Float, denom: mi.Float) -> Lumped:
        """Lambertian queries gathered through ``K ρ/π n_s · V_C``, ``V_C`` summed over the sources with
        ``n̄·ω' >= 0``. Exact when every such source is on the receiver's side and every other source behind
        it (contributing 0): with ``θ`` the angle between ``n_s`` and ``n̄``, ``m`` the least ``n̄·ω'`` of the
        first kind and ``M`` the largest of the second, ``n_s·ω' >= m cos θ - sin θ >= 0`` and
        ``n_s·ω' <= M cos θ + sin θ <= 0``. On a flat patch (``θ = 0``) every Lambertian receiver qualifies."""
        n, C, sums = pool.size, self.clusters, self.sums
        along = dr.dot(dr.gather(mi.Vector3f, sums.mean, self.cid_x, source), pool.wx)
        front = source & (along >= 0)
        dr.eval(along)
        least, most = self.sorted_reduce("x", (dr.ReduceOp.Min, dr.ReduceOp.Max), (1e30, -1e30), along,
                                         (front, source & ~front))
        ys = pool.end_surface("y", dr.arange(mi.UInt32, n), query)
        lam, normal, w = _lambertian(ys, pool.dy, query)
        ok, cos_t, sin_t = _gathers_through_sum(normal, self.cid_y, sums.mean, least, most, lam)
        ok |= lam & (w == 0)  # seen from its unlit side: it gathers nothing (factor 0)
        # Banded: tilted from n̄ by at most atan(BAND). Sources with n̄·ω' >= BAND are then on its side and those
        # with n̄·ω' <= -BAND behind it, so V_C is exact for all but the band |n̄·ω'| < BAND, whose few (grazing)
        # sources it lists explicitly (mostly faces of two planes sharing a cluster, docs/maths.md §6.3).
        banded = lam & ~ok & (cos_t > 0) & (LAMBERTIAN_BAND * cos_t >= sin_t)
        ok |= banded
        si = ys.interaction(pool.dy)
        albedo = si.bsdf().eval(ctx, si, si.to_local(normal), ok)  # ρ/π (cosine 1)
        offsets, order = self.cluster_lists("x", front)
        # ω'/D of the sources in cluster order, read at random through one packed copy
        wd = dr.gather(mi.Array4f, pack_vector(pool.wx, denom), order)
        weight = mi.Vector3f(wd.x, wd.y, wd.z) / wd.w
        lumped = Lumped(query=ok, factor=dr.select(ok, albedo * kernel, 0), normal=normal, cluster=self.cid_y,
                        sources=order, source_weight=weight,
                        source_pieces=None if self.scatter_sums else run_pieces(offsets),
                        source_cluster=dr.gather(mi.UInt32, self.cid_x, order) if self.scatter_sums else None,
                        clusters=C,
                        banded=banded, front=front, band_sources=source & (dr.abs(along) < LAMBERTIAN_BAND),
                        least=least, most=most, mean=sums.mean, members=self.members, start_cluster=self.cid_x)
        dr.eval(lumped.query, lumped.factor, lumped.normal, lumped.sources, lumped.source_weight, lumped.banded,
                lumped.band_sources, lumped.source_cluster)
        return lumped


class _RadiusKernel:
    """The radius kernel (docs/maths.md §5.1): a disc of radius ``r`` around each end, ``K = 1/(π r²)``."""

    #: ends carry no cluster: the discs are around each point
    cid_x = cid_y = None

    def __init__(self, pool: SegmentPool, radius: float, seed: int, x_ok: mi.Bool, y_ok: mi.Bool,
                 techniques: dict, lambertian_sums: bool = False):
        self.radius = radius
        self.kernel = 1.0 / (dr.pi * radius**2)
        self.techniques = techniques
        #: per set of technique records, a grid over their own ends
        self.grids = {t.records: RadiusGrid(getattr(pool, t.own), radius, active=techniques[t.records])
                      for t in TECHNIQUES if t.of is None and t.records in techniques
                      and dr.any(techniques[t.records])}

    def technique_sum(self, tech: Technique, body, point: mi.Point3f, normal: mi.Normal3f, wo: mi.Vector3f,
                      cid: mi.UInt32 | None, active: mi.Bool) -> mi.Float:
        """``K Σ_t q_t pdf_t(wo)`` over the records ``t`` of ``tech`` within ``r`` of each lane's ``point``."""
        total = dr.zeros(mi.Float, dr.width(active))
        grid = self.grids.get(tech.records)
        if grid is None:
            return total
        total = grid.reduce(point, lambda st, j, pj, d2: body(st, j), total, active=active)
        dr.eval(total)
        return total * self.kernel

    def technique_count(self, tech: Technique, point: mi.Point3f, normal: mi.Normal3f, cid: mi.UInt32 | None,
                        active: mi.Bool) -> mi.Float:
        """``K`` times the number of records of ``tech`` within ``r`` of each lane's ``point``."""
        return self.technique_sum(tech, lambda st, j: st + 1.0, point, normal, None, None, active)

    def system(self, estimator: MMISEstimator, pool: SegmentPool, gatherable: mi.Bool, query: mi.Bool,
               x_ok: mi.Bool, denom: mi.Float) -> MMISSystem:
        """The edges of every query: the sources (``gatherable``, ``D > 0``) starting within ``r`` of its end."""
        n = pool.size
        grid = RadiusGrid(pool.x, self.radius, active=gatherable & (denom > 0))
        offsets, cols = grid.neighbors(pool.y, active=query)
        rows = edge_rows(offsets, query, n, dr.width(cols)) if dr.width(cols) else None
        weights = estimator._edge_weights(pool, cols, rows, denom, dr.opaque(mi.Float, self.kernel))
        idx = dr.arange(mi.UInt32, n)
        domain = dr.gather(mi.UInt32, offsets, idx + 1) - dr.gather(mi.UInt32, offsets, idx)
        return MMISSystem(offsets=offsets, cols=cols, weights=weights, denominator=denom, rows=rows,
                          gatherable=gatherable, query=query, kernel=dr.full(mi.Float, self.kernel, n),
                          source_kernel=dr.full(mi.Float, self.kernel, n),
                          segment_density=estimator._segment_density(pool, self, None), domain_count=domain,
                          sparse_count=2)


#: the kernels by name (``kernel``): each sums techniques into ``D`` and builds the edges of a pool
KERNELS = {"cluster": _ClusterKernel, "radius": _RadiusKernel}


@dataclass
class MMISSystem:
    """The linear system of one pass: edges (CSR by query segment) with their weights."""

    offsets: mi.UInt32
    cols: mi.UInt32
    weights: mi.Spectrum
    denominator: mi.Float
    gatherable: mi.Bool
    query: mi.Bool
    kernel: mi.Float  #: K of each query's kernel domain (1/(π r²), or 1/A(C) of its cluster)
    lumped: Lumped | None = None  #: queries gathered through Lambertian cluster sums (cluster kernel)
    source_kernel: mi.Float | None = None  #: K of each segment's start (its gatherers' kernel)
    #: ``D`` of new segments leaving the ends ``y`` of given segments (next-event samples, docs/maths.md §4.7)
    segment_density: Callable | None = None
    #: the query of every edge (:func:`edge_rows`)
    rows: mi.UInt32 | None = None
    #: Lambertian receivers outside the pool (final gathering, docs/maths.md §4.9): ``(points, geometric
    #: normals, oriented shading normals, Lambertian, unlit, active) -> (cluster, gathered through V_C, K)``
    receiver_cluster: Callable | None = None
    #: with private glossy vertices: the segments arriving at one (their walk surface is glossy), else None
    glossy: mi.Bool | None = None
    #: per query, how many segments its kernel domain holds: its cluster's segment ends (two per walk vertex) or
    #: its disc's sources (one per vertex); None where unknown
    domain_count: mi.UInt32 | None = None
    #: the count at or below which a domain is sparse: about two walk vertices, the query's own and one more
    sparse_count: int = 0

    @property
    def edge_count(self) -> int:
        return dr.width(self.cols)

    @property
    def lumped_count(self) -> int:
        return 0 if self.lumped is None else int(dr.count(self.lumped.query)[0])

    def sparse_share(self) -> float:
        """The share of the queries whose kernel domain holds at most about two walk vertices: pools that sparse
        bias ``segment_bdf`` upwards (docs/maths.md §8.1, item 4). One reduction; call it once per render call."""
        if self.domain_count is None:
            return 0.0
        queries = self.query if self.lumped is None else self.query | self.lumped.query
        total = int(dr.count(queries)[0])
        if total == 0:
            return 0.0
        return int(dr.count(queries & (self.domain_count <= self.sparse_count))[0]) / total


@dataclass
class Lumped:
    """Lambertian receivers that gather a whole cluster through its sum ``V_C`` (see the module docstring)."""

    query: mi.Bool  #: receivers gathered this way (all but the banded ones have no explicit edges)
    factor: mi.Spectrum  #: K ρ/π of each receiver
    normal: mi.Vector3f  #: each receiver's oriented shading normal
    cluster: mi.UInt32  #: each receiver's cluster
    sources: mi.UInt32  #: segments summed into their start's cluster (n̄·ω' >= 0), sorted by cluster
    source_weight: mi.Vector3f  #: ``ω' / D(s')`` of each of them (fixed over the solve's iterations)
    #: the runs of ``sources`` per cluster in pieces (:func:`~segmitsuba.grid.run_pieces`), or None where the sums
    #: scatter by ``source_cluster`` (:func:`~segmitsuba.grid.scatter_sorted_runs`)
    source_pieces: tuple[mi.UInt32, mi.UInt32, mi.UInt32] | None
    source_cluster: mi.UInt32 | None  #: the cluster of each of ``sources`` where the sums scatter, or None
    clusters: int
    #: receivers lumped only outside the grazing band ``|n̄·ω'| < BAND``: they list the band's sources explicitly
    banded: mi.Bool | None = None
    front: mi.Bool | None = None  #: the segments summed into ``V_C`` (per segment)
    band_sources: mi.Bool | None = None  #: sources in the grazing band of their cluster
    #: per cluster: the least ``n̄·ω'`` of the sources summed into ``V_C`` and the largest of the others (the
    #: receiver test), and ``n̄``
    least: mi.Float | None = None
    most: mi.Float | None = None
    mean: mi.Vector3f | None = None
    members: mi.UInt32 | None = None  #: segment ends in each cluster
    start_cluster: mi.UInt32 | None = None  #: the cluster of each segment's start x


@dataclass
class ClusterSums:
    """Lambertian techniques lumped per cluster."""

    techniques: mi.Bool  #: techniques counted through the sums (not listed)
    mean: mi.Vector3f  #: n̄: mean normal of each cluster's Lambertian techniques (0: nothing lumped)
    sin: mi.Float  #: sine of their largest angle to n̄
    cam: mi.Vector3f  #: Σ q_t w_t n_t of the camera techniques
    light: mi.Vector3f  #: the same for the light techniques
    #: ``(n_t, q_t w_t)`` of every record, packed (:func:`pack_vector`): a lumped record's ``q_t pdf_t(ω)`` is
    #: ``q_t w_t max(0, n_t·ω)/π``
    records: mi.Float | None = None


def _lambertian(surf: Surface, wi: mi.Vector3f, active: mi.Bool) -> tuple[mi.Bool, mi.Vector3f, mi.Float]:
    """Where the BSDF on ``surf`` (seen from ``wi``) is Lambertian: its oriented shading normal and its density
    scale ``π pdf(n)`` (1 on the lit side of a diffuse BSDF, 0 where it reflects nothing). Checked by value
    too: the density must be ``cos/π`` at two directions."""
    return lambertian_at(surf.interaction(wi), active)  # an invalid surface gives an invalid interaction


def lambertian_at(si: mi.SurfaceInteraction3f, active: mi.Bool) -> tuple[mi.Bool, mi.Vector3f, mi.Float]:
    """:func:`_lambertian` of an interaction (``si.wi`` set)."""
    bsdf = si.bsdf()
    flags = bsdf.flags()
    lobes = (mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) & ~mi.has_flag(flags, mi.BSDFFlags.Glossy)
             & ~mi.has_flag(flags, mi.BSDFFlags.Delta) & ~mi.has_flag(flags, mi.BSDFFlags.DiffuseTransmission)
             & ~mi.has_flag(flags, mi.BSDFFlags.Null))
    active = active & si.is_valid() & lobes
    side = dr.select(mi.Frame3f.cos_theta(si.wi) < 0, -1.0, 1.0)
    ctx = mi.BSDFContext(mi.TransportMode.Radiance)
    p_up = bsdf.pdf(ctx, si, mi.Vector3f(0, 0, side), active)
    p_tilt = bsdf.pdf(ctx, si, mi.Vector3f(0.6, 0, 0.8 * side), active)
    ok = active & (dr.abs(p_tilt - 0.8 * p_up) <= 1e-4 * p_up) & (dr.abs(p_up * dr.pi - 1) < 1e-3)
    ok |= active & (p_up == 0) & (p_tilt == 0)  # the unlit side of a one-sided diffuse BSDF: density 0
    normal = si.to_world(mi.Vector3f(0, 0, side))
    return ok, normal, dr.select(ok, p_up * dr.pi, 0.0)


def per_cluster(op: dr.ReduceOp, tp: type, init: float | int, value, index: mi.UInt32, active: mi.Bool,
                size: int):
    """``size`` entries of type ``tp`` set to ``init``, each reduced by ``op`` with the ``value`` of every
    ``active`` lane whose ``index`` it is. For indices in no particular order into a small array (a cluster's
    counts, least and largest values): ``ReduceMode.Expand`` reduces into a copy per thread, where a local
    reduction found few equal neighbours and paid an atomic per lane (a count over Cornell's 1.1M segment ends:
    8 -> 2.5 ms); other backends than LLVM take ``Auto``. Expand compiles its target's size into the kernel,
    so the target is padded to a power of two: pools of similar cluster counts reuse one kernel."""
    padded = 1 << max(size - 1, 1).bit_length()
    target = dr.full(tp, init, padded)
    dr.scatter_reduce(op, target, value, index, active, mode=dr.ReduceMode.Expand)
    dr.eval(target)  # the expanded copies are combined into the target here: a view taken before reads it early
    return dr.reshape(tp, target, size, shrink=True)


def _gathers_through_sum(normal: mi.Vector3f, cid: mi.UInt32, mean: mi.Vector3f, least: mi.Float, most: mi.Float,
                         active: mi.Bool) -> tuple[mi.Bool, mi.Float, mi.Float]:
    """Whether a Lambertian receiver (oriented normal ``normal``) in cluster ``cid`` gathers it exactly through
    ``V_C`` (see ``_ClusterKernel.lumped_receivers``), and the cosine and sine of its tilt from ``n̄``."""
    cos_t = dr.minimum(dr.dot(normal, dr.gather(mi.Vector3f, mean, cid, active)), 1.0)
    sin_t = dr.safe_sqrt(1 - dr.square(cos_t))
    exact = (active & (cos_t > 0) & (dr.gather(mi.Float, least, cid, active) * cos_t >= sin_t)
             & (-dr.gather(mi.Float, most, cid, active) * cos_t >= sin_t))
    return exact, cos_t, sin_t


def edge_rows(offsets: mi.UInt32, active: mi.Bool, n: int, edges: int) -> mi.UInt32:
    """The row of every entry of a CSR list (``active``: the rows that may have entries)."""
    idx = dr.arange(mi.UInt32, n)
    rows = dr.compress(active & (dr.gather(mi.UInt32, offsets, idx + 1) > dr.gather(mi.UInt32, offsets, idx)))
    first = dr.zeros(mi.UInt32, edges)
    dr.scatter(first, 1, dr.gather(mi.UInt32, offsets, rows))
    out = dr.gather(mi.UInt32, rows, dr.cumsum(first) - 1)
    dr.eval(out)
    return out


@dataclass
class EdgeSubset:
    """The edges of some queries alone: a sweep for them reads and sums nothing else."""

    queries: mi.Bool  #: per segment: its query is in the subset
    rows: mi.UInt32 | None  #: None where the subset has no edge
    cols: mi.UInt32 | None
    weights: mi.Spectrum | None


def edge_subset(system: MMISSystem, queries: mi.Bool) -> EdgeSubset:
    """The edges of ``queries`` (in their order, each query's edges still consecutive)."""
    keep = None if system.rows is None else dr.compress(dr.gather(mi.Bool, queries, system.rows))
    if keep is None or dr.width(keep) == 0:
        return EdgeSubset(queries=queries, rows=None, cols=None, weights=None)
    subset = EdgeSubset(queries=queries, rows=dr.gather(mi.UInt32, system.rows, keep),
                        cols=dr.gather(mi.UInt32, system.cols, keep),
                        weights=dr.gather(mi.Spectrum, system.weights, keep))
    dr.eval(subset.rows, subset.cols, subset.weights)
    return subset


def _sweep_edges(system: MMISSystem, only: EdgeSubset | None) -> tuple | None:
    """``(weights, cols, rows)`` of the edges a sweep runs over: the system's, or those of ``only``; None where
    there are none."""
    if system.rows is None or (only is not None and only.rows is None):
        return None
    return (system.weights, system.cols, system.rows) if only is None else (only.weights, only.cols, only.rows)


def _packed_type() -> type:
    """The type of one packed entry of a spectrum: 4 floats (RGB padded, or spectral) or 1 (monochrome)."""
    return mi.Float if dr.size_v(mi.Spectrum) == 1 else mi.Array4f


def _packed_width() -> int:
    return 1 if _packed_type() is mi.Float else 4


def pack(values: mi.Spectrum) -> mi.Float:
    """``values`` interleaved in one flat array, 4 floats per entry (RGB padded with 0): a random read of an
    entry is then one 16-byte load instead of one cache miss per channel. The solve's random reads (edges,
    cluster sources) take 2.5x less time this way on AVX2 CPUs."""
    n = dr.width(values)
    flat = dr.empty(mi.Float, n * _packed_width())  # every entry is written below
    pack_into(flat, values, dr.arange(mi.UInt32, n))
    dr.eval(flat)
    return flat


def packed_zeros(n: int) -> mi.Float:
    """A :func:`pack`-ed array of ``n`` zero entries."""
    return dr.zeros(mi.Float, n * _packed_width())


def pack_into(flat: mi.Float, values: mi.Spectrum, index: mi.UInt32) -> None:
    """Write ``values`` into entries ``index`` of a :func:`pack`-ed array."""
    if _packed_type() is mi.Float:
        dr.scatter(flat, mi.Float(values[0] if dr.depth_v(values) > 1 else values), index)
    else:
        c = dr.size_v(mi.Spectrum)
        dr.scatter(flat, mi.Array4f(*(values[k] if k < c else 0 for k in range(4))), index)


def pack_vector(v: mi.Vector3f, w: mi.Float) -> mi.Float:
    """``(v, w)`` of every entry interleaved in one flat array, read at random as one ``mi.Array4f`` per entry."""
    n = dr.width(v)
    flat = dr.empty(mi.Float, 4 * n)
    dr.scatter(flat, mi.Array4f(v.x, v.y, v.z, w), dr.arange(mi.UInt32, n))
    dr.eval(flat)
    return flat


def unpack(flat: mi.Float, index: mi.UInt32, active: mi.Bool | bool = True) -> mi.Spectrum:
    """Entries ``index`` of a :func:`pack`-ed array."""
    tp = _packed_type()
    v = dr.gather(tp, flat, index, active)
    if tp is mi.Float:
        return mi.Spectrum(v)
    return mi.Spectrum(*(v[k] for k in range(dr.size_v(mi.Spectrum))))


class MMISEstimator:
    def __init__(self, scene: mi.Scene, radius: float, light_paths: int, kernel: str = "radius", seed: int = 0,
                 lambertian_sums: bool = True, private_glossy: bool = False, light_delta_chains_only: bool = False,
                 next_event: bool = False, all_sources: bool = False):
        """``radius``: the disc radius of the radius kernel, or the voxel side of the cluster kernel (``kernel``, a
        name of :data:`KERNELS`).
        ``lambertian_sums``: use the exact Lambertian cluster sums (cluster kernel only). ``private_glossy``: the
        camera walks continue privately from glossy vertices (``RandomWalk.private_glossy``), which then gather
        nothing (docs/maths.md §4.8). ``light_delta_chains_only``: the light walks keep only segments through a
        delta vertex past their first (``RandomWalk.delta_chains_only``), so the light technique makes no
        straight segment (docs/maths.md §2.5). ``next_event``: every camera technique also took one emitter sample
        (:func:`~segmitsuba.population.record_next_event`), whose density enters the ``D`` of the emission that
        straight segments carry from emitters (docs/maths.md §3.5). ``all_sources``: every gatherable segment is
        a source, also those whose estimate is 0 at every level, which are left out otherwise (the same
        estimate; the identity of docs/maths.md §4.2 sums over all of them)."""
        self.next_event = next_event
        self.all_sources = all_sources
        self.techniques = tuple(
            replace(t, straight=not light_delta_chains_only) if t.density == "bsdf" and t.kind == LIGHT else t
            for t in TECHNIQUES if t.density != "next_event" or next_event)
        self.lambertian_sums = lambertian_sums
        self.private_glossy = private_glossy
        self.scene = scene
        self.radius = float(radius)
        self.kernel_type = kernel
        self.seed = seed
        self.light_paths = light_paths
        self.ctx_radiance = mi.BSDFContext(mi.TransportMode.Radiance)
        self.ctx_importance = mi.BSDFContext(mi.TransportMode.Importance)

    # -- the system ---------------------------------------------------------------------------------------

    def build(self, pool: SegmentPool) -> MMISSystem:
        n = pool.size
        x_surf = pool.end_surface("x", dr.arange(mi.UInt32, n), dr.full(mi.Bool, True, n))
        y_surf = pool.end_surface("y", dr.arange(mi.UInt32, n), dr.full(mi.Bool, True, n))
        gatherable = (pool.x_surf != INVALID) & x_surf.smooth & ~pool.private & ~pool.delta_emit
        # a delta-emitter segment is gathered too, but no other technique can produce it
        gatherable_any = (pool.x_surf != INVALID) & x_surf.smooth & ~pool.private
        query = (pool.y_surf != INVALID) & y_surf.smooth
        glossy = None
        if self.private_glossy:
            # Glossy vertices gather nothing: what leaves one toward the camera is carried by the camera walk's
            # private continuation. So no technique there makes sources (a camera walk's child from it is
            # private; a light walk's child from it would need a gather there), and a light segment leaving one
            # is no source: it would miss the light scattered there (docs/maths.md §4.8).
            glossy = pool.surf.valid & glossy_vertex(pool.surf.shape.bsdf())
            dr.eval(glossy)
            lit_y = (pool.kind == LIGHT) & (pool.y_surf < dr.opaque(mi.UInt32, n))
            glossy_y = dr.select(pool.kind == CAMERA, glossy, dr.gather(mi.Bool, glossy, pool.y_surf, lit_y) & lit_y)
            query &= ~glossy_y
            no_source = (pool.kind == LIGHT) & glossy_y
            gatherable &= ~no_source
            gatherable_any &= ~no_source
        # a next-event segment's attempt is false: it is no technique
        tech = technique_records(pool.attempt, pool.surf, glossy)
        cam_tech, light_tech = (pool.kind == CAMERA) & tech, (pool.kind == LIGHT) & tech
        # where y is a point in the scene: a camera segment's own arrival, unless it escaped (Mitsuba then
        # reports the origin with a zero normal, which must not enter any cluster or its area)
        y_known = (pool.kind == LIGHT) | ((pool.y_surf != INVALID) & pool.surf.valid)
        if pool.next_event_count:  # on an emitter surface, not an environment's
            y_known |= (pool.kind == NEXT_EVENT) & ~mi.has_flag(pool.emitter.flags(), mi.EmitterFlags.Infinite)

        # A segment whose estimate is 0 at every level adds nothing where it is gathered: one without emission
        # that gathers nothing and is no camera row of the direct light (docs/maths.md §4.7; a camera segment
        # with a private child ends on a smooth surface, so it is one), such as a camera segment that left a
        # scene without an environment. It is no source, and its D is not needed.
        row = (pool.kind == CAMERA) & (pool.y_surf != INVALID) & y_surf.smooth
        carries = query | row | dr.any(mi.unpolarized_spectrum(pool.le) != 0)
        sources = gatherable_any if self.all_sources else gatherable_any & carries
        dr.eval(gatherable, sources, query, cam_tech, light_tech)
        techniques = {"camera": cam_tech, "light": light_tech}
        x_ok = pool.x_surf != INVALID
        kern = KERNELS[self.kernel_type](pool, self.radius, self.seed, x_ok, y_known, techniques,
                                         self.lambertian_sums)  # emission y: on the emitter
        ends = Ends(x=pool.x, nx=pool.nx, wx=pool.wx, y=pool.y, ny=pool.ny, dy=pool.dy, x_known=x_ok,
                    y_known=y_known, absorbed=pool.absorbed, straight=pool.straight, cid_x=kern.cid_x,
                    cid_y=kern.cid_y, delta=pool.delta_emit)
        nee_units = None
        if self.next_event:
            # Next-event segments end only on emitters that reflect nothing, so D of a segment ending on one is
            # that of all the light it carries (§3.5).
            on = x_ok & pool.straight & (pool.emitter != None)  # noqa: E711 (Dr.Jit pointer test)
            si_y = y_surf.interaction(pool.dy)
            ends.emits = on & ~reflects(si_y, si_y.bsdf(), on & y_surf.valid)
            ends.emitter_sample = emitter_sample_of(pool)
            ratio, known = photon_to_next_event(self.scene, pool.emitter, pool.x, pool.y, ends.emits & pool.delta_emit)
            if self.light_paths == 0:
                # no photons: every delta emitter's next-event segments are its only technique past the sharp
                # rows, D = K n whatever the photon ratio would be (a projector's is not known)
                unknown = ends.emits & pool.delta_emit & ~known
                ratio, known = dr.select(unknown, 1.0, ratio), known | unknown
            ends.delta_ratio = dr.select(known, ratio, 0)
            # a photon carries W_e = ρ w, a next-event segment of a delta emitter w (its sample weight)
            nee_units = known & (pool.kind == NEXT_EVENT)
        denom = self._density(pool, kern, ends, sources, pool.emit_factor)
        if nee_units is not None:
            denom = dr.select(nee_units, denom / dr.maximum(ends.delta_ratio, 1e-30), denom)
        dr.eval(denom)
        system = kern.system(self, pool, sources, query, x_ok, denom)
        system.glossy = glossy
        return system

    def _density(self, pool: SegmentPool, kern, ends: Ends, active: mi.Bool, emit_factor: mi.Float) -> mi.Float:
        """``D`` of ``ends`` (docs/maths.md §4.2) where ``active``, in the ``(x, ω)`` measure of their gathered
        end ``x``: the sum over the estimator's techniques (:data:`TECHNIQUES`) of each one's density, through the
        kernel ``kern`` at the end where it would have started them and converted to that measure.
        ``emit_factor``: the emission technique's density over ``N_e cos_x`` (``N_e`` light sub-paths)."""
        cos_x = dr.abs(dr.dot(ends.nx, ends.wx))
        d = dr.zeros(mi.Float, dr.width(active))
        delta = ends.delta if ends.delta is not None else mi.Bool(False)
        for tech in self.techniques:
            point, normal, wo, known, cid = ends.at(tech.end)
            on = active & known
            if not tech.absorbed and ends.absorbed is not None:
                on &= ~ends.absorbed
            if not tech.straight:
                if ends.straight is None:
                    continue
                on &= ~ends.straight
            if tech.emission_only:
                if ends.emits is None:
                    continue
                on &= ends.emits
            if tech.density == "emission":
                # a delta emitter's segment: this technique alone, in photon units
                d += dr.select(active, self.light_paths * cos_x * dr.select(delta, 1.0, emit_factor), 0)
            elif tech.density == "next_event":
                on &= ~delta | (ends.delta_ratio > 0)
                count = kern.technique_count(tech, point, normal, cid, on)
                x_it = point_interaction(ends.x, ends.nx, pool.surf.time, pool.surf.wavelengths)
                p_e = self.scene.pdf_emitter_direction(x_it, ends.emitter_sample, on & ~delta)
                d += dr.select(on, count * dr.select(delta, ends.delta_ratio, p_e), 0)
            else:
                ctx = self.ctx_radiance if tech.mode == "radiance" else self.ctx_importance
                on &= ~delta  # no BSDF sample makes a segment from a delta emitter
                term = kern.technique_sum(tech, _density_body(pool, tech, wo, ctx), point, normal, wo, cid, on)
                if tech.end == "y":  # sampled in the measure of y: to that of x (§3.2)
                    term *= cos_x / dr.maximum(dr.abs(dr.dot(ends.ny, ends.dy)), 1e-8)
                d += term
        return d

    def _segment_density(self, pool: SegmentPool, kern, cid_start: mi.UInt32 | None) -> Callable:
        """``segment_density(rows, wo, z, nz, z_known, emit_factor)``: ``D`` of the segments that would leave the
        ends ``y`` of the pool's segments ``rows`` along ``wo`` and end at ``z`` (next-event samples, §4.7)."""

        def segment_density(rows, wo, z, nz, z_known, emit_factor):
            ends = Ends(x=pool.y, nx=pool.ny, wx=wo, y=z, ny=nz, dy=-wo, x_known=rows, y_known=z_known,
                        cid_x=cid_start)
            # rows only: elsewhere ``wo`` may be anything (an emitter sample that failed), NaN included
            return dr.select(rows, self._density(pool, kern, ends, rows, emit_factor), 0)

        return segment_density

    def _edge_weights(self, pool: SegmentPool, cols, rows, denom, kernel) -> mi.Spectrum:
        """``K f_r(s, s') / D(s')`` for every edge (one lane each; ``rows``: its query, :func:`edge_rows`), with
        f_r the BSDF at ``y_s`` (cosine included); ``kernel``: K per edge, or one opaque value."""
        if rows is None:
            return dr.zeros(mi.Spectrum, dr.width(cols))
        ys = pool.end_surface("y", rows, True)
        si = ys.interaction(dr.gather(mi.Vector3f, pool.dy, rows))
        f = si.bsdf().eval(self.ctx_radiance, si, si.to_local(dr.gather(mi.Vector3f, pool.wx, cols)))
        weights = f * kernel / dr.gather(mi.Float, denom, cols)
        dr.eval(weights)
        return weights

    # -- the solve ----------------------------------------------------------------------------------------

    @staticmethod
    def _gather_lumped(system: MMISSystem, pool: SegmentPool, prev: mi.Spectrum, final=None,
                       packed: mi.Float | None = None,
                       queries: mi.Bool | None = None) -> tuple[mi.Spectrum, mi.Spectrum | None]:
        """``K ρ/π n_C · V_C`` for the lumped receivers (of ``queries`` alone, where given), ``V_C = Σ ω' L̂(s')/D(s')``
        over the cluster (:meth:`_cluster_sums`). ``final`` (:class:`~segmitsuba.estimators.direct.FinalGather`):
        receivers outside the pool, whose ``factor · n · V_C`` summed into their rows is returned apart (None
        without)."""
        lp = system.lumped
        if dr.width(lp.sources) == 0:
            return dr.zeros(mi.Spectrum, pool.size), None
        vx, vy, vz = MMISEstimator._cluster_sums(lp, prev if packed is None else packed)

        # every receiver reads its cluster's three sums: packed, three loads instead of nine
        vx, vy, vz = pack(vx), pack(vy), pack(vz)

        def dot_v(cluster, normal, active):
            return (unpack(vx, cluster, active) * normal.x + unpack(vy, cluster, active) * normal.y
                    + unpack(vz, cluster, active) * normal.z)

        on = lp.query if queries is None else lp.query & queries
        out = dr.select(on, lp.factor * dot_v(lp.cluster, lp.normal, on), 0)
        extra = None
        if final is not None and dr.width(final.row):
            extra = dr.zeros(mi.Spectrum, pool.size)
            dr.scatter_reduce(dr.ReduceOp.Add, extra, final.factor * dot_v(final.cluster, final.normal, True),
                              final.row, mode=REDUCE)
            dr.eval(extra)
        return out, extra

    @staticmethod
    def _cluster_sums(lp: Lumped, values: mi.Spectrum | mi.Float,
                      offset: mi.UInt32 | int = 0) -> tuple[mi.Spectrum, mi.Spectrum, mi.Spectrum]:
        """The three components of ``V_C = Σ ω' values(s') / D(s')`` of every cluster: the sources are in cluster
        order, each cluster a run that :func:`~segmitsuba.grid.reduce_runs` adds in pieces. ``values``: per
        segment, or :func:`pack`-ed (segment ``s`` at entry ``offset + s``)."""
        if isinstance(values, mi.Spectrum):
            values = pack(values)
        value = unpack(values, lp.sources + offset)
        dr.eval(value)  # the random reads apart: fused into the sums' kernel they cost more than alone
        if lp.source_pieces is None:
            vx, vy, vz = (dr.zeros(mi.Spectrum, lp.clusters) for _ in range(3))
            w = lp.source_weight
            for target, wk in ((vx, w.x), (vy, w.y), (vz, w.z)):
                dr.scatter_reduce(dr.ReduceOp.Add, target, value * wk, lp.source_cluster, mode=REDUCE)
        else:
            def weighted(i):
                v, w = dr.gather(mi.Spectrum, value, i), dr.gather(mi.Vector3f, lp.source_weight, i)
                return v * w.x, v * w.y, v * w.z

            vx, vy, vz = reduce_runs(weighted, (mi.Spectrum,) * 3, lp.source_pieces, lp.clusters)
        dr.eval(vx, vy, vz)
        return vx, vy, vz

    def _gather(self, system: MMISSystem, pool: SegmentPool, prev: mi.Spectrum, final=None,
                only: EdgeSubset | None = None) -> tuple[mi.Spectrum, mi.Spectrum | None]:
        """``Σ_{s'} K f_r(s, s') prev(s') / D(s')`` for every query ``s`` (explicit edges and lumped sums), and
        apart the final gathering of ``final`` from the same ``prev`` (None without). With ``only``, for its
        queries alone (0 elsewhere)."""
        gathered = dr.zeros(mi.Spectrum, pool.size)
        packed = None
        edges = _sweep_edges(system, only)
        if edges is not None:
            # one lane per edge, summed into its query: the edges of a query are consecutive, so the local
            # (per SIMD packet) reduction leaves about one atomic per packet (3x faster than a loop per query);
            # the weighted reads are evaluated apart (fused with the scatter they cost 1.5x as much on AVX2)
            packed = pack(prev)
            weights, cols, rows = edges
            terms = weights * unpack(packed, cols)
            dr.eval(terms)
            dr.scatter_reduce(dr.ReduceOp.Add, gathered, terms, rows, mode=REDUCE)
            dr.eval(gathered)  # alone: fused with a sweep of the same width, it would compile a kernel per size
        extra = None
        if system.lumped is not None:
            lumped, extra = self._gather_lumped(system, pool, prev, final, packed,
                                                None if only is None else only.queries)
            gathered += lumped
        return gathered, extra

    def gather(self, system: MMISSystem, pool: SegmentPool, values: mi.Spectrum,
               only: EdgeSubset | None = None) -> mi.Spectrum:
        """``(A values)(s) = Σ_{s'} K f_r(s, s') values(s') / D(s')`` for every query ``s`` (one sweep), or for
        the queries of ``only`` alone (0 elsewhere)."""
        return self._gather(system, pool, values, only=only)[0]

    def solve(self, pool: SegmentPool, system: MMISSystem, iterations: int, emitted: mi.Spectrum,
              direct=None, read: EdgeSubset | None = None) -> mi.Spectrum:
        """``L̂`` of every segment over the paths of at most ``iterations + 1`` rays (docs/maths.md §4.4):
        ``iterations`` levels of ``L̂ = T (Le + A L̂ + private)`` from ``L̂ = T Le``, where a query spanning
        ``r`` rays (a delta chain) gathers the level ``r`` back. ``read`` (:func:`edge_subset`): the segments
        whose ``L̂`` the caller reads; the last level is then computed for them alone, and the result is 0
        elsewhere (what the last level gathers elsewhere reaches no pixel, docs/maths.md §4.4).

        ``direct`` (:class:`~segmitsuba.estimators.direct.DirectLight`): at its rows, the sampled direct light
        takes the place of its share of the gathered emission (docs/maths.md §4.7); that gathered part does not
        change over the levels."""
        base = pool.chain * emitted
        correction = None
        if direct is not None and dr.any(direct.rows):
            # read at the rows alone
            covered, _ = self._gather(system, pool, base * direct.covered, only=edge_subset(system, direct.rows))
            correction = dr.select(direct.rows, direct.value - covered, 0)
            dr.eval(correction)
        if direct is not None and direct.delta is not None:
            correction = direct.delta if correction is None else correction + direct.delta
            dr.eval(correction)
        # A camera segment that left a mixed vertex through its delta lobe feeds only its own parent (its
        # sequential continuation). Light-side private segments (left an emissive mixed vertex, which light
        # walks do not absorb) point the other way and feed nothing: camera walks cover those lobes (§2.3).
        private = pool.private & (pool.parent != INVALID) & (pool.kind == CAMERA)
        has_private = dr.any(private)
        # a private child whose emission the direct light of its parent already holds feeds only the rest
        counted = direct.counted if direct is not None and direct.counted is not None else None
        final = direct.final if direct is not None else None
        # a private child shares the directions its parent's final gathering covers (docs/maths.md §4.9)
        lead = pool.lead if final is None else pool.lead * final.child_scale
        if has_private:
            # Each parent reads its private child by a gather: a camera walk absorbs no vertex, so a camera
            # segment has at most one child, and a gather costs a fraction of an atomic scatter per lane.
            child = dr.full(mi.UInt32, INVALID, pool.size)
            dr.scatter(child, dr.arange(mi.UInt32, pool.size), pool.parent, private)
            has_child = child != INVALID
            child_lead = dr.gather(mi.Spectrum, lead, child, has_child)
            child_base = None if counted is None else dr.select(
                dr.gather(mi.Bool, counted, child, has_child), dr.gather(mi.Spectrum, base, child, has_child), 0)
            dr.eval(child, child_lead, child_base)
        rays = segment_rays(pool)
        span = int(dr.max(rays)[0]) if pool.size else 1
        levels = (_RayLevels(pool, system, rays, span, final) if span >= RAY_LEVELS_FROM
                  else _LastLevel(self, pool, system, final))
        radiance = levels.first(base)
        # Where every segment spans one ray the correction joins every level the same way: added to the
        # emission once, one array less to read per level
        closed_base = base
        if correction is not None and isinstance(levels, _LastLevel):
            closed_base, correction = base + correction, None
            dr.eval(closed_base)
        #: L̂ before the last level: what the last one gathered (light tracing splits it, docs/maths.md §4.11)
        self.previous = radiance
        for level in range(2, iterations + 2):
            self.previous = radiance
            levels.store(level - 1, radiance)
            last = level == iterations + 1
            gathered = levels.gather(level, read if last else None, last)
            if correction is not None:
                gathered += correction
            if has_private:
                feed = levels.read(child, level, has_child)
                gathered += child_lead * (feed if child_base is None else feed - child_base)
            radiance = levels.close(level, closed_base, pool.chain, gathered)
            if last and read is not None:
                radiance = dr.select(read.queries, radiance, 0)
            dr.eval(radiance)
        return radiance


def segment_rays(pool: SegmentPool) -> mi.UInt32:
    """The rays of every segment (several through a delta chain): its walk depth less that of its start,
    the sensor at depth -1 for camera segments and the emitter at 0 for light segments (docs/maths.md §2.4)."""
    has_parent = pool.parent != INVALID
    start = dr.gather(mi.UInt32, pool.depth, pool.parent, has_parent)
    return dr.select(has_parent, pool.depth - start, dr.select(pool.kind == CAMERA, pool.depth + 1, pool.depth))


class _LastLevel:
    """The levels of the solve where every segment spans one ray: level ``j`` gathers level ``j - 1`` alone (the
    plain fixed-point iteration), and a row's final gathering reads ``V_C`` one level late, as its child's gather
    reaches it one level late through the child: both then stop at the same path depth."""

    def __init__(self, estimator: MMISEstimator, pool: SegmentPool, system: MMISSystem, final=None):
        self.estimator, self.pool, self.system, self.final = estimator, pool, system, final
        self.last: mi.Spectrum | None = None
        self.final_prev: mi.Spectrum | None = None

    @staticmethod
    def first(base: mi.Spectrum) -> mi.Spectrum:
        """Level 1: the emission of every segment."""
        radiance = mi.Spectrum(base)
        dr.eval(radiance)
        return radiance

    def store(self, level: int, radiance: mi.Spectrum) -> None:
        self.last = radiance

    def read(self, index: mi.UInt32, level: int, active: mi.Bool) -> mi.Spectrum:
        """Level ``level - 1`` of ``L̂`` at ``index`` (a private child's feed)."""
        return dr.gather(mi.Spectrum, self.last, index, active)

    def gather(self, level: int, only: EdgeSubset | None = None, last: bool = False) -> mi.Spectrum:
        """What level ``level`` gathers (for the queries of ``only`` alone, where given); at the ``last`` level the
        final gathering, which the next level would read, is not made."""
        gathered, final_now = self.estimator._gather(self.system, self.pool, self.last,
                                                     None if last else self.final, only)
        if self.final_prev is not None:
            gathered += self.final_prev
        self.final_prev = final_now
        return gathered

    @staticmethod
    def close(level: int, base: mi.Spectrum, chain: mi.Spectrum, gathered: mi.Spectrum) -> mi.Spectrum:
        """``base + gathered``: a segment of one ray holds no delta vertex, so its ``chain`` is 1."""
        return base + gathered


class _RayLevels:
    """The last levels of the solve where segments span several rays (docs/maths.md §4.4): level ``b`` of
    ``L̂(s)`` holds the paths of at most ``b`` rays from the start of ``s``, and a query spanning ``r(s)`` rays
    gathers level ``j - r(s)`` into its level ``j`` (its final gathering, one ray more, level ``j - r(s) - 1``).
    ``L̂`` and the cluster sums ``V_C`` of the last ``span + 1`` levels are kept in rings, one slot per level;
    reads of level 0 or below give 0."""

    def __init__(self, pool: SegmentPool, system: MMISSystem, rays: mi.UInt32, span: int, final=None):
        self.system, self.rays = system, rays
        self.n = pool.size
        self.slots = span + 1
        self.radiance = packed_zeros(self.n * self.slots)  # read at random: packed
        lp = system.lumped
        self.sums = None
        if lp is not None and dr.width(lp.sources):
            self.sums = [packed_zeros(lp.clusters * self.slots) for _ in range(3)]  # read per receiver: packed
        # per edge: the rays of its query (the level it reads back); per final-gathering sample: its row's
        self.edge_rays = None if system.rows is None else dr.gather(mi.UInt32, rays, system.rows)
        self.final = final if self.sums is not None and final is not None and dr.width(final.row) else None
        self.final_rays = None if self.final is None else dr.gather(mi.UInt32, rays, final.row)
        dr.eval(self.edge_rays, self.final_rays)

    def first(self, base: mi.Spectrum) -> mi.Spectrum:
        """Level 1: the emission of the segments that span one ray."""
        radiance = dr.select(self.rays <= 1, base, 0)
        dr.eval(radiance)
        return radiance

    def close(self, level: int, base: mi.Spectrum, chain: mi.Spectrum, gathered: mi.Spectrum) -> mi.Spectrum:
        """Level ``level`` of ``L̂``: a query spanning ``level`` rays or more gathers nothing yet, and one spanning
        more emits nothing."""
        return dr.select(self.rays <= level, base + chain * dr.select(self.rays < level, gathered, 0), 0)

    def _slot(self, level: mi.UInt32, size: int) -> mi.UInt32:
        return (level % dr.opaque(mi.UInt32, self.slots)) * dr.opaque(mi.UInt32, size)

    def store(self, level: int, radiance: mi.Spectrum) -> None:
        """Keep level ``level`` of ``L̂`` (and of the cluster sums over it)."""
        at = dr.opaque(mi.UInt32, level)
        pack_into(self.radiance, radiance, dr.arange(mi.UInt32, self.n) + self._slot(at, self.n))
        if self.sums is not None:
            lp = self.system.lumped
            dr.eval(self.radiance)  # the sums read this level back from the ring: packed once
            offset = self._slot(at, lp.clusters)
            sums = MMISEstimator._cluster_sums(lp, self.radiance, self._slot(at, self.n))
            for ring, v in zip(self.sums, sums, strict=True):
                pack_into(ring, v, dr.arange(mi.UInt32, lp.clusters) + offset)
        dr.eval(self.radiance, *(self.sums or ()))

    def _subset_rays(self, only: EdgeSubset) -> mi.UInt32:
        """The rays of the query of every edge of ``only``."""
        rays = dr.gather(mi.UInt32, self.rays, only.rows)
        dr.eval(rays)
        return rays

    def _back(self, level: int, rays: mi.UInt32, extra: int = 0) -> tuple[mi.UInt32, mi.Bool]:
        at = dr.opaque(mi.UInt32, level - extra)
        return at - rays, rays < at

    def read(self, index: mi.UInt32, level: int, active: mi.Bool) -> mi.Spectrum:
        """Level ``level - r(p)`` of ``L̂`` at ``index`` for every segment ``p`` (its private child's feed)."""
        back, ok = self._back(level, self.rays)
        return unpack(self.radiance, index + self._slot(back, self.n), active & ok)

    def _dot_sums(self, cluster: mi.UInt32, normal: mi.Vector3f, back: mi.UInt32, active: mi.Bool) -> mi.Spectrum:
        at = cluster + self._slot(back, self.system.lumped.clusters)
        vx, vy, vz = (unpack(ring, at, active) for ring in self.sums)
        return vx * normal.x + vy * normal.y + vz * normal.z

    def gather(self, level: int, only: EdgeSubset | None = None, last: bool = False) -> mi.Spectrum:
        """What every query (of ``only`` alone, where given) gathers into its level ``level``: the explicit edges
        and the cluster sums at level ``level - r(s)``, and its final gathering at ``level - r(s) - 1``."""
        system = self.system
        gathered = dr.zeros(mi.Spectrum, self.n)
        edges = _sweep_edges(system, only)
        if edges is not None:
            weights, cols, rows = edges
            edge_rays = self.edge_rays if only is None else self._subset_rays(only)
            back, ok = self._back(level, edge_rays)
            terms = weights * unpack(self.radiance, cols + self._slot(back, self.n), ok)
            dr.eval(terms)  # apart from the scatter, as in MMISEstimator._gather
            dr.scatter_reduce(dr.ReduceOp.Add, gathered, terms, rows, mode=REDUCE)
            dr.eval(gathered)
        if self.sums is not None:
            lp = system.lumped
            back, ok = self._back(level, self.rays)
            on = lp.query & ok if only is None else lp.query & ok & only.queries
            gathered += dr.select(on, lp.factor * self._dot_sums(lp.cluster, lp.normal, back, on), 0)
            final = self.final
            if final is not None:
                back, ok = self._back(level, self.final_rays, extra=1)
                if only is not None:
                    ok &= dr.gather(mi.Bool, only.queries, final.row)
                extra = dr.zeros(mi.Spectrum, self.n)
                dr.scatter_reduce(dr.ReduceOp.Add, extra,
                                  dr.select(ok, final.factor * self._dot_sums(final.cluster, final.normal, back, ok),
                                            0), final.row, mode=REDUCE)
                gathered += extra
        dr.eval(gathered)
        return gathered
