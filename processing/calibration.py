"""Bench calibration of an MCA lens: a flat target's global disparity, and the thin-lens fit of d_a, d_ls and an offset.

The model (eq. 11 with the inter-image depth Δd = d_ls - v, v from the Gaussian lens
equation, eq. 6): a target at distance u from the lens shows, between the red and blue
images (the widest pair, d_a apart),

    disparity_px(u) = d_a (d_ls - v(u)) / v(u) / pitch + offset_px,    v(u) = f u / (u - f).

Identifiability. With f fixed this is exactly A - B / u, with B = d_a d_ls / pitch and
A = d_a (d_ls - f) / (f pitch) + offset_px: a sweep of distances measures two numbers,
so d_a, d_ls and the offset cannot all be fitted (the 3-column Jacobian has rank 2 for
any sweep; `identifiability` reports it). Depth from disparity, u = B / (A - disparity),
depends on A and B alone, so fixing the offset (default 0: the Bayer offset is removed
exactly) and fitting d_a and d_ls gives exact depths; a real offset is then absorbed into
d_ls (a focus shift of offset / (B / u_F²) mm). Pure: arrays and numbers in and out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from mca.processing.camera import FilterAperture
from mca.processing.optics import thin_lens_disparity_mm, thin_lens_distance_mm

# In half-resolution R and B planes of an RGGB mosaic the red site (0, 0) and the blue site (1, 1) of a
# 2x2 block are one mosaic pixel apart in x and y: red content appears (+1, +1) mosaic px from blue.
BAYER_RED_FROM_BLUE_PX: tuple[float, float] = (1.0, 1.0)

PARAMETERS = ("filter_centre_distance_mm", "sensor_distance_mm", "disparity_offset_px")
SHORT_NAMES = {"filter_centre_distance_mm": "d_a", "sensor_distance_mm": "d_ls", "disparity_offset_px": "offset"}


class CalibrationFitError(ValueError):
    """A fit that cannot be made or trusted (too few points, parameters not identifiable)."""


# --- the target's disparity -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class TargetDisparity:
    """The global red-blue disparity of a fronto-parallel target, in mosaic pixels of the photograph."""

    disparity_px: float  # along the baseline (red minus blue shift, Bayer offset removed)
    across_px: float  # perpendicular to the baseline: should be ~0; a check of the set-up
    shift_px: tuple[float, float]  # measured red-from-blue shift (dx, dy), mosaic px, Bayer offset included
    correlation: float  # normalised correlation of red and the registered blue (1 = identical)
    iterations: int


def baseline_direction(aperture: FilterAperture, first: str = "red", second: str = "blue") -> tuple[float, float]:
    """Unit vector (x right, y down) along which `first`'s image moves away from `second`'s per unit disparity."""
    ax, ay = aperture.shift_per_disparity(first)
    bx, by = aperture.shift_per_disparity(second)
    dx, dy = ax - bx, ay - by
    norm = math.hypot(dx, dy)
    if norm == 0:
        raise ValueError(f"filters {first} and {second} coincide: no baseline")
    return (dx / norm, dy / norm)


def _central_window(shape: tuple[int, int], crop_fraction: float, max_side_px: int) -> tuple[slice, slice]:
    h, w = shape
    ch = min(int(h * crop_fraction), max_side_px)
    cw = min(int(w * crop_fraction), max_side_px)
    if ch < 16 or cw < 16:
        raise ValueError(f"planes of {w}x{h} px are too small for a disparity estimate")
    y0, x0 = (h - ch) // 2, (w - cw) // 2
    return slice(y0, y0 + ch), slice(x0, x0 + cw)


def plane_shift_px(
    reference: np.ndarray,
    moving: np.ndarray,
    *,
    crop_fraction: float = 0.6,
    max_side_px: int = 768,
    max_iterations: int = 30,
    tolerance_px: float = 1e-4,
    smoothing_px: float = 1.0,
    search_centre_px: tuple[float, float] = (0.0, 0.0),
    search_half_size_px: tuple[float, float] = (8.0, 8.0),
) -> tuple[float, float, float, int]:
    """Sub-pixel translation (dx, dy) with reference(x) ≈ a · moving(x - (dx, dy)) + c over a central window.

    The phase-correlation peak inside the box `search_centre_px` ± `search_half_size_px` (dx, dy) gives the
    start (the box keeps a tiled, periodic texture from matching the wrong tile); Gauss-Newton on the windowed residual with
    cubic-spline resampling of `moving` refines it to ~0.005 px on textured, noisy planes.
    Returns (dx, dy, correlation, iterations).
    """
    from scipy import ndimage

    ref = np.asarray(reference, dtype=np.float64)
    mov = np.asarray(moving, dtype=np.float64)
    if smoothing_px > 0:  # the same low-pass on both keeps the shift and removes aliased, near-Nyquist content
        ref = ndimage.gaussian_filter(ref, smoothing_px, mode="mirror")
        mov = ndimage.gaussian_filter(mov, smoothing_px, mode="mirror")
    if ref.shape != mov.shape or ref.ndim != 2:
        raise ValueError(f"planes must be 2-D and equal in shape, got {ref.shape} and {mov.shape}")
    rows, cols = _central_window(ref.shape, crop_fraction, max_side_px)
    r = ref[rows, cols]
    r = (r - r.mean()) / max(r.std(), 1e-12)
    m_norm = (mov - mov[rows, cols].mean()) / max(mov[rows, cols].std(), 1e-12)
    dx, dy = _correlation_peak(r, m_norm[rows, cols], search_centre_px, search_half_size_px)
    yy, xx = np.mgrid[rows, cols].astype(np.float64)
    coeffs = ndimage.spline_filter(m_norm, order=3, mode="mirror")
    iterations = 0
    for iterations in range(1, max_iterations + 1):  # noqa: B007 (the count is reported after the loop)
        coords = np.stack([yy - dy, xx - dx])
        warped = ndimage.map_coordinates(coeffs, coords, order=3, mode="mirror", prefilter=False)
        gy, gx = np.gradient(warped)
        # r ≈ a w(x - dt) + c ≈ a w - a ∇w·dt + c: linear in (a, c, a dt_x, a dt_y)
        design = np.stack([warped.ravel(), np.ones(warped.size), -gx.ravel(), -gy.ravel()], axis=1)
        solution, *_ = np.linalg.lstsq(design, r.ravel(), rcond=None)
        a = solution[0] if abs(solution[0]) > 1e-9 else 1e-9
        step_x, step_y = solution[2] / a, solution[3] / a
        step_x, step_y = float(np.clip(step_x, -0.5, 0.5)), float(np.clip(step_y, -0.5, 0.5))
        dx, dy = dx + step_x, dy + step_y
        if math.hypot(step_x, step_y) < tolerance_px:
            break
    coords = np.stack([yy - dy, xx - dx])
    warped = ndimage.map_coordinates(coeffs, coords, order=3, mode="mirror", prefilter=False)
    correlation = float(np.corrcoef(r.ravel(), warped.ravel())[0, 1])
    return dx, dy, correlation, iterations


def _correlation_peak(
    reference: np.ndarray, moving: np.ndarray, centre: tuple[float, float], half_size: tuple[float, float]
) -> tuple[float, float]:
    """Integer (dx, dy) of the highest phase-correlation peak within centre ± half_size."""
    window = np.outer(np.hanning(reference.shape[0]), np.hanning(reference.shape[1]))
    spectrum = np.fft.fft2(reference * window) * np.conj(np.fft.fft2(moving * window))
    surface = np.real(np.fft.ifft2(spectrum / np.maximum(np.abs(spectrum), 1e-12)))
    sy = np.fft.fftfreq(reference.shape[0], 1.0 / reference.shape[0])[:, None]
    sx = np.fft.fftfreq(reference.shape[1], 1.0 / reference.shape[1])[None, :]
    allowed = (np.abs(sx - centre[0]) <= half_size[0] + 0.5) & (np.abs(sy - centre[1]) <= half_size[1] + 0.5)
    if not allowed.any():
        raise ValueError("the disparity search box is empty")
    index = np.unravel_index(np.argmax(np.where(allowed, surface, -np.inf)), surface.shape)
    return float(np.broadcast_to(sx, surface.shape)[index]), float(np.broadcast_to(sy, surface.shape)[index])


def target_disparity_px(
    red_plane: np.ndarray,
    blue_plane: np.ndarray,
    direction: tuple[float, float],
    *,
    bayer_offset_px: tuple[float, float] = BAYER_RED_FROM_BLUE_PX,
    crop_fraction: float = 0.6,
    max_disparity_px: float = 24.0,
) -> TargetDisparity:
    """Disparity (mosaic px) of a fronto-parallel textured target filling the centre of the frame.

    `red_plane`, `blue_plane`: the half-resolution Bayer planes (R at site (0, 0), B at (1, 1)).
    The red-from-blue shift is measured in plane pixels, doubled to mosaic pixels, the Bayer
    offset subtracted, and projected on `direction` (`baseline_direction`): the widest pair's
    disparity δ / pitch of eq. 11 for that one plane. Shifts beyond ±`max_disparity_px` along the
    baseline (and 4 px across) are not searched.
    """
    ux, uy = direction
    centre = (bayer_offset_px[0] / 2.0, bayer_offset_px[1] / 2.0)
    half = (abs(ux) * max_disparity_px / 2.0 + 2.0, abs(uy) * max_disparity_px / 2.0 + 2.0)
    dx, dy, correlation, iterations = plane_shift_px(
        red_plane, blue_plane, crop_fraction=crop_fraction, search_centre_px=centre, search_half_size_px=half
    )
    sx, sy = 2.0 * dx, 2.0 * dy
    ex, ey = sx - bayer_offset_px[0], sy - bayer_offset_px[1]
    return TargetDisparity(
        disparity_px=ex * ux + ey * uy,
        across_px=-ex * uy + ey * ux,
        shift_px=(sx, sy),
        correlation=correlation,
        iterations=iterations,
    )


# --- crosstalk: how much of each filter's light each sensor channel takes ------------------------------------

MIN_LEAK_SEPARATION_PX = 3.0  # a shot measures the leak when every two channels' images are this far apart


@dataclass(frozen=True)
class LeakEstimate:
    """The crosstalk measured on one shot of a grey textured target (`measure_leak`)."""

    matrix: np.ndarray  # (3, 3) sensor channel <- filter, column k scaled so that channel k takes 1 of filter k
    separation_px: float  # the smallest distance between two channels' images of the target, px of the planes
    shifts_px: np.ndarray  # (3, 2) where each channel shows the target, against green (0, 0), px of the planes


def _band(plane: np.ndarray, band_px: tuple[float, float]) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(plane, (0, 0), band_px[0]) - cv2.GaussianBlur(plane, (0, 0), band_px[1])


def measure_leak(
    planes: np.ndarray,
    *,
    crop_fraction: float = 0.6,
    max_side_px: int = 1024,
    band_px: tuple[float, float] = (0.8, 2.0),
    iterations: int = 3,
    max_shift_px: float = 40.0,
    channel_offsets_px: Sequence[tuple[float, float]] | None = None,
) -> LeakEstimate:
    """Crosstalk from one photograph of a fronto-parallel target with a grey texture T filling the centre.

    Each filter k forms the target's image T(x + s_k), s_k its displacement (0 for green, measured by
    `plane_shift_px`), and sensor channel c records sum_k M[c, k] g_k T(x + s_k): its own filter's image
    and faint copies of the others' where those filters put them. Away from focus the three copies are apart,
    so a least-squares fit of each channel's band-pass plane (a difference of Gaussians of `band_px`) to T
    moved by s_r, s_g and s_b reads its row of M diag(g). T is estimated as the mean of the three channels,
    each moved back onto green and scaled to unit spread; it is estimated again from the channels unmixed
    by the current matrix (`iterations` times), so that the copies in it fade.

    The filters' transmissions g_k and M's columns cannot be told apart, and need not be: unmixing by
    M diag(g) gives each filter's image times 1 / g_k, and the colour-line cost ignores each channel's
    scale. The matrix returned has its columns scaled to a unit diagonal. The copies must be apart by more
    than the texture's grain: `separation_px` says by how much (`MIN_LEAK_SEPARATION_PX` for a usable shot).
    A coloured texture breaks the model (T differs per channel): the target must be grey.

    `channel_offsets_px`: where each channel's samples sit in its plane's pixel, (dx, dy) per channel
    (`pipeline.RGGB_HALF_RES_OFFSETS_PX` for the half-resolution planes of an RGGB mosaic; None: co-sited).
    The channels are first moved onto the pixel centres by a band-limited shift (as `unmix_sites` does): filter
    k's light in channel c is sampled at c's sites, and mixing samples from different sites leaves copies half
    a pixel off (a 6 % leak between red and blue read as 5 %).
    """
    from mca.processing.cost import shift_band_limited

    planes = np.asarray(planes, dtype=np.float32)
    if planes.ndim != 3 or planes.shape[2] != 3:
        raise ValueError(f"measure_leak needs (H, W, 3) planes, got {planes.shape}")
    if channel_offsets_px is not None:
        planes = _move_sites(planes, channel_offsets_px, onto_centres=True)
    shifts = np.zeros((3, 2))
    for k in (0, 2):
        dx, dy, _, _ = plane_shift_px(
            planes[..., 1],
            planes[..., k],
            crop_fraction=crop_fraction,
            search_half_size_px=(max_shift_px, max_shift_px),
        )
        shifts[k] = (dx, dy)  # green(x) ~ a k(x - s): k shows the target at x + s where green shows it at x
    rows, cols = _central_window(planes.shape[:2], crop_fraction, max_side_px)
    margin = int(np.ceil(np.abs(shifts).max())) + 12  # the band-limited shift's taps and the bands' reach
    y0, y1 = max(rows.start - margin, 0), min(rows.stop + margin, planes.shape[0])
    x0, x1 = max(cols.start - margin, 0), min(cols.stop + margin, planes.shape[1])
    window = np.ascontiguousarray(planes[y0:y1, x0:x1])
    inner = (slice(rows.start - y0, rows.stop - y0), slice(cols.start - x0, cols.stop - x0))
    observed = [_band(np.ascontiguousarray(window[..., c]), band_px)[inner].ravel() for c in range(3)]
    matrix = np.eye(3)
    for _ in range(iterations):
        unmixed = unmix_sites(window, matrix, None)
        texture = np.zeros(window.shape[:2], np.float32)
        for k in range(3):
            back = shift_band_limited(
                _band(np.ascontiguousarray(unmixed[..., k]), band_px), -shifts[k, 0], -shifts[k, 1]
            )
            texture += back / max(float(back[inner].std()), 1e-12)
        design = np.stack([shift_band_limited(texture, sx, sy)[inner].ravel() for sx, sy in shifts], axis=1)
        for c in range(3):
            matrix[c] = np.linalg.lstsq(design, observed[c], rcond=None)[0]
        if np.any(np.diag(matrix) <= 0):
            raise ValueError("measure_leak: a channel does not follow its own filter's image (is the target grey?)")
        matrix = matrix / np.diag(matrix)[None, :]
    return LeakEstimate(matrix, closest_pair_px(shifts), shifts)


def closest_pair_px(points: np.ndarray) -> float:
    """The smallest distance between two of the (N, 2) `points`: how far apart the closest two channels' images
    are, given where each shows the target (or how far each moves per pixel of disparity)."""
    points = np.asarray(points, np.float64)
    return min(float(np.hypot(*(points[i] - points[j]))) for i in range(len(points)) for j in range(i + 1, len(points)))


def _move_sites(planes: np.ndarray, offsets_px: Sequence[tuple[float, float]], *, onto_centres: bool) -> np.ndarray:
    """Each channel's samples moved from where they sit in the pixel (`offsets_px`, (dx, dy) per channel) onto
    the pixel centres, or back; band-limited (`cost.shift_band_limited`), so that the round trip keeps the
    position to a thousandth of a pixel (a cubic filter moved the calibration target by 0.03 px)."""
    from mca.processing.cost import shift_band_limited

    sign = -1.0 if onto_centres else 1.0
    out = np.empty_like(np.asarray(planes, dtype=np.float32))
    for c, (dx, dy) in enumerate(offsets_px):
        out[..., c] = shift_band_limited(np.ascontiguousarray(planes[..., c], np.float32), sign * dx, sign * dy)
    return out


def unmix_sites(
    planes: np.ndarray, crosstalk: np.ndarray, offsets_px: Sequence[tuple[float, float]] | None
) -> np.ndarray:
    """(H, W, 3) planes with the crosstalk (sensor channel <- filter) taken out, each channel's samples left
    where they were: moved onto the pixel centres (`offsets_px`, e.g. `pipeline.RGGB_HALF_RES_OFFSETS_PX`;
    None: co-sited already), unmixed there by the inverse matrix, and moved back. What is measured on the
    channels' own sites afterwards (the calibration target's disparity with the Bayer offset taken out) stays
    comparable with a shot that has no crosstalk."""
    from mca.processing.pipeline import remove_crosstalk  # the inverse and its check, as the pipeline's

    matrix = np.asarray(crosstalk, np.float64)
    if matrix.shape != (3, 3):
        raise ValueError(f"crosstalk {matrix.tolist()} is not a 3x3 matrix")
    moved = planes if offsets_px is None else _move_sites(planes, offsets_px, onto_centres=True)
    unmixed = remove_crosstalk(
        moved,
        tuple((float(a), float(b), float(c)) for a, b, c in matrix),
        "the crosstalk",
        "measure it again on a grey, textured target far from focus (`mca calibrate`), or leave it out",
    )
    return unmixed if offsets_px is None else _move_sites(unmixed, offsets_px, onto_centres=False)


def combine_leaks(
    estimates: Sequence[LeakEstimate], min_separation_px: float = MIN_LEAK_SEPARATION_PX
) -> tuple[np.ndarray, int, float] | None:
    """The median, entry by entry, of the shots whose channels are at least `min_separation_px` apart, how many
    shots that is and how far they spread (the largest difference of a shot's entry from the median; 0 for one
    shot); None when no shot is that far apart."""
    usable = [e.matrix for e in estimates if e.separation_px >= min_separation_px]
    if not usable:
        return None
    matrix = np.median(np.stack(usable), axis=0)
    return matrix, len(usable), float(max(np.abs(m - matrix).max() for m in usable))


# --- the lens model and its fit -------------------------------------------------------------------------------


@dataclass(frozen=True)
class LensModel:
    """The thin-lens MCA model of one lens: disparities in pixels of pitch `pixel_pitch_mm` (eqs. 6, 11)."""

    focal_length_mm: float
    sensor_distance_mm: float  # the paper's d_ls
    filter_centre_distance_mm: float  # the paper's d_a, red to blue (widest pair)
    pixel_pitch_mm: float
    disparity_offset_px: float = 0.0  # added to every disparity (lateral colour, filter wedge, ...)

    @property
    def focus_distance_mm(self) -> float:
        """u_F = f d_ls / (d_ls - f): the distance of zero (offset-free) disparity (eq. 6)."""
        f, d = self.focal_length_mm, self.sensor_distance_mm
        return f * d / (d - f)

    def disparity_px(self, distance_mm: np.ndarray | float) -> np.ndarray | float:
        """d_a (d_ls - v) / v / pitch + offset (eq. 11 with Δd = d_ls - v)."""
        return (
            thin_lens_disparity_mm(
                distance_mm,  # type: ignore[type-var]
                self.sensor_distance_mm,
                self.focal_length_mm,
                self.filter_centre_distance_mm,
            )
            / self.pixel_pitch_mm
            + self.disparity_offset_px
        )

    def distance_mm(self, disparity_px: np.ndarray | float) -> np.ndarray | float:
        """The inverse: distance from the lens of a measured disparity (offset removed first)."""
        return thin_lens_distance_mm(
            (np.asarray(disparity_px, dtype=float) - self.disparity_offset_px) * self.pixel_pitch_mm,
            self.sensor_distance_mm,
            self.focal_length_mm,
            self.filter_centre_distance_mm,
        )

    def with_values(self, values: dict[str, float]) -> LensModel:
        return replace(self, **values)


@dataclass(frozen=True)
class Identifiability:
    """Singular values of the column-scaled Jacobian of the model at some distances, for some free parameters."""

    parameters: tuple[str, ...]
    singular_values: tuple[float, ...]

    @property
    def condition_number(self) -> float:
        smallest = self.singular_values[-1]
        return math.inf if smallest <= 0 else self.singular_values[0] / smallest

    @property
    def identifiable(self) -> bool:
        """True when every parameter is determined (relative condition number below 1e8)."""
        return self.condition_number < 1e8


def _jacobian(model: LensModel, distances_mm: np.ndarray, parameters: Sequence[str]) -> np.ndarray:
    """d disparity_px / d (relative change of each parameter; the offset per 1 px), central differences."""
    columns = []
    for name in parameters:
        value = getattr(model, name)
        step = 1e-6 if name == "disparity_offset_px" else 1e-7 * value
        scale = 1.0 if name == "disparity_offset_px" else value
        up = np.asarray(model.with_values({name: value + step}).disparity_px(distances_mm), dtype=float)
        down = np.asarray(model.with_values({name: value - step}).disparity_px(distances_mm), dtype=float)
        columns.append((up - down) / (2 * step) * scale)
    return np.stack(columns, axis=1)


def identifiability(
    model: LensModel, distances_mm: Sequence[float] | np.ndarray, parameters: Sequence[str] = PARAMETERS
) -> Identifiability:
    """How well a sweep over `distances_mm` determines `parameters` (rank and conditioning of the Jacobian)."""
    jac = _jacobian(model, np.asarray(distances_mm, dtype=float), parameters)
    jac = jac / np.linalg.norm(jac, axis=0, keepdims=True)
    values = np.linalg.svd(jac, compute_uv=False)
    return Identifiability(tuple(parameters), tuple(float(v) for v in values))


@dataclass(frozen=True)
class CalibrationFit:
    """The fitted lens, its uncertainties from the Jacobian, and how well it explains the sweep."""

    fitted: LensModel
    nominal: LensModel
    free: tuple[str, ...]
    sigma: dict[str, float]  # one standard deviation of each free parameter (and focus distance)
    correlation: np.ndarray  # between the free parameters
    distances_mm: np.ndarray
    disparities_px: np.ndarray
    residuals_px: np.ndarray  # measured - fitted disparity
    depth_errors_mm: np.ndarray  # distance from the fitted model at the measured disparity - known
    three_parameter: Identifiability = field(repr=False)

    @property
    def residual_rms_px(self) -> float:
        return float(np.sqrt(np.mean(self.residuals_px**2)))

    @property
    def max_depth_error_mm(self) -> float:
        return float(np.max(np.abs(self.depth_errors_mm)))


def fit_lens(
    distances_mm: Sequence[float] | np.ndarray,
    disparities_px: Sequence[float] | np.ndarray,
    nominal: LensModel,
    *,
    free: Sequence[str] = ("filter_centre_distance_mm", "sensor_distance_mm"),
) -> CalibrationFit:
    """Least-squares fit of the `free` parameters of `nominal` to measured (distance, disparity) pairs.

    Parameters not in `free` keep their values in `nominal` (give a known offset there). Raises
    `CalibrationFitError` when there are too few points or the free parameters are not identifiable
    over these distances (d_a, d_ls and the offset together never are: see the module docstring).
    """
    from scipy.optimize import least_squares

    u = np.asarray(distances_mm, dtype=float)
    measured = np.asarray(disparities_px, dtype=float)
    free = tuple(free)
    unknown = [name for name in free if name not in PARAMETERS]
    if unknown:
        raise CalibrationFitError(f"cannot fit {unknown}: choose among {', '.join(PARAMETERS)}")
    if u.shape != measured.shape or u.ndim != 1:
        raise CalibrationFitError("distances and disparities must be 1-D and of equal length")
    if u.size < len(free) + 2:
        raise CalibrationFitError(
            f"{u.size} points cannot fit {len(free)} parameters and estimate the noise; "
            f"shoot at least {len(free) + 2} positions"
        )
    if np.any(u <= nominal.focal_length_mm):
        raise CalibrationFitError("every target distance must exceed the focal length")
    check = identifiability(nominal, u, free)
    if not check.identifiable:
        names = ", ".join(SHORT_NAMES[n] for n in free)
        raise CalibrationFitError(
            f"{names} are not identifiable from disparities against distance (condition number "
            f"{check.condition_number:.3g}): with f fixed the model is A - B/u; fix one of them"
        )

    def model_at(x: np.ndarray) -> LensModel:
        values = {}
        for name, value in zip(free, x):
            values[name] = value if name == "disparity_offset_px" else value * getattr(nominal, name)
        return nominal.with_values(values)

    x0 = np.array([nominal.disparity_offset_px if n == "disparity_offset_px" else 1.0 for n in free])
    result = least_squares(
        lambda x: np.asarray(model_at(x).disparity_px(u), dtype=float) - measured,
        x0,
        method="lm",
        xtol=1e-14,
        ftol=1e-14,
        gtol=1e-14,
    )
    fitted = model_at(result.x)
    residuals = measured - np.asarray(fitted.disparity_px(u), dtype=float)
    dof = max(u.size - len(free), 1)
    noise_var = float(np.sum(residuals**2) / dof)
    jac = _jacobian(fitted, u, free)  # per relative change (offset: per px)
    cov_rel = np.linalg.inv(jac.T @ jac) * noise_var
    sigma: dict[str, float] = {}
    for i, name in enumerate(free):
        scale = 1.0 if name == "disparity_offset_px" else getattr(fitted, name)
        sigma[name] = float(math.sqrt(max(cov_rel[i, i], 0.0)) * scale)
    # focus distance u_F = f d_ls / (d_ls - f): propagate d_ls's sigma
    if "sensor_distance_mm" in free:
        f, d = fitted.focal_length_mm, fitted.sensor_distance_mm
        sigma["focus_distance_mm"] = f * f / (d - f) ** 2 * sigma["sensor_distance_mm"]
    std = np.sqrt(np.clip(np.diag(cov_rel), 1e-300, None))
    correlation = cov_rel / np.outer(std, std)
    depth_errors = np.asarray(fitted.distance_mm(measured), dtype=float) - u
    return CalibrationFit(
        fitted=fitted,
        nominal=nominal,
        free=free,
        sigma=sigma,
        correlation=correlation,
        distances_mm=u,
        disparities_px=measured,
        residuals_px=residuals,
        depth_errors_mm=depth_errors,
        three_parameter=identifiability(fitted, u, PARAMETERS),
    )


def scaled_aperture(aperture: FilterAperture, filter_centre_distance_mm: float) -> FilterAperture:
    """The aperture with every filter centre scaled about the axis so that the widest pair is d_a apart."""
    factor = filter_centre_distance_mm / aperture.baseline_mm
    return replace(
        aperture,
        red_mm=(aperture.red_mm[0] * factor, aperture.red_mm[1] * factor),
        green_mm=(aperture.green_mm[0] * factor, aperture.green_mm[1] * factor),
        blue_mm=(aperture.blue_mm[0] * factor, aperture.blue_mm[1] * factor),
    )


def plot_fit(
    fit: CalibrationFit, *, width_px: int = 960, height_px: int = 720, truth: LensModel | None = None
) -> np.ndarray:
    """A BGR uint8 image: measured disparity (dots) against distance, fitted curve (blue), nominal (grey),
    optional truth (green, dashed), and below it the residuals in px."""
    import cv2

    img = np.full((height_px, width_px, 3), 255, np.uint8)
    left, right, top = 90, width_px - 30, 40
    split = int(height_px * 0.68)
    bottom_main, top_res, bottom_res = split - 30, split + 10, height_px - 50
    u = fit.distances_mm
    span = max(float(u.max() - u.min()), 1.0)
    grid = np.linspace(u.min() - 0.05 * span, u.max() + 0.05 * span, 400)
    curves = [(fit.nominal, (150, 150, 150), "nominal profile"), (fit.fitted, (200, 80, 0), "fitted")]
    if truth is not None:
        curves.append((truth, (0, 160, 0), "simulated truth"))
    values = [fit.disparities_px] + [np.asarray(m.disparity_px(grid)) for m, _, _ in curves]
    y_lo = min(float(v.min()) for v in values)
    y_hi = max(float(v.max()) for v in values)
    pad = 0.05 * max(y_hi - y_lo, 1e-6)
    y_lo, y_hi = y_lo - pad, y_hi + pad

    def px(x: np.ndarray | float, y: np.ndarray | float, lo: float, hi: float, y0: int, y1: int):
        xs = left + (np.asarray(x) - grid[0]) / (grid[-1] - grid[0]) * (right - left)
        ys = y1 - (np.asarray(y) - lo) / (hi - lo) * (y1 - y0)
        return xs, ys

    font = cv2.FONT_HERSHEY_SIMPLEX
    for y0, y1 in ((top, bottom_main), (top_res, bottom_res)):
        cv2.rectangle(img, (left, y0), (right, y1), (0, 0, 0), 1)
    for tick in np.linspace(grid[0], grid[-1], 6):
        x, _ = px(tick, 0.0, 0.0, 1.0, 0, 1)
        cv2.line(img, (int(x), bottom_res), (int(x), bottom_res + 5), (0, 0, 0), 1)
        cv2.putText(img, f"{tick:.0f}", (int(x) - 22, bottom_res + 22), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(
        img, "distance from the lens (mm)", (width_px // 2 - 120, height_px - 10), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA
    )
    for tick in np.linspace(y_lo, y_hi, 6):
        _, y = px(grid[0], tick, y_lo, y_hi, top, bottom_main)
        cv2.putText(img, f"{tick:.1f}", (left - 70, int(y) + 5), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    cv2.putText(img, "disparity (px)", (left, top - 12), font, 0.5, (0, 0, 0), 1, cv2.LINE_AA)
    for model, colour, label in curves:
        xs, ys = px(grid, np.asarray(model.disparity_px(grid)), y_lo, y_hi, top, bottom_main)
        points = np.stack([xs, ys], axis=1).round().astype(np.int32)
        cv2.polylines(img, [points], False, colour, 2 if label == "fitted" else 1, cv2.LINE_AA)
    xs, ys = px(u, fit.disparities_px, y_lo, y_hi, top, bottom_main)
    for x, y in zip(xs, ys):
        cv2.circle(img, (int(round(x)), int(round(y))), 4, (0, 0, 220), -1, cv2.LINE_AA)
    for i, (_, colour, label) in enumerate(curves + [(None, (0, 0, 220), "measured")]):
        cv2.putText(img, label, (left + 15, top + 22 + 20 * i), font, 0.5, colour, 1, cv2.LINE_AA)
    text = (
        f"d_a {fit.fitted.filter_centre_distance_mm:.4f} mm  d_ls {fit.fitted.sensor_distance_mm:.4f} mm  "
        f"focus {fit.fitted.focus_distance_mm:.1f} mm  rms {fit.residual_rms_px:.4f} px"
    )
    cv2.putText(img, text, (left + 15, bottom_main - 12), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    r_max = max(float(np.abs(fit.residuals_px).max()) * 1.3, 1e-3)
    _, zero = px(grid[0], 0.0, -r_max, r_max, top_res, bottom_res)
    cv2.line(img, (left, int(zero)), (right, int(zero)), (150, 150, 150), 1)
    xs, ys = px(u, fit.residuals_px, -r_max, r_max, top_res, bottom_res)
    for x, y in zip(xs, ys):
        cv2.circle(img, (int(round(x)), int(round(y))), 3, (0, 0, 220), -1, cv2.LINE_AA)
    cv2.putText(img, f"residual (px), +-{r_max:.3f}", (left + 5, top_res + 16), font, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return img
