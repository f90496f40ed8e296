"""Film and sampler plumbing shared by every integrator (Mitsuba's conventions)."""

from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi


def _takes_sample_count(sampler: mi.Sampler, spp: int) -> bool:
    """Whether ``sampler`` generates exactly ``spp`` samples per pixel: stratified, low-discrepancy, multi-jitter
    and orthogonal samplers round the count to their own lattices (Mitsuba warns and renders the rounded count)."""
    if sampler.class_name() == "IndependentSampler":
        return True
    probe = sampler.clone()
    logger = mi.logger()
    level = logger.log_level()
    logger.set_log_level(mi.LogLevel.Error)  # the probe's rounding warning is not the user's concern
    try:
        probe.set_sample_count(spp)
    finally:
        logger.set_log_level(level)
    return probe.sample_count() == spp


def prepare_sampler(sensor: mi.Sensor, seed: int, spp: int, wavefront_size: int) -> mi.Sampler:
    """A clone of the sensor's sampler, seeded for one wavefront of ``wavefront_size`` samples. A sampler that
    cannot generate ``spp`` samples per pixel (a pass or pool of 2 spp from a stratified one) is replaced by an
    ``independent`` one for this wavefront: a pass must render the samples it was given."""
    sampler = sensor.sampler().clone()
    if not _takes_sample_count(sampler, spp):
        warnings.warn(f"the sensor's {sampler.class_name()} cannot generate every sample count that passes and "
                      "pools use (it rounds them to its own lattice); those use an independent sampler",
                      RuntimeWarning, stacklevel=2)
        sampler = mi.load_dict({"type": "independent"})
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    if wavefront_size >= 2**32:
        raise RuntimeError(
            f"a pass of {wavefront_size} samples exceeds Dr.Jit's 2^32 wavefront limit: use fewer samples "
            "per pass (e.g. render with lower spp in several passes)"
        )
    sampler.seed(seed, wavefront_size)
    return sampler


def film_sample_size(film: mi.Film) -> mi.ScalarVector2u:
    """Width and height of the grid of film samples: the crop window, and the filter's border where the film
    samples it."""
    size = film.crop_size()
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    return size


def film_sample_count(film: mi.Film) -> int:
    return int(dr.prod(film_sample_size(film)))


def film_lattice(film: mi.Film, groups: int, group: int) -> mi.UInt32:
    """The film samples (raster indices, as :func:`film_sample_count` counts them) of lattice ``group`` of
    ``groups`` (a power of two): every ``a``-th column and ``b``-th row, ``a b = groups``, ``a`` = ``b`` or ``2 b``,
    offset by ``group``. The lattices split the film into near-equal parts, and each spreads evenly over it."""
    if groups & (groups - 1) or not 0 <= group < groups:
        raise ValueError(f"group {group} of {groups}: groups must be a power of two above the group")
    size = film_sample_size(film)
    j = groups.bit_length() - 1
    a, b = 1 << ((j + 1) // 2), 1 << (j // 2)
    idx = dr.arange(mi.UInt32, int(dr.prod(size)))
    y = idx // int(size[0])
    x = idx - y * int(size[0])
    # opaque: one kernel for every group
    keep = ((x & (a - 1)) == dr.opaque(mi.UInt32, group % a)) & ((y & (b - 1)) == dr.opaque(mi.UInt32, group // a))
    return dr.compress(keep)


def to_rgb(value: mi.Spectrum, wavelengths) -> mi.Color3f:
    if mi.is_polarized:
        value = mi.unpolarized_spectrum(value)
    if mi.is_spectral:
        return mi.spectrum_to_srgb(value, wavelengths)
    if mi.is_monochromatic:
        return mi.Color3f(value.x)
    return value


def splat_camera_samples(film: mi.Film, block: mi.ImageBlock, pos: mi.Vector2f, value: mi.Spectrum,
                         wavelengths, alpha: mi.Float) -> None:
    """Accumulate camera samples (weight 1) into ``block`` with the film's channel layout."""
    rgb = to_rgb(value, wavelengths)
    if mi.has_flag(film.flags(), mi.FilmFlags.Alpha):
        block.put(pos, [rgb.x, rgb.y, rgb.z, alpha, mi.Float(1.0)])
    else:
        block.put(pos, [rgb.x, rgb.y, rgb.z, mi.Float(1.0)])


class FilmTarget:
    """Where one ``render()`` call's samples go: a camera block (samples of weight 1, normalized by their
    filter weights) and a light block (splats from light tracing, scaled by ``light_scale``), each created
    on first use, developed apart and summed, as Mitsuba's ``ptracer`` and ``path`` do.

    ``normalize_light`` divides the light image by the filter coverage of each pixel (:func:`splat_coverage`),
    so that it follows the camera samples' convention at the film border when both are summed; Mitsuba's
    ``ptracer`` does not (and neither does ``segment_lt``, which matches it).
    """

    def __init__(self, film: mi.Film, spp: int, normalize_light: bool = False):
        self.film = film
        self.spp = spp
        self.normalize_light = normalize_light
        self._camera: mi.ImageBlock | None = None
        self._light: mi.ImageBlock | None = None
        self._apart: mi.ImageBlock | None = None
        #: factor of the light block in the image: a render that ends before all of ``spp`` (a filter's
        #: ``time_budget``) scales its light splats to the samples it took
        self.light_factor = 1.0
        film.prepare([])

    @property
    def camera_block(self) -> mi.ImageBlock:
        if self._camera is None:
            self._camera = self.film.create_block()
            self._camera.set_offset(self.film.crop_offset())  # absolute positions (Mitsuba's prb forgets this)
            self._camera.set_coalesce(self._camera.coalesce() and self.spp >= 4)
        return self._camera

    @property
    def apart_block(self) -> mi.ImageBlock:
        """Camera samples of a part of the light apart from the camera block's (weight 1, normalized by their
        own filter weights, then added): the filters' sharp direct light (docs/maths.md §4.10)."""
        if self._apart is None:
            self._apart = self.film.create_block()
            self._apart.set_offset(self.film.crop_offset())
            self._apart.set_coalesce(False)
        return self._apart

    @property
    def light_block(self) -> mi.ImageBlock:
        if self._light is None:
            self._light = self.film.create_block(mi.ScalarVector2u(0), True, False)
            self._light.set_offset(self.film.crop_offset())
            self._light.set_coalesce(False)
        return self._light

    def light_scale(self, count: int) -> mi.Float:
        """Weight of one splat of ``count`` light sub-paths (opaque: no kernel recompiles when it changes)."""
        return dr.opaque(mi.Float, float(dr.prod(self.film.crop_size())) / count)

    def splat_camera(self, pos: mi.Vector2f, value: mi.Spectrum, wavelengths, alpha: mi.Float) -> None:
        splat_camera_samples(self.film, self.camera_block, pos, value, wavelengths, alpha)

    def splat_apart(self, pos: mi.Vector2f, value: mi.Spectrum, wavelengths) -> None:
        """Camera samples into :attr:`apart_block`; their alpha is the camera block's."""
        splat_camera_samples(self.film, self.apart_block, pos, value, wavelengths, dr.zeros(mi.Float, dr.width(pos)))

    def develop(self, develop: bool, evaluate: bool) -> mi.TensorXf:
        """Commit the blocks and develop them, as ``Integrator.render`` promises."""
        blocks = [b for b in (self._camera, self._light, self._apart) if b is not None] or [self.camera_block]
        if not develop:
            # Mitsuba's contract (as path and ptracer): the samples are in the film, whose develop() gives the
            # image later, and nothing is returned.
            if len(blocks) > 1:
                self._merge_into_film()
            else:
                self.film.put_block(blocks[0])
            self.film.schedule_storage()
            if evaluate:
                dr.eval()
            return mi.TensorXf()
        image = None
        for block in blocks:
            part = self._develop_block(block, evaluate=len(blocks) > 1)
            image = part if image is None else image + part
        if evaluate:
            dr.eval(image)
        return image

    def develop_apart(self) -> tuple[mi.TensorXf, mi.TensorXf]:
        """The image without :attr:`apart_block`'s samples and the image of those alone (zero if none)."""
        rest = None
        for block in (self.camera_block, self._light):
            if block is not None:
                part = self._develop_block(block)
                rest = part if rest is None else rest + part
        apart = self._develop_block(self._apart) if self._apart is not None else dr.zeros(mi.TensorXf, rest.shape)
        return rest, apart

    def _develop_block(self, block: mi.ImageBlock, evaluate: bool = True) -> mi.TensorXf:
        """One block developed through the film (which it leaves holding that block) as part of the image;
        ``evaluate`` before the film is reused for another block."""
        self.film.prepare([])
        self.film.put_block(block)
        part = self.film.develop()
        if block is self._light and self.normalize_light:
            part = part / coverage(self.film, block)
        if block is self._light and self.light_factor != 1.0:
            part = part * self.light_factor
        if evaluate:
            dr.eval(part)
        return part


    def _merge_into_film(self) -> None:
        """Put both blocks into the film's one storage so that ``film.develop()`` gives the same image as
        ``develop()``: ``I_cam + I_LT / c_p``. The film divides every channel by the accumulated filter weight
        ``W`` of the camera samples (the light block's weight channel is 0), so the light block goes in
        multiplied by ``W / c_p`` per pixel. Pixels without camera weight would lose their splats; every pixel
        has camera samples of positive weight."""
        apart = None
        if self._apart is not None:
            # the apart samples as an image normalized by their own weights, its weight channel 0
            self.film.prepare([])
            self.film.put_block(self._apart)
            raw = self.film.develop(raw=True)
            h, w, c = raw.shape
            own = dr.repeat(dr.gather(mi.Float, raw.array, dr.arange(mi.UInt32, h * w) * c + (c - 1)), c)
            last = (dr.arange(mi.UInt32, h * w * c) % c) == c - 1
            apart = dr.select(last, 0.0, raw.array / dr.maximum(own, 1e-30))
            dr.eval(apart)
        self.film.prepare([])
        self.film.put_block(self.camera_block)
        raw = self.film.develop(raw=True)  # the film's storage: channels summed, last one the weight
        h, w, c = raw.shape
        weight = dr.gather(mi.Float, raw.array, dr.arange(mi.UInt32, h * w) * c + (c - 1))
        scale = dr.repeat(weight, c)  # per pixel, for each of its channels
        parts = []
        if self._light is not None:
            light_weight = weight / coverage(self.film, self._light).array if self.normalize_light else weight
            light_weight = light_weight * self.light_factor
            light = self._light.tensor()
            parts.append((light.array * dr.repeat(light_weight, c), light.shape, self._light.offset()))
        if apart is not None:
            parts.append((apart * scale, (h, w, c), self.film.crop_offset()))
        for values, shape, offset in parts:
            merged = mi.ImageBlock(mi.TensorXf(values, shape), offset, self.film.rfilter(), border=False,
                                   normalize=True, coalesce=False)
            dr.eval(merged.tensor())
            self.film.put_block(merged)


_COVERAGE: dict[tuple, mi.TensorXf] = {}


def coverage(film: mi.Film, block: mi.ImageBlock) -> mi.TensorXf:
    """:func:`splat_coverage`, cached per variant, film crop and reconstruction filter."""
    key = (mi.variant(), tuple(film.crop_size()), tuple(film.crop_offset()), str(film.rfilter()))
    if key not in _COVERAGE:
        _COVERAGE.clear()  # one film at a time is the common case: keep the cache small
        _COVERAGE[key] = splat_coverage(film, block)
    return _COVERAGE[key]


def splat_coverage(film: mi.Film, block: mi.ImageBlock, per_axis: int = 8) -> mi.TensorXf:
    """Fraction of each pixel's reconstruction filter that splats from inside the film can reach (1 away from
    the borders; 1 everywhere for a box filter), as an ``H x W x 1`` tensor.

    Camera samples are normalized by their accumulated filter weights, so a border pixel averages only the
    film positions that exist; splatted light-tracing samples are not, and lose the part of the filter that
    falls off the film (Mitsuba's ``ptracer`` images are darker at the borders than ``path``'s for non-box
    filters). Dividing a splatted image by this coverage makes the two agree. Computed by splatting a
    stratified grid of unit samples through a block configured like ``block``.
    """
    size = film.crop_size()
    w, h = int(size[0]), int(size[1])
    probe = film.create_block(mi.ScalarVector2u(0), True, False)
    probe.set_offset(block.offset())
    probe.set_coalesce(False)
    k = per_axis
    idx = dr.arange(mi.UInt32, w * h * k * k)
    sub = idx % (k * k)
    pixel = idx // (k * k)
    pos = mi.Vector2f(mi.Float(pixel % w) + (mi.Float(sub % k) + 0.5) / k,
                      mi.Float(pixel // w) + (mi.Float(sub // k) + 0.5) / k)
    pos += mi.Vector2f(block.offset())
    ones = dr.full(mi.Float, 1.0, dr.width(idx))
    channels = probe.channel_count()
    values = [ones] + [dr.zeros(mi.Float, dr.width(idx))] * (channels - 1)
    probe.put(pos, values)
    coverage = probe.tensor().array
    coverage = dr.gather(mi.Float, coverage, dr.arange(mi.UInt32, w * h) * channels) / (k * k)
    return mi.TensorXf(coverage, shape=(h, w, 1))
