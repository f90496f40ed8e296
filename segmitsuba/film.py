"""Film and sampler plumbing shared by every integrator (Mitsuba's conventions)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


def prepare_sampler(sensor: mi.Sensor, seed: int, spp: int, wavefront_size: int) -> mi.Sampler:
    """A clone of the sensor's sampler, seeded for one wavefront of ``wavefront_size`` samples."""
    sampler = sensor.sampler().clone()
    sampler.set_sample_count(spp)
    sampler.set_samples_per_wavefront(spp)
    if wavefront_size >= 2**32:
        raise RuntimeError(
            f"a pass of {wavefront_size} samples exceeds Dr.Jit's 2^32 wavefront limit: use fewer samples "
            "per pass (e.g. render with lower spp in several passes)"
        )
    sampler.seed(seed, wavefront_size)
    return sampler


def film_sample_count(film: mi.Film) -> int:
    size = film.crop_size()
    if film.sample_border():
        size += 2 * film.rfilter().border_size()
    return int(dr.prod(size))


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


def develop_film(film: mi.Film, block: mi.ImageBlock, develop: bool, evaluate: bool) -> mi.TensorXf:
    """Commit ``block`` to the film and develop it, as ``Integrator.render`` promises."""
    film.put_block(block)
    if not develop:
        return mi.TensorXf()
    image = film.develop()
    if evaluate:
        dr.eval(image)
    return image
