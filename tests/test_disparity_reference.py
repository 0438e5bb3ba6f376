"""The per-pixel disparity module against references written here: numpy/scipy sampling, det() of the colour
correlation matrix, the parabola vertex, and images whose channels the test itself displaced by a known
disparity along the paper's filter geometry (red right, green up, blue left, seen from behind the camera).

Nothing here builds its input with `mca.processing.disparity`; the expected values come from first principles.
"""

from __future__ import annotations

import threading

import cv2
import numpy as np
import pytest
from scipy import ndimage

from mca.devices.profiles import load_profile
from mca.processing import disparity as dsp
from mca.processing.sampling import remap_cubic, remap_linear

APERTURE = load_profile("paper-70d").aperture
# A farther object (disparity d > 0) shows each channel displaced toward its filter's side by d * centre / 12 mm,
# image axes x right, y down (the filter's y is up): red (+d/2, 0), green (0, -d/2), blue (-d/2, 0).
TRUE_SHIFT_PER_PX = np.array([[0.5, 0.0], [0.0, -0.5], [-0.5, 0.0]])


def texture(height: int, width: int, seed: int = 1, sigma: float = 1.5) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return ndimage.gaussian_filter(rng.random((height, width)), sigma).astype(np.float64)


def fourier_shift(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    """`image` displaced by (dx, dy) (content moves right/down), exact for band-limited periodic images."""
    return np.real(np.fft.ifft2(ndimage.fourier_shift(np.fft.fft2(image), (dy, dx))))


def mca_planes(base: np.ndarray, disparity_px: float, gains=(1.0, 0.6, 1.4), offsets=(0.1, 0.3, 0.0)) -> np.ndarray:
    """Three channels of one scene whose content is displaced by `disparity_px` along the filter geometry."""
    planes = np.empty((*base.shape, 3), np.float32)
    for c in range(3):
        dx, dy = disparity_px * TRUE_SHIFT_PER_PX[c]
        planes[..., c] = gains[c] * fourier_shift(base, dx, dy) + offsets[c]
    return planes


def bilinear(plane: np.ndarray, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
    """plane sampled at (xs, ys), edges replicated: scipy's order-1 spline with mode 'nearest'."""
    return ndimage.map_coordinates(plane.astype(np.float64), [ys, xs], order=1, mode="nearest")


def reference_cost(channels: list[np.ndarray], window: int, eps: float) -> np.ndarray:
    """det of the 3x3 matrix of regularised uncentred correlations over each window (Bando et al. 2008)."""
    height, width = channels[0].shape
    half = window // 2
    padded = [np.pad(c.astype(np.float64), half, mode="symmetric") for c in channels]
    out = np.full((height, width), np.nan)
    for y in range(height):
        for x in range(width):
            vectors = [p[y : y + window, x : x + window].ravel() for p in padded]
            n = vectors[0].size
            gram = np.array([[np.dot(a, b) / n for b in vectors] for a in vectors])
            norms = np.sqrt(np.diag(gram) + eps)
            corr = gram / np.outer(norms, norms)
            np.fill_diagonal(corr, 1.0)
            out[y, x] = np.clip(np.linalg.det(corr), 0.0, 1.0)
    return out


def test_channel_shifts_follow_the_filter_geometry() -> None:
    np.testing.assert_allclose(dsp.channel_shifts(APERTURE), TRUE_SHIFT_PER_PX, atol=1e-12)


@pytest.mark.parametrize(("dx", "dy"), [(2.0, 0.0), (0.0, -3.0), (1.25, 0.75), (-0.4, 2.6)])
def test_sampling_a_shifted_plane_is_bilinear_with_replicated_borders(dx: float, dy: float) -> None:
    plane = texture(40, 56).astype(np.float32)
    ys, xs = np.mgrid[0:40, 0:56].astype(np.float64)
    expected = bilinear(plane, xs + dx, ys + dy)
    np.testing.assert_allclose(dsp.sample_shifted(plane, dx, dy), expected, atol=2e-3)
    # rows 10..25 only: the same values as the full sampling, borders at the plane's own edges
    np.testing.assert_allclose(dsp.sample_shifted_rows(plane, dx, dy, 10, 25), expected[10:25], atol=2e-3)
    np.testing.assert_allclose(dsp.sample_shifted_rows(plane, dx, dy, 0, 40), expected, atol=2e-3)
    assert dsp.sample_shifted_rows(plane, dx, dy, 33, 40).shape == (7, 56)


def test_shift_channels_undoes_a_uniform_disparity() -> None:
    base = texture(48, 64, seed=3, sigma=2.0)
    planes = mca_planes(base, 4.0, gains=(1, 1, 1), offsets=(0, 0, 0))  # integer 2 px displacements
    aligned = dsp.shift_channels(planes, APERTURE, 4.0)
    inner = np.s_[4:-4, 4:-4]
    for c in range(3):
        np.testing.assert_allclose(aligned[..., c][inner], base[inner], atol=1e-4)
    # the wrong sign (or the wrong disparity) leaves the channels apart
    wrong = dsp.shift_channels(planes, APERTURE, -4.0)
    assert np.abs(wrong[..., 0][inner] - base[inner]).max() > 0.05


@pytest.mark.parametrize("origin", [(0, 0), (5, 7)])
def test_warp_channels_with_a_per_pixel_map_matches_the_reference_sampling(origin: tuple[int, int]) -> None:
    base = texture(150, 40, seed=4)
    planes = np.stack([base, base * 0.5, base + 0.2], axis=-1).astype(np.float32)
    rng = np.random.default_rng(5)
    height, width = 140, 30  # more than two 64-row strips, a crop at `origin`
    d = rng.uniform(-3, 3, (height, width)).astype(np.float32)
    out = dsp.warp_channels(planes, APERTURE, d, origin_xy=origin)
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    xs += origin[0]
    ys += origin[1]
    for c in range(3):
        dx, dy = TRUE_SHIFT_PER_PX[c]
        expected = bilinear(planes[..., c], xs + d * dx, ys + d * dy)
        # exact, not to OpenCV 4's 1/32 px coordinate grid (which gives errors up to ~1e-3 on this texture)
        np.testing.assert_allclose(out[..., c], expected, atol=2e-6)


def sampling_maps(seed: int) -> tuple[np.ndarray, np.ndarray]:
    """(20, 33) float32 coordinates into a 37 x 45 plane: random, inside and past every border, and in row 0 four
    positions finer than OpenCV's 1/32 px grid, at x = 3 + (0, 1/128, 1/64, 3/128), y = 5."""
    rng = np.random.default_rng(seed)
    map_x = rng.uniform(-6.0, 51.0, (20, 33)).astype(np.float32)
    map_y = rng.uniform(-6.0, 43.0, (20, 33)).astype(np.float32)
    map_x[0, :4] = np.float32(3.0) + np.array([0.0, 1 / 128, 1 / 64, 3 / 128], np.float32)
    map_y[0, :4] = 5.0
    return map_x, map_y


def test_remap_linear_is_exact_bilinear_sampling_with_replicated_borders() -> None:
    plane = texture(37, 45, seed=8).astype(np.float32)
    map_x, map_y = sampling_maps(9)
    map_x[3, 3] = np.nan
    expected = bilinear(plane, map_x.astype(np.float64), map_y.astype(np.float64))
    out = remap_linear(plane, map_x, map_y)
    finite = np.isfinite(map_x)
    np.testing.assert_allclose(out[finite], expected[finite], atol=2e-6)
    assert np.isnan(out[3, 3])
    # the four sub-1/32 px positions give four different values, on the line between the two samples
    row = out[0, :4]
    assert np.all(np.diff(row) != 0)
    slope = plane[5, 4] - plane[5, 3]
    np.testing.assert_allclose(row - plane[5, 3], slope * np.array([0.0, 1 / 128, 1 / 64, 3 / 128]), atol=1e-6)
    with pytest.raises(ValueError, match="one plane"):
        remap_linear(np.zeros((4, 4, 3), np.float32), map_x, map_y)
    with pytest.raises(ValueError, match="two maps"):
        remap_linear(plane, map_x, map_y[:5])


def keys_cubic(plane: np.ndarray, xs: np.ndarray, ys: np.ndarray, a: float = -0.75) -> np.ndarray:
    """Keys' cubic convolution (the kernel as Keys 1981 writes it, piecewise in |s|) at (xs, ys) in float64, taps'
    indices clamped to the image (replicated borders)."""

    def kernel(s: np.ndarray) -> np.ndarray:
        s = np.abs(s)
        near = ((a + 2) * s - (a + 3)) * s**2 + 1
        far = a * s**3 - 5 * a * s**2 + 8 * a * s - 4 * a
        return np.where(s <= 1, near, np.where(s < 2, far, 0.0))

    h, w = plane.shape
    x0, y0 = np.floor(xs).astype(int), np.floor(ys).astype(int)
    out = np.zeros(xs.shape)
    for m in range(-1, 3):
        for n in range(-1, 3):
            rows, cols = np.clip(y0 + m, 0, h - 1), np.clip(x0 + n, 0, w - 1)
            out += kernel(ys - (y0 + m)) * kernel(xs - (x0 + n)) * plane[rows, cols]
    return out


def test_remap_cubic_is_keys_cubic_at_the_exact_coordinates() -> None:
    """The all-in-focus image's sampler: Keys' cubic (a = -0.75, OpenCV's INTER_CUBIC) with replicated borders,
    at exact coordinates; on OpenCV's own 1/32 px grid of coordinates, OpenCV's remap under any release."""
    plane = texture(37, 45, seed=10).astype(np.float32)
    map_x, map_y = sampling_maps(11)
    map_x[3, 3] = np.inf
    out = remap_cubic(plane, map_x, map_y)
    finite = np.isfinite(map_x)
    expected = keys_cubic(plane.astype(np.float64), map_x[finite].astype(np.float64), map_y[finite].astype(np.float64))
    np.testing.assert_allclose(out[finite], expected, atol=2e-6)
    assert np.isnan(out[3, 3])
    assert np.all(np.diff(out[0, :4]) != 0)  # four positions within 1/32 px, four values
    # at whole pixels it returns the samples themselves; a constant stays constant everywhere
    grid_y, grid_x = np.mgrid[0:37, 0:45].astype(np.float32)
    np.testing.assert_allclose(remap_cubic(plane, grid_x, grid_y), plane, atol=1e-6)
    np.testing.assert_allclose(remap_cubic(np.full((9, 9), 0.3, np.float32), map_x, map_y)[finite], 0.3, atol=1e-6)
    on_grid_x = (np.round(map_x * 32) / 32).astype(np.float32)
    on_grid_y = (np.round(map_y * 32) / 32).astype(np.float32)
    opencv = cv2.remap(plane, on_grid_x, on_grid_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    np.testing.assert_allclose(remap_cubic(plane, on_grid_x, on_grid_y)[finite], opencv[finite], atol=2e-6)
    with pytest.raises(ValueError, match="remap_cubic samples one plane"):
        remap_cubic(np.zeros((4, 4, 3), np.float32), map_x, map_y)
    with pytest.raises(ValueError, match="remap_cubic needs two maps"):
        remap_cubic(plane, map_x, map_y[:5])


def test_parallel_map_keeps_order_uses_the_workers_and_does_not_deadlock_inside_them() -> None:
    names: list[str] = []

    def square(i: int) -> int:
        names.append(threading.current_thread().name)
        # a nested call from a worker runs serially (a pool waiting on itself would deadlock)
        inner = dsp.parallel_map(lambda j: j + 1, range(3))
        assert inner == [1, 2, 3]
        return i * i

    assert dsp.parallel_map(square, range(12)) == [i * i for i in range(12)]
    if dsp._WORKERS > 1:
        assert all(n.startswith("mca-processing") for n in names)
    assert dsp.parallel_map(square, [3]) == [9]
    assert dsp.parallel_map(square, []) == []


def test_band_pass_is_a_difference_of_gaussians_of_log_intensities() -> None:
    rng = np.random.default_rng(6)
    planes = (rng.random((60, 50, 3)) * 1000.0).astype(np.float32)
    scale = np.percentile(planes, 99.5)
    compressed = np.log1p(np.clip(planes, 0, None) * 32.0 / scale)
    expected = np.stack(
        [
            ndimage.gaussian_filter(compressed[..., c], 0.8, mode="reflect", truncate=4.0)
            - ndimage.gaussian_filter(compressed[..., c], 4.0, mode="reflect", truncate=4.0)
            for c in range(3)
        ],
        axis=-1,
    )
    got = dsp.band_pass(planes)
    inner = np.s_[14:-14, 14:-14]  # OpenCV and scipy cut their kernels at slightly different radii
    np.testing.assert_allclose(got[inner], expected[inner], atol=0.02)
    # exposure does not matter (log compression against the 99.5th percentile)
    np.testing.assert_allclose(dsp.band_pass(planes * 7.0), got, atol=1e-4)


@pytest.mark.parametrize("height", [30, 250])  # one block, and strips of 96 rows with their halos
def test_colour_line_cost_is_the_determinant_of_the_correlation_matrix(height: int) -> None:
    rng = np.random.default_rng(7)
    channels = [ndimage.gaussian_filter(rng.standard_normal((height, 12)), 1.0).astype(np.float32) for _ in range(3)]
    channels[1] = (0.7 * channels[0] + 0.3 * channels[1]).astype(np.float32)  # partly aligned
    eps = np.float32(1e-4)
    expected = reference_cost(channels, 5, float(eps))
    np.testing.assert_allclose(dsp.colour_line_cost(channels, 5, eps), expected, atol=2e-4)
    rows = dsp.colour_line_cost_rows(lambda a0, a1: [c[a0:a1] for c in channels], height, 5, eps)
    np.testing.assert_allclose(rows, expected, atol=2e-4)
    energy = [dsp.colour_line_energy(c, 5, eps) for c in channels]
    inv = 1.0 / np.sqrt(ndimage.uniform_filter(channels[0].astype(np.float64) ** 2, 5, mode="reflect") + eps)
    np.testing.assert_allclose(energy[0], inv, rtol=1e-4)
    with_energy = dsp.colour_line_cost(channels, 5, eps, [energy[0], None, energy[2]])
    np.testing.assert_allclose(with_energy, expected, atol=2e-4)
    rows_energy = dsp.colour_line_cost_rows(lambda a0, a1: [c[a0:a1] for c in channels], height, 5, eps, energy)
    np.testing.assert_allclose(rows_energy, expected, atol=2e-4)


def test_colour_line_cost_is_zero_for_aligned_channels_of_any_gain_and_sign() -> None:
    base = texture(40, 40, seed=8) - 0.5
    channels = [base.astype(np.float32), (-2.0 * base).astype(np.float32), (0.3 * base).astype(np.float32)]
    cost = dsp.colour_line_cost(channels, 9, np.float32(1e-8))
    assert float(cost.max()) < 1e-3
    unrelated = [(texture(40, 40, seed=s) - 0.5).astype(np.float32) for s in (9, 10, 11)]
    assert float(dsp.colour_line_cost(unrelated, 9, np.float32(1e-8)).mean()) > 0.3


def test_alignment_cost_uniform_per_pixel_and_offsets_agree_with_the_reference() -> None:
    base = texture(210, 30, seed=12) - 0.5
    planes = mca_planes(base, 4.0, gains=(1, 1, 1), offsets=(0, 0, 0))
    cost = dsp.AlignmentCost(planes, APERTURE, window_px=8, noise_floor=1e-3)  # an even window becomes 9
    assert cost.window == 9
    aligned = cost.uniform(4.0)
    inner = np.s_[6:-6, 6:-6]
    assert float(aligned[inner].max()) < 1e-3  # the true disparity aligns the channels
    assert float(cost.uniform(0.0)[inner].mean()) > 0.05
    assert float(cost.uniform(-4.0)[inner].mean()) > float(cost.uniform(0.0)[inner].mean()) * 0.5
    d = np.full((210, 30), 4.0, np.float32)
    np.testing.assert_allclose(cost.per_pixel(d), aligned, atol=1e-4)
    # a crop: the same windows as the full map's where the window lies inside the crop
    crop = cost.per_pixel(d[20:120, 5:25], origin_xy=(5, 20))
    np.testing.assert_allclose(crop[6:-6, 6:-6], aligned[26:114, 11:19], atol=1e-4)
    deltas = np.array([-1.0, 0.0, 1.5])
    start = np.full((210, 30), 3.0, np.float32)
    by_offsets = cost.offsets(start, deltas)
    for k, delta in enumerate(deltas):
        np.testing.assert_allclose(by_offsets[k], cost.per_pixel(start + np.float32(delta)), atol=1e-4)
    means = cost.offsets(start, deltas, reduce=lambda k, c: (k, float(c[inner].mean())))
    assert [k for k, _ in means] == [0, 1, 2]
    assert min(means, key=lambda m: m[1])[0] == 2  # 3 + 1.5 is nearest the truth, 4
    # texture: the mean over channels of the windowed band-pass variance
    expected = np.mean(
        [
            ndimage.uniform_filter(planes[..., c].astype(np.float64) ** 2, 9, mode="reflect")
            - ndimage.uniform_filter(planes[..., c].astype(np.float64), 9, mode="reflect") ** 2
            for c in range(3)
        ],
        axis=0,
    )
    np.testing.assert_allclose(cost.texture(), np.maximum(expected, 0), atol=1e-4)
    flat = dsp.AlignmentCost(np.zeros((20, 20, 3), np.float32), APERTURE, 9, 1e-3)
    assert float(flat.texture().min()) == 0.0


def test_candidate_disparities_cover_the_range_on_a_grid_through_zero() -> None:
    got = dsp.candidate_disparities((-2.3, 3.1), 0.5)
    np.testing.assert_allclose(got, np.arange(-2.5, 3.5 + 1e-9, 0.5))
    assert 0.0 in dsp.candidate_disparities((0.7, 3.0), 0.5) or dsp.candidate_disparities((0.7, 3.0), 0.5)[0] == 0.5
    np.testing.assert_allclose(dsp.candidate_disparities((1.0, 2.0), 1.0), [1.0, 2.0])


def test_subpixel_minimum_is_the_vertex_of_the_parabola() -> None:
    for vertex in (-0.45, -0.2, 0.0, 0.13, 0.4):
        y = [(x - vertex) ** 2 * 3.0 + 1.0 for x in (-1, 0, 1)]
        got = dsp.subpixel_minimum(np.array([y[0]]), np.array([y[1]]), np.array([y[2]]))
        assert got[0] == pytest.approx(vertex, abs=1e-9)
    # beyond half a step: clipped to the step; no curvature (a line or a peak): no offset
    far = [(x - 0.9) ** 2 for x in (-1, 0, 1)]
    assert dsp.subpixel_minimum(np.array([far[0]]), np.array([far[1]]), np.array([far[2]]))[0] == 0.5
    far = [(x + 0.9) ** 2 for x in (-1, 0, 1)]
    assert dsp.subpixel_minimum(np.array([far[0]]), np.array([far[1]]), np.array([far[2]]))[0] == -0.5
    assert dsp.subpixel_minimum(np.array([1.0]), np.array([2.0]), np.array([3.0]))[0] == 0.0
    assert dsp.subpixel_minimum(np.array([1.0]), np.array([2.0]), np.array([1.0]))[0] == 0.0


@pytest.mark.parametrize("truth_px", [-3.0, 1.6, 4.0])
def test_estimate_disparity_recovers_a_displacement_made_by_the_test(truth_px: float) -> None:
    base = texture(220, 64, seed=13, sigma=1.2)
    planes = mca_planes(base * 500.0 + 50.0, truth_px)
    result = dsp.estimate_disparity(planes, APERTURE, (-6.0, 6.0))
    inner = np.s_[12:-12, 12:-12]
    assert result.disparity_px.dtype == np.float32 and result.disparity_px.shape == (220, 64)
    assert float(np.median(result.disparity_px[inner])) == pytest.approx(truth_px, abs=0.08)
    assert float(np.mean(np.abs(result.disparity_px[inner] - truth_px) < 0.25)) > 0.9
    assert float(np.median(result.confidence[inner])) > 0.2
    assert float(result.confidence.min()) >= 0.0 and float(result.confidence.max()) <= 1.0
    assert float(np.median(result.cost[inner])) < 0.05
    np.testing.assert_allclose(result.candidates_px, np.arange(-6.0, 6.0 + 1e-9, 0.5))
    # integer winner only: on the candidate grid
    whole = dsp.estimate_disparity(planes, APERTURE, (-6.0, 6.0), dsp.DisparityParams(subpixel=False))
    assert np.all(np.isin(whole.disparity_px, whole.candidates_px.astype(np.float32)))
    # box aggregation keeps the answer
    boxed = dsp.estimate_disparity(planes, APERTURE, (-6.0, 6.0), dsp.DisparityParams(aggregation_px=5))
    assert float(np.median(boxed.disparity_px[inner])) == pytest.approx(truth_px, abs=0.1)


def test_estimate_disparity_flat_areas_and_range_edges_get_little_confidence() -> None:
    base = texture(200, 60, seed=14, sigma=1.2) * 500.0 + 50.0
    planes = mca_planes(base, 5.0)
    planes[:, 40:] = 100.0  # a flat right part
    result = dsp.estimate_disparity(planes, APERTURE, (-2.0, 6.0))
    assert float(np.median(result.confidence[20:-20, 55:])) < 0.01
    textured = np.median(result.confidence[20:-20, 10:30])
    assert textured > 0.2
    # the truth beyond the range: the winner sits at the range's edge, without sub-pixel offset, confidence / 4
    short = dsp.estimate_disparity(planes, APERTURE, (-2.0, 3.0))
    edge = short.disparity_px[20:-20, 10:30]
    assert float(np.mean(edge == 3.0)) > 0.8
    assert float(np.median(short.confidence[20:-20, 10:30])) <= 0.25 * 1.0001
    # a second, equally good minimum more than two steps away (a periodic texture) makes the match ambiguous
    stripes = np.tile(np.sin(np.arange(60) * 2 * np.pi / 4.0), (200, 1)) * 100.0 + 200.0
    periodic = dsp.estimate_disparity(mca_planes(stripes, 0.0), APERTURE, (-6.0, 6.0))
    assert float(np.median(periodic.confidence[20:-20, 10:-10])) < 0.5 * textured


def test_texture_weight_in_the_confidence_follows_the_noise_floor() -> None:
    base = texture(200, 50, seed=15, sigma=1.2) * 500.0 + 50.0
    planes = mca_planes(base, 2.0)
    low = dsp.estimate_disparity(planes, APERTURE, (-4.0, 4.0), dsp.DisparityParams(noise_floor=1e-4))
    high = dsp.estimate_disparity(planes, APERTURE, (-4.0, 4.0), dsp.DisparityParams(noise_floor=0.3))
    assert float(np.median(high.confidence)) < float(np.median(low.confidence))


def test_green_moves_vertically_and_its_sign_matters() -> None:
    """A disparity seen only in green (red and blue agree): a flipped vertical sign would find -d."""
    base = texture(200, 60, seed=16, sigma=1.2) * 500.0 + 50.0
    planes = mca_planes(base, 3.0)
    result = dsp.estimate_disparity(planes, APERTURE, (-5.0, 5.0), band=dsp.band_pass(planes))
    assert float(np.median(result.disparity_px[15:-15, 15:-15])) == pytest.approx(3.0, abs=0.1)
    # warp_channels with the found map aligns the channels again
    aligned = dsp.warp_channels(planes, APERTURE, np.full((200, 60), 3.0, np.float32), cv2.INTER_CUBIC)
    a = aligned[15:-15, 15:-15]
    r = (a[..., 0] - 0.1) / 1.0
    g = (a[..., 1] - 0.3) / 0.6
    np.testing.assert_allclose(g, r, atol=6.0)
    apart = dsp.warp_channels(planes, APERTURE, np.full((200, 60), -3.0, np.float32), cv2.INTER_CUBIC)[15:-15, 15:-15]
    assert float(np.abs((apart[..., 1] - 0.3) / 0.6 - (apart[..., 0] - 0.1)).max()) > 30.0


def test_defaults_are_the_documented_ones() -> None:
    params = dsp.DisparityParams()
    assert (params.window_px, params.step_px, params.noise_floor, params.aggregation_px, params.subpixel) == (
        9,
        0.5,
        2e-3,
        0,
        True,
    )
    base = texture(60, 40, seed=20)
    planes = np.stack([base, base * 0.5, base + 0.2], axis=-1).astype(np.float32)
    d = np.random.default_rng(21).uniform(-2, 2, (60, 40)).astype(np.float32)
    # without origin_xy: the map covers the planes from their top-left corner
    np.testing.assert_array_equal(
        dsp.warp_channels(planes, APERTURE, d), dsp.warp_channels(planes, APERTURE, d, origin_xy=(0, 0))
    )
    cost = dsp.AlignmentCost(planes, APERTURE, 9, 1e-3)
    np.testing.assert_array_equal(cost.per_pixel(d), cost.per_pixel(d, origin_xy=(0, 0)))


def test_texture_is_never_negative_even_where_rounding_cancels() -> None:
    rng = np.random.default_rng(0)
    band = (1000 + rng.random((40, 40, 3)) * 1e-3).astype(np.float32)  # float32 var = E[x^2] - E[x]^2 cancels
    assert float(dsp.AlignmentCost(band, APERTURE, 9, 1e-3).texture().min()) >= 0.0


def test_the_three_correlation_form_is_the_determinant() -> None:
    rng = np.random.default_rng(22)
    rg, rb, gb = (rng.uniform(-0.9, 0.9, 50) for _ in range(3))
    expected = [
        np.clip(np.linalg.det(np.array([[1, a, b], [a, 1, c], [b, c, 1]])), 0, 1) for a, b, c in zip(rg, rb, gb)
    ]
    np.testing.assert_allclose(dsp._colour_line(rg.copy(), rb.copy(), gb.copy()), expected, atol=1e-12)


def test_the_winning_cost_is_the_minimum_over_candidates_with_the_default_window() -> None:
    base = texture(60, 50, seed=23, sigma=1.2) * 500.0 + 50.0
    planes = mca_planes(base, 1.3)
    band = dsp.band_pass(planes)
    result = dsp.estimate_disparity(planes, APERTURE, (-2.0, 2.0), dsp.DisparityParams(subpixel=False), band=band)
    nine = dsp.AlignmentCost(band, APERTURE, 9, 2e-3)
    volume = np.stack([nine.uniform(d) for d in result.candidates_px])
    np.testing.assert_allclose(result.cost, volume.min(axis=0), atol=1e-5)
    np.testing.assert_array_equal(result.disparity_px, result.candidates_px[volume.argmin(axis=0)].astype(np.float32))


def test_the_last_but_one_candidate_still_gets_its_sub_pixel_offset() -> None:
    base = texture(200, 60, seed=24, sigma=1.2) * 500.0 + 50.0
    planes = mca_planes(base, 2.6)  # between the candidates 2.5 and 3.0, the last one
    result = dsp.estimate_disparity(planes, APERTURE, (-2.0, 3.0))
    inner = result.disparity_px[20:-20, 15:-15]
    assert float(np.median(inner)) == pytest.approx(2.6, abs=0.06)
    assert float(np.mean(inner == 2.5)) < 0.5  # not snapped to the candidate as at the range's edge
