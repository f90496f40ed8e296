"""Hash grids in Dr.Jit arrays: fixed-radius neighbour search and jittered voxel clusters (docs/maths.md §5)."""

from __future__ import annotations

from .hashgrid import (
    INVALID,
    ClusterGrid,
    RadiusGrid,
    counting_sort,
    normal_bin,
    plane_cube_area,
    random_offset,
    reduce_runs,
    run_pieces,
    scatter_sorted_runs,
)

__all__ = [
    "INVALID",
    "ClusterGrid",
    "RadiusGrid",
    "counting_sort",
    "normal_bin",
    "plane_cube_area",
    "random_offset",
    "reduce_runs",
    "run_pieces",
    "scatter_sorted_runs",
]
