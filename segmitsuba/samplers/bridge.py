"""Bridge segment sampler: a segment joining a camera-side end and a light-side start (talk: "importance-sample
the two kernel functions defined by a pair of segments ... very much like the connections in classic path
sampling").

With zero-radius kernels, as in every estimator of this package, sampling the two kernels returns their
centres, so the bridge is the straight segment between the camera sub-path's end ``y_t`` and the light
sub-path's start ``x_u``: the segment analogue of a BDPT connection. Its density is a product of the two end
densities that the sequential samplers already paid for; the bridge itself only adds the visibility test and
the geometry of the straight segment. A bridge can never contain a delta interaction: generalized segments
through mirrors or glass are produced by the sequential samplers only.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class Bridge:
    """The straight segment from a camera-side point to a light-side point."""

    d: mi.Vector3f  #: unit direction, camera end -> light end
    dist2: mi.Float  #: squared length
    cos_camera: mi.Float  #: |geometric normal . d| at the camera end
    cos_light: mi.Float  #: |geometric normal . d| at the light end
    visible: mi.Bool  #: nothing blocks the segment (and it has a length)


def bridge(scene: mi.Scene, camera_end: mi.SurfaceInteraction3f, light_p: mi.Point3f, light_n: mi.Normal3f,
           active: mi.Bool) -> Bridge:
    """Sample the bridge segment between ``camera_end`` and the point ``light_p`` (normal ``light_n``)."""
    delta = light_p - camera_end.p
    dist2 = dr.squared_norm(delta)
    active = active & (dist2 > 0)
    d = delta * dr.rsqrt(dr.maximum(dist2, 1e-30))
    ray = camera_end.spawn_ray_to(light_p)
    visible = active & ~scene.ray_test(ray, active)
    return Bridge(d=d, dist2=dist2, cos_camera=dr.abs(dr.dot(camera_end.n, d)), cos_light=dr.abs(dr.dot(light_n, d)),
                  visible=visible)
