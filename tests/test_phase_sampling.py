"""The band-limited ("phase") sampler of the colour-line cost (`processing.cost`): shifts against scipy's Fourier
shift, the noise it keeps at every fractional shift, and the cost it gives against the written-out measure."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.ndimage
from mca_scenes import texture
from test_cost import reference_cost
from test_noise_model import noisy_plane

from mca.devices.profiles import load_profile
from mca.processing.cost import channel_shifts, cost_at, cost_volume, shift_band_limited, shift_taps, stack_bands
from mca.processing.features import feature_bands

APERTURE = load_profile("paper-70d").aperture


def fourier_sampler(plane: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Exact band-limited sampling at one uniform offset (mx - x, my - y), by scipy's Fourier shift (periodic)."""
    dx = float(mx[0, 0])
    dy = float(my[0, 0])
    moved = scipy.ndimage.fourier_shift(np.fft.fft2(plane), (-dy, -dx))
    return np.real(np.fft.ifft2(moved))


def periodic_texture(shape: tuple[int, int], seed: int) -> np.ndarray:
    """A smooth random texture that is periodic over the image (its spectrum cut at 0.6 of Nyquist), so that a
    Fourier shift is the exact answer everywhere but near the borders, where ours repeats the edge."""
    rng = np.random.default_rng(seed)
    spectrum = np.fft.fft2(rng.normal(size=shape + (3,)), axes=(0, 1))
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.fftfreq(shape[1])[None, :]
    spectrum[(np.abs(fy) > 0.3) | (np.abs(fx) > 0.3)] = 0
    planes = np.real(np.fft.ifft2(spectrum, axes=(0, 1)))
    planes = 0.3 + 0.05 * planes / planes.std()
    return planes.astype(np.float32)


@pytest.mark.parametrize("dx, dy", [(0.25, 0.0), (0.0, 0.5), (-1.375, 0.0), (0.0, 2.875), (0.3, -0.7)])
def test_a_shift_is_scipys_fourier_shift_inside_the_image(dx, dy):
    plane = periodic_texture((64, 96), 1)[..., 0].astype(np.float64)
    got = shift_band_limited(plane.astype(np.float32), dx, dy)
    ys, xs = np.mgrid[0:64, 0:96].astype(np.float64)
    expected = fourier_sampler(plane, xs + dx, ys + dy)
    inner = (slice(12, -12), slice(12, -12))
    assert np.abs(got[inner] - expected[inner]).max() < 2e-3 * plane.std() * 10


@pytest.mark.parametrize("axis", [0, 1])
def test_a_fractional_shift_is_the_taps_convolved_with_the_mirrored_image_up_to_its_borders(axis):
    """Against numpy in float64, borders included: the taps at offsets -7..8 read the image mirrored at its edges
    (the edge pixel repeated, "fedcba|abcdef"), along x or along y alone."""
    plane = periodic_texture((40, 52), 3)[..., 0]
    taps = shift_taps(0.375).astype(np.float64)
    got = shift_band_limited(plane, 0.375, 0.0) if axis == 0 else shift_band_limited(plane, 0.0, 0.375)
    lines = plane.astype(np.float64) if axis == 0 else plane.astype(np.float64).T
    padded = np.pad(lines, ((0, 0), (7, 8)), mode="symmetric")
    expected = sum(taps[k] * padded[:, k : k + lines.shape[1]] for k in range(16))
    expected = expected if axis == 0 else expected.T
    assert np.abs(got - expected).max() < 1e-6


def test_whole_pixel_shifts_repeat_the_border_and_the_taps_sum_to_one():
    plane = np.arange(20, dtype=np.float32)[None, :].repeat(3, axis=0)
    assert np.array_equal(shift_band_limited(plane, 2.0, 0.0)[0], np.r_[np.arange(2, 20), 19, 19])
    assert np.array_equal(shift_band_limited(plane, -1.0, 0.0)[0], np.r_[0, np.arange(0, 19)])
    for fraction in (0.0, 0.125, 0.5, 0.875):
        assert abs(float(shift_taps(fraction).sum()) - 1.0) < 1e-6


@pytest.mark.parametrize("band", [0, 1, 2])
def test_the_bands_noise_keeps_its_variance_at_every_fractional_shift(band):
    """What the sampler exists for: bilinear sampling halfway between pixels takes a third or more of a band's
    noise variance away, a band-limited shift a few per cent at most."""
    rng = np.random.default_rng(2)
    bands = feature_bands(np.clip(0.3 + 0.02 * rng.normal(size=(300, 400, 3)), 1e-3, None).astype(np.float32))
    plane = np.ascontiguousarray(bands[band][..., 0])
    inner = (slice(30, -30), slice(30, -30))
    before = plane[inner].var()
    for fraction in (0.25, 0.5, 0.75):
        kept = shift_band_limited(plane, fraction, 0.0)[inner].var() / before
        assert 0.95 < kept < 1.01, (fraction, kept)
    halfway = (0.5 * (plane + np.roll(plane, -1, axis=1)))[inner].var() / before
    assert halfway < 0.9  # bilinear sampling halfway, for contrast


def test_the_volume_is_the_measure_written_out_with_fourier_shifts():
    planes = periodic_texture((72, 96), 3)
    bands = feature_bands(planes)
    shifts = channel_shifts(APERTURE)
    candidates = np.arange(-1.5, 2.01, 0.5)
    volume = cost_volume(stack_bands(bands), APERTURE, candidates, 7, 2e-3, sampling="phase")
    inner = (slice(16, -16), slice(16, -16))
    for k, d in enumerate(candidates):
        expected = reference_cost(bands, shifts, float(d), 7, 2e-3, sample=fourier_sampler)
        assert np.abs(volume[k][inner] - expected[inner]).max() < 5e-3, d


def spline_sampler(plane: np.ndarray, mx: np.ndarray, my: np.ndarray) -> np.ndarray:
    """Per-pixel interpolating quintic spline (scipy), near band-limited on a texture without fine detail."""
    return scipy.ndimage.map_coordinates(plane, [my, mx], order=5, mode="nearest")


def test_per_pixel_maps_equal_the_volume_at_constant_disparity():
    bands = stack_bands(feature_bands(texture((48, 64), 3, blur_px=1.2)))
    candidates = np.arange(-1.0, 1.51, 0.25)
    volume = cost_volume(bands, APERTURE, candidates, 9, 2e-3, sampling="phase")
    maps = np.stack([np.full((48, 64), d, np.float32) for d in candidates])
    at = cost_at(bands, APERTURE, maps, 9, 2e-3, sampling="phase")
    inner = (slice(None), slice(8, -8), slice(8, -8))
    assert np.abs(at[inner] - volume[inner]).max() < 1e-5


def test_per_pixel_maps_at_varying_disparity_match_the_written_out_measure():
    """A slanted map with a step (every fractional shift met): bands shifted 1/8 px apart and blended, against
    each pixel sampled on its own by scipy's interpolating spline."""
    h, w = 64, 96
    bands = feature_bands(periodic_texture((h, w), 4))
    ys, xs = np.mgrid[0:h, 0:w]
    ramp = (-2.0 + 0.037 * xs + 0.021 * ys + np.where(xs > 50, 0.9, 0.0)).astype(np.float32)
    got = cost_at(stack_bands(bands), APERTURE, ramp[None], 7, 2e-3, sampling="phase")[0]
    expected = reference_cost(bands, channel_shifts(APERTURE), ramp.astype(np.float64), 7, 2e-3, sample=spline_sampler)
    inner = (slice(14, -14), slice(14, -14))
    assert np.abs(got[inner] - expected[inner]).max() < 3e-3  # bilinear sampling: 0.09


def test_strips_give_the_costs_of_the_whole_image(monkeypatch):
    """Per-pixel maps are costed strip by strip (`cost._PHASE_STRIP_ROWS`), each strip's shifted bands made for
    the rows it reads: the costs are those of one strip over the whole image (to the float32 rounding of the
    windows' running sums, which start again at each strip). The maps move green up to 8 rows up and down across strip
    boundaries and off the image's top and bottom."""
    from mca.processing import cost

    h, w = 230, 64
    bands = stack_bands(feature_bands(texture((h, w), 5, blur_px=1.2)))
    ys, xs = np.mgrid[0:h, 0:w]
    wave = 12.0 * np.sin(ys / 17.0) + 0.03 * xs  # green moves half the disparity along y: up to 7.2 rows
    maps = np.stack([wave, wave + 0.4, -wave]).astype(np.float32)
    sampled: list[tuple[int, int, int]] = []  # (axis, first, last): the rows a strip's channel samples
    made: list[tuple[int, int]] = []  # the rows whose shifted bands were made for it
    phase_rows, phase_strip = cost._phase_rows, cost._phase_strip

    def rows_spy(h, axis, rows):
        sampled.append((axis, *rows))
        return phase_rows(h, axis, rows)

    def strip_spy(bands, c, axis, span, out):
        made.append(span)
        return phase_strip(bands, c, axis, span, out)

    monkeypatch.setattr(cost, "_phase_rows", rows_spy)
    monkeypatch.setattr(cost, "_phase_strip", strip_spy)
    strips = cost_at(bands, APERTURE, maps, 9, 2e-3, sampling="phase")
    assert len(made) == 3 * 3  # 3 strips of 96 rows, 3 moving channels each
    assert max(last - first for _, first, last in sampled) <= 96 + 2 * 4 + 2 * 8  # never the whole image
    # each strip's bands are made for the rows it samples, and the shifts' taps beyond them (within the image)
    assert made == [phase_rows(h, axis, (first, last)) for axis, first, last in sampled]
    monkeypatch.setattr(cost, "_PHASE_STRIP_ROWS", h)
    whole = cost_at(bands, APERTURE, maps, 9, 2e-3, sampling="phase")
    assert np.abs(strips - whole).max() < 1e-5
    assert np.array_equal(strips[:, :92], whole[:, :92])  # the first strip's rows that read no row of the next


def test_the_shifts_written_in_place_are_the_band_limited_shifts():
    from mca.processing.cost import _shift_into

    planes = np.random.default_rng(2).normal(size=(2, 30, 40)).astype(np.float32)
    for axis in (0, 1):
        for amount in (0.0, 0.125, 0.5, 0.875, 1.0):
            out = np.empty_like(planes)
            _shift_into(planes, amount, axis, out)
            dx, dy = (amount, 0.0) if axis == 0 else (0.0, amount)
            assert np.array_equal(out, shift_band_limited(planes, dx, dy)), (axis, amount)


@pytest.mark.parametrize("truth", [0.25, 2.0])
def test_noise_alone_no_longer_pulls_the_minimum_to_a_sampling_phase(truth):
    """Without a noise model the bilinear cost of a noisy capture is lowest toward odd red-blue disparities (every
    channel halfway between pixels); with the band-limited sampler it needs no model and lies on the truth."""
    noisy = noisy_plane(truth, 0.05, 3)
    bands = stack_bands(feature_bands(noisy))
    candidates = np.arange(truth - 1.0, truth + 1.001, 0.05)
    minima = {}
    for sampling in ("bilinear", "phase"):
        volume = cost_volume(bands, APERTURE, candidates, 9, 2e-3, sampling)
        curve = volume[:, 25:-25, 25:-25].reshape(len(candidates), -1).mean(axis=1)
        minima[sampling] = float(candidates[int(np.argmin(curve))])
    assert abs(minima["phase"] - truth) <= 0.1
    assert abs(minima["bilinear"] - truth) > 0.15  # the bias, for contrast


def test_on_noise_alone_the_cost_is_the_same_at_every_sampling_phase():
    """Flat grey with white noise: the bilinear cost swings with the disparity's phase (lowest where every channel
    falls halfway), the band-limited one does not."""
    rng = np.random.default_rng(5)
    noisy = np.clip(0.3 + 0.03 * rng.normal(size=(200, 240, 3)), 1e-3, None).astype(np.float32)
    bands = stack_bands(feature_bands(noisy))
    candidates = np.arange(-2.0, 2.01, 0.5)
    swings = {}
    for sampling in ("bilinear", "phase"):
        volume = cost_volume(bands, APERTURE, candidates, 9, 2e-3, sampling)
        curve = volume[:, 20:-20, 20:-20].reshape(len(candidates), -1).mean(axis=1)
        swings[sampling] = float(curve.max() - curve.min())
    assert swings["phase"] < 0.25 * swings["bilinear"], swings


@pytest.mark.parametrize("sampling", ["phase", "bilinear", "bspline"])
def test_a_disparity_that_is_not_finite_is_costed_at_zero(sampling):
    """The kernels assume finite values: a NaN or an infinity in a per-pixel map is costed as disparity 0, not
    turned into an index anywhere in memory."""
    bands = stack_bands(feature_bands(texture((40, 48), 6, blur_px=1.2)))
    maps = np.full((2, 40, 48), 0.75, np.float32)
    maps[0, 10, 20] = np.nan
    maps[1, 30, 5] = np.inf
    maps[1, 0, 0] = -np.inf
    cleaned = np.where(np.isfinite(maps), maps, np.float32(0.0))
    got = cost_at(bands, APERTURE, maps, 9, 2e-3, sampling=sampling)
    assert np.isfinite(got).all()
    assert np.array_equal(got, cost_at(bands, APERTURE, cleaned, 9, 2e-3, sampling=sampling))
