"""The calibration sweep at the bench: move the rail, shoot, download, measure the target's disparity, record, resume.

Rail position -> object distance: sweep position s (mm, `--from` .. `--to`) puts the
rail at `rail_start_mm + (s - from)` mm from its home switch, and the target then stands
u = target_distance_at_zero_mm + (rail position) from the lens (the rail moves the target
away from the camera as its position grows). The default distance at rail zero is the
profile's focus distance plus the sweep start, so that s reads as the offset from the
nominal focus plane (s = -100 is 100 mm nearer than focus).

Every measured position is a row of the `calibration` table in `DIR/catalog.sqlite`
(beside the tether `shots` table); a rerun after a fault skips positions already there.
"""

from __future__ import annotations

import dataclasses
import datetime
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture.catalog import open_database
from mca.processing.calibration import (
    CalibrationFit,
    LensModel,
    baseline_direction,
    scaled_aperture,
    target_disparity_px,
)
from mca.processing.camera import CameraProfile

_SCHEMA = """
CREATE TABLE IF NOT EXISTS calibration (
    position_mm REAL PRIMARY KEY,
    rail_mm REAL NOT NULL,
    distance_mm REAL NOT NULL,
    shot_id INTEGER,
    file_name TEXT NOT NULL,
    mosaic_height_px INTEGER NOT NULL,
    disparity_raw_px REAL NOT NULL,
    disparity_px REAL NOT NULL,
    across_px REAL NOT NULL,
    correlation REAL NOT NULL,
    measured_at TEXT NOT NULL
);
"""


class CalibrationError(RuntimeError):
    """The sweep stopped: says where, what was kept, the device's own message, and what to do next."""


@dataclass(frozen=True)
class SweepPlan:
    """Where to shoot: sweep positions and how they map onto the rail and onto object distance."""

    from_mm: float
    to_mm: float
    step_mm: float
    target_distance_at_zero_mm: float  # object distance (mm from the lens) with the rail at 0 mm
    rail_start_mm: float = 0.0  # rail position of the first sweep position

    def __post_init__(self) -> None:
        if not self.step_mm > 0:
            raise ValueError(f"--step must be positive, got {self.step_mm}")
        if self.to_mm < self.from_mm:
            raise ValueError(f"--to {self.to_mm} is before --from {self.from_mm}")

    @property
    def positions_mm(self) -> list[float]:
        count = int(math.floor((self.to_mm - self.from_mm) / self.step_mm + 1e-9)) + 1
        return [round(self.from_mm + i * self.step_mm, 6) for i in range(count)]

    def rail_mm(self, position_mm: float) -> float:
        return self.rail_start_mm + (position_mm - self.from_mm)

    def distance_mm(self, rail_mm: float) -> float:
        """u = distance at rail zero + rail position."""
        return self.target_distance_at_zero_mm + rail_mm


@dataclass(frozen=True)
class CalibrationPoint:
    """One measured position of the sweep (disparity_px in pixels of the profile's pitch)."""

    position_mm: float
    rail_mm: float
    distance_mm: float
    shot_id: int | None
    file_name: str
    mosaic_height_px: int
    disparity_raw_px: float
    disparity_px: float
    across_px: float
    correlation: float


class CalibrationStore:
    """The `calibration` table in `DIR/catalog.sqlite`: one committed row per measured position."""

    def __init__(self, path: Path) -> None:
        self.path = Path(path)
        self.db = open_database(self.path, _SCHEMA)

    def close(self) -> None:
        self.db.close()

    def points(self) -> list[CalibrationPoint]:
        rows = self.db.execute(
            "SELECT position_mm, rail_mm, distance_mm, shot_id, file_name, mosaic_height_px,"
            " disparity_raw_px, disparity_px, across_px, correlation FROM calibration"
            " ORDER BY position_mm"
        ).fetchall()
        return [CalibrationPoint(*row) for row in rows]

    def add(self, point: CalibrationPoint) -> None:
        fields = dataclasses.astuple(point) + (datetime.datetime.now().isoformat(timespec="seconds"),)
        self.db.execute("INSERT OR REPLACE INTO calibration VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)", fields)
        self.db.commit()


def nominal_lens(profile: CameraProfile, disparity_offset_px: float = 0.0) -> LensModel:
    """The profile's lens as a `LensModel` (disparities in pixels of the profile's pitch)."""
    if profile.lens is None or profile.pixel_pitch_mm is None or not profile.height_px:
        raise ValueError(
            f"profile '{profile.name}' needs [lens], camera.pixel_pitch_mm and camera.height_px to be calibrated"
        )
    return LensModel(
        profile.lens.focal_length_mm,
        profile.lens.sensor_distance_mm,
        profile.aperture.baseline_mm,
        profile.pixel_pitch_mm,
        disparity_offset_px,
    )


def measure_file(
    path: Path, profile: CameraProfile, max_disparity_px: float = 24.0, crosstalk: np.ndarray | None = None
) -> tuple[float, float, float, float, int]:
    """(disparity in the file's mosaic px, in profile px, across px, correlation, mosaic height) of a shot.

    `max_disparity_px` (pixels of the profile's pitch) bounds the search. `crosstalk` (sensor channel <- filter,
    `measure_sweep_crosstalk`): taken out of the planes first; left in, the faint copy of each filter's image in
    the other channels pulls the measured disparity towards zero (4-5 % at 2-3 px on the simulated bench).
    """
    from mca.capture.raw import read_raw
    from mca.processing.calibration import BAYER_RED_FROM_BLUE_PX, unmix_sites
    from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX

    frame = read_raw(path)
    planes = frame.planes
    bayer_offset_px = BAYER_RED_FROM_BLUE_PX if frame.half_resolution else (0.0, 0.0)
    if crosstalk is not None:  # unmixed where every channel is sampled at the same place, then moved back
        planes = unmix_sites(planes, crosstalk, RGGB_HALF_RES_OFFSETS_PX if frame.half_resolution else None)
    height = int(planes.shape[0] * 2) if frame.half_resolution else int(planes.shape[0])
    to_profile = (profile.height_px or height) / height  # a reduced image has a proportionally larger pitch
    est = target_disparity_px(
        planes[..., 0],
        planes[..., 2],
        baseline_direction(profile.aperture),
        bayer_offset_px=bayer_offset_px,
        max_disparity_px=max_disparity_px / to_profile + 4.0,
    )
    return est.disparity_px, est.disparity_px * to_profile, est.across_px, est.correlation, height


@dataclass
class SweepOutcome:
    points: list[CalibrationPoint]
    shot_positions_mm: list[float]  # positions shot in this run (resumed ones excluded)


def _search_bound_px(profile: CameraProfile, plan: SweepPlan) -> float:
    """How far (profile px) a shot's disparity is searched: half as far again as the nominal lens puts the
    farthest position of the sweep, plus 8 px."""
    nominal = nominal_lens(profile)
    span = [nominal.disparity_px(plan.distance_mm(plan.rail_mm(s))) for s in plan.positions_mm]
    return 1.5 * max(abs(float(v)) for v in span) + 8.0


def run_sweep(
    plan: SweepPlan,
    profile: CameraProfile,
    out_dir: Path,
    *,
    camera_factory: Callable[[], Any],
    rail: Any,
    log: Callable[[str], None] = lambda m: None,
    on_point: Callable[[CalibrationPoint], None] | None = None,
    feed_mm_per_min: float | None = None,
) -> SweepOutcome:
    """Shoot every position of `plan` not yet in `out_dir/catalog.sqlite`; raise `CalibrationError` on a fault.

    `rail` is an open `devices.rail.Rail` (homed here); `camera_factory` opens the camera (see
    `capture.tether.camera_factory`). Each position: move, read the position back, capture,
    download (verified, catalogued), measure, commit. Nothing already committed is shot again.
    """
    from mca.capture.raw import RawReadError
    from mca.capture.tether import TetherSession
    from mca.devices.ptp.transport import TransportError
    from mca.devices.rail import RailError

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    store = CalibrationStore(out_dir / "catalog.sqlite")
    done = {round(p.position_mm, 6): p for p in store.points()}
    for point in done.values():
        expected = plan.distance_mm(plan.rail_mm(point.position_mm))
        if abs(point.distance_mm - expected) > 1.0:
            store.close()
            raise CalibrationError(
                f"{out_dir}: position {point.position_mm:+.1f} mm was recorded at {point.distance_mm:.1f} mm from "
                f"the lens, this sweep puts it at {expected:.1f} mm; use a new --dir or the earlier "
                "--target-distance-at-zero / --from"
            )
    todo = [s for s in plan.positions_mm if round(s, 6) not in done]
    if done:
        log(f"resuming: {len(done)} position(s) already measured in {store.path}, {len(todo)} to go")
    max_disparity_px = _search_bound_px(profile, plan)
    shot: list[float] = []
    session = TetherSession(camera_factory, out_dir, log=log) if todo else None
    position = math.nan
    try:
        if todo:
            rail.home()
        for position in todo:
            rail_target = plan.rail_mm(position)
            status = rail.move_to(rail_target, feed_mm_per_min)
            distance = plan.distance_mm(status.position_mm)
            assert session is not None
            result = session.capture(1)[0]
            shot.append(position)
            if result.path is None:
                raise TransportError(f"shot {result.shot_id} was not downloaded: {result.message}")
            raw_px, disparity, across, correlation, height = measure_file(result.path, profile, max_disparity_px)
            point = CalibrationPoint(
                position,
                status.position_mm,
                distance,
                result.shot_id,
                result.path.name,
                height,
                raw_px,
                disparity,
                across,
                correlation,
            )
            store.add(point)
            done[round(position, 6)] = point
            log(
                f"{position:+8.1f} mm  rail {status.position_mm:7.2f} mm  u {distance:8.2f} mm  "
                f"disparity {disparity:+8.3f} px  ({result.path.name})"
            )
            if on_point is not None:
                on_point(point)
    except RailError as exc:
        raise CalibrationError(
            f"calibration sweep stopped at {position:+.1f} mm: {exc} -- {len(done)} of {len(plan.positions_mm)} "
            f"positions are recorded in {store.path}; fix the rail and rerun the same command to shoot only the "
            "rest"
        ) from exc
    except (TransportError, RawReadError, OSError, ValueError) as exc:
        raise CalibrationError(
            f"calibration sweep stopped at {position:+.1f} mm (camera or file): {exc}. {len(done)} of "
            f"{len(plan.positions_mm)} positions are recorded in {store.path}; rerun the same command to "
            "shoot only the rest"
        ) from exc
    finally:
        if session is not None:
            session.close()
        points = sorted(done.values(), key=lambda p: p.position_mm)
        store.close()
    return SweepOutcome(points, shot)


def measure_sweep_crosstalk(
    points: list[CalibrationPoint],
    directory: Path,
    profile: CameraProfile,
    log: Callable[[str], None] = lambda m: None,
) -> tuple[np.ndarray | None, int, float]:
    """The crosstalk of the camera and lens (sensor channel <- filter) from the sweep's shots, how many shots
    gave it and how far apart they are (the largest difference of an entry from the result; 0 for one shot):
    `processing.calibration.measure_leak` on each shot whose channels show the target at least
    `MIN_LEAK_SEPARATION_PX` apart (the ends of the sweep, away from focus), the median of those; (None, 0, 0)
    when no shot is that far from focus (sweep farther, or give the profile's own `aperture.crosstalk`). Shots
    that disagree by more than a few thousandths point at a coloured target or a bad shot."""
    from mca.capture.raw import RawReadError, read_raw
    from mca.processing.calibration import MIN_LEAK_SEPARATION_PX, closest_pair_px, combine_leaks, measure_leak
    from mca.processing.pipeline import RGGB_HALF_RES_OFFSETS_PX

    nominal = nominal_lens(profile)
    closest = closest_pair_px(np.array([profile.aperture.shift_per_disparity(c) for c in ("red", "green", "blue")]))
    estimates = []
    for point in points:
        # shots the nominal lens puts too near focus are not read: their closest two channels are less than the
        # minimum apart even in mosaic pixels (half-resolution planes halve it: those are read, then dropped)
        mosaic_px = (
            abs(float(nominal.disparity_px(point.distance_mm)))
            * point.mosaic_height_px
            / (profile.height_px or point.mosaic_height_px)
        )
        if mosaic_px * closest < MIN_LEAK_SEPARATION_PX:
            continue
        path = Path(directory) / point.file_name
        try:
            frame = read_raw(path)
            offsets = RGGB_HALF_RES_OFFSETS_PX if frame.half_resolution else None
            estimate = measure_leak(frame.planes, channel_offsets_px=offsets)
        except (RawReadError, OSError, ValueError) as exc:
            log(f"crosstalk: {path.name} skipped ({exc})")
            continue
        estimates.append(estimate)
        apart = estimate.separation_px >= MIN_LEAK_SEPARATION_PX
        verdict = "" if apart else f": too close to read ({MIN_LEAK_SEPARATION_PX:g} px needed)"
        log(f"crosstalk: {path.name}  channels {estimate.separation_px:.1f} px apart{verdict}")
    combined = combine_leaks(estimates)
    return (None, 0, 0.0) if combined is None else combined


# --- the simulated bench -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SimDeviation:
    """How the simulated lens differs from its profile (the defaults of `--sim-deviation`)."""

    baseline_factor: float = 1.03  # effective d_a = 1.03 x nominal
    focus_factor: float = 1.02  # d_ls chosen so that the focus distance is 1.02 x nominal
    disparity_offset_px: float = 0.3  # red-blue misregistration, pixels of the profile's pitch
    leak: float = 0.0  # crosstalk: each sensor channel takes this share from the other two filters (half each)

    @classmethod
    def parse(cls, text: str) -> SimDeviation:
        """`BASELINE,FOCUS,OFFSET[,LEAK]`, e.g. `1.03,1.02,0.3` or `1.03,1.02,0.3,0.06`."""
        try:
            values = [float(v) for v in text.split(",")]
        except ValueError:
            values = []
        leak_ok = len(values) != 4 or 0.0 <= values[3] < 0.5
        if len(values) not in (3, 4) or values[0] <= 0 or values[1] <= 0 or not leak_ok:
            raise ValueError(
                f"--sim-deviation must be BASELINE_FACTOR,FOCUS_FACTOR,OFFSET_PX[,LEAK] (LEAK in [0, 0.5)), got {text!r}"
            )
        return cls(*values)

    def crosstalk(self) -> tuple[tuple[float, float, float], ...] | None:
        """The simulated sensor's crosstalk (sensor channel <- filter), None without a leak."""
        from mca.capture.simulate_app import crosstalk_matrix

        return crosstalk_matrix(self.leak)

    def truth(self, profile: CameraProfile) -> LensModel:
        nominal = nominal_lens(profile)
        f = nominal.focal_length_mm
        focus = nominal.focus_distance_mm * self.focus_factor
        return dataclasses.replace(
            nominal,
            sensor_distance_mm=f * focus / (focus - f),
            filter_centre_distance_mm=nominal.filter_centre_distance_mm * self.baseline_factor,
            disparity_offset_px=self.disparity_offset_px,
        )


class SimBench:
    """The simulated bench: the camera photographs a textured target wherever the simulated rail's carriage is.

    `frame(index)` is the simulated EOS 70D's frame source: it reads the carriage position from the
    simulated GRBL controller (`rail_runner`, set once the rail is open), renders `target_scene(u)`
    through the deviating lens at `scale` of the profile's size, and returns the CR2 bytes.
    """

    def __init__(
        self, profile: CameraProfile, plan: SweepPlan, deviation: SimDeviation, *, scale: float = 0.25, seed: int = 0
    ) -> None:
        from mca.devices.sim.render import SimulationOptics

        self.profile = profile
        self.plan = plan
        self.deviation = deviation
        self.truth = deviation.truth(profile)
        nominal = SimulationOptics.from_profile(profile, scale)
        self.optics = nominal.perturbed(
            baseline_factor=deviation.baseline_factor,
            sensor_distance_factor=self.truth.sensor_distance_mm / nominal.sensor_distance_mm,
        )
        leaking = deviation.crosstalk()
        if leaking is not None:  # the sensor takes some of every filter's light in every channel
            self.optics = dataclasses.replace(
                self.optics, aperture=dataclasses.replace(self.optics.aperture, crosstalk=leaking)
            )
        self.seed = seed
        self.rail_runner: Any = None
        self.distances_shot_mm: list[float] = []

    def carriage_rail_mm(self) -> float:
        from mca.devices.rail import grbl_protocol as gp

        if self.rail_runner is None:
            raise RuntimeError("the simulated camera has no simulated rail to look at (open the rail first)")
        sim = self.rail_runner.sim
        return gp.rail_mm(sim.machine_x_mm, gp.GrblAxisSettings.from_settings(sim.settings))

    def frame(self, index: int) -> tuple[str, bytes]:
        from mca.devices.sim.scenes import target_scene
        from mca.devices.sim.world import capture_cr2_bytes, render_scene

        distance = self.plan.distance_mm(self.carriage_rail_mm())
        self.distances_shot_mm.append(distance)
        shot = render_scene(target_scene(distance), self.profile, optics=self.optics, seed=self.seed + index)
        offset_px = (
            self.deviation.disparity_offset_px
            * self.optics.height_px
            / (self.profile.height_px or self.optics.height_px)
        )
        if offset_px:
            mosaic = misregister_red(shot.mosaic, offset_px, baseline_direction(self.optics.aperture))
            shot = dataclasses.replace(shot, mosaic=mosaic)
        return f"IMG_{index + 1:04d}.CR2", capture_cr2_bytes(shot, self.profile)


def misregister_red(mosaic: np.ndarray, shift_px: float, direction: tuple[float, float]) -> np.ndarray:
    """The mosaic with its red sites' content moved `shift_px` mosaic px along `direction` (a disparity offset)."""
    out = mosaic.copy()
    red = mosaic[0::2, 0::2].astype(np.float64)
    ky = np.fft.fftfreq(red.shape[0])[:, None]
    kx = np.fft.fftfreq(red.shape[1])[None, :]
    dx, dy = direction[0] * shift_px / 2.0, direction[1] * shift_px / 2.0  # plane px
    moved = np.real(np.fft.ifft2(np.fft.fft2(red) * np.exp(-2j * np.pi * (kx * dx + ky * dy))))
    out[0::2, 0::2] = np.clip(np.round(moved), 0, np.iinfo(mosaic.dtype).max).astype(mosaic.dtype)
    return out


# --- the calibrated profile -----------------------------------------------------------------------------------


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        v = float(value)
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def calibrated_profile_toml(
    profile: CameraProfile,
    fit: CalibrationFit,
    plan: SweepPlan,
    *,
    shots_dir: str,
    name: str | None = None,
    crosstalk: np.ndarray | None = None,
) -> str:
    """A profile TOML: the profile with the fitted d_ls and filter centres scaled to the fitted d_a, plus a
    `[calibration]` table (date, sweep, residuals, sigmas) that the profile loader ignores. `crosstalk`: the
    measured one (`measure_sweep_crosstalk`) replaces the profile's `aperture.crosstalk`."""
    fitted = fit.fitted
    aperture = scaled_aperture(profile.aperture, fitted.filter_centre_distance_mm)
    lens = profile.lens
    assert lens is not None
    lines = [
        f"# Calibrated with `mca calibrate` from profile '{profile.name}' ({profile.source}).",
        f"name = {_toml_value(name or profile.name + '-calibrated')}",
        "",
        "[camera]",
        f"model = {_toml_value(profile.model)}",
    ]
    for key in ("pixel_pitch_mm", "width_px", "height_px"):
        if getattr(profile, key) is not None:
            lines.append(f"{key} = {_toml_value(getattr(profile, key))}")
    lines += [
        "",
        "[lens]",
        f"focal_length_mm = {_toml_value(lens.focal_length_mm)}",
        f"sensor_distance_mm = {_toml_value(round(fitted.sensor_distance_mm, 6))}"
        f"   # fitted; focus at {fitted.focus_distance_mm:.2f} mm",
    ]
    if lens.f_number is not None:
        lines.append(f"f_number = {_toml_value(lens.f_number)}")
    lines += ["", "[aperture]", f"filter_diameter_mm = {_toml_value(aperture.filter_diameter_mm)}"]
    for channel in ("red", "green", "blue"):
        x, y = aperture.centre_mm(channel)
        lines.append(f"{channel} = {_toml_value([round(x, 6), round(y, 6)])}")
    if profile.aperture.diameter_mm is not None and (
        lens.f_number is None or abs(lens.focal_length_mm / lens.f_number - profile.aperture.diameter_mm) > 1e-9
    ):
        lines.append(f"diameter_mm = {_toml_value(profile.aperture.diameter_mm)}")
    if crosstalk is not None:
        rows = [[round(float(v), 5) for v in row] for row in crosstalk]
        lines.append(f"crosstalk = {_toml_value(rows)}   # measured on the sweep's shots")
    elif aperture.crosstalk is not None:
        lines.append(f"crosstalk = {_toml_value([list(r) for r in aperture.crosstalk])}")
    sigma = fit.sigma
    lines += [
        "",
        "[calibration]",
        f"date = {_toml_value(datetime.datetime.now().isoformat(timespec='seconds'))}",
        f"from_profile = {_toml_value(profile.name)}",
        f"sweep_from_mm = {_toml_value(plan.from_mm)}",
        f"sweep_to_mm = {_toml_value(plan.to_mm)}",
        f"sweep_step_mm = {_toml_value(plan.step_mm)}",
        f"target_distance_at_zero_mm = {_toml_value(plan.target_distance_at_zero_mm)}",
        f"rail_start_mm = {_toml_value(plan.rail_start_mm)}",
        f"points = {_toml_value(len(fit.distances_mm))}",
        f"shots = {_toml_value(shots_dir)}",
        f"free_parameters = {_toml_value([p for p in fit.free])}",
        f"filter_centre_distance_mm = {_toml_value(fitted.filter_centre_distance_mm)}",
        f"sensor_distance_mm = {_toml_value(fitted.sensor_distance_mm)}",
        f"focus_distance_mm = {_toml_value(fitted.focus_distance_mm)}",
        f"disparity_offset_px = {_toml_value(fitted.disparity_offset_px)}"
        "   # fixed unless fitted: pixels of camera.pixel_pitch_mm",
        f"residual_rms_px = {_toml_value(fit.residual_rms_px)}",
        f"max_depth_error_mm = {_toml_value(fit.max_depth_error_mm)}",
    ]
    for key, value in sigma.items():
        lines.append(f"sigma_{key} = {_toml_value(value)}")
    if len(fit.free) == 2:
        lines.append(f"correlation = {_toml_value(float(fit.correlation[0, 1]))}")
    lines.append(
        "three_parameter_singular_values = "
        f"{_toml_value(list(fit.three_parameter.singular_values))}   # d_a, d_ls, offset: rank 2"
    )
    lines += [
        f"nominal_filter_centre_distance_mm = {_toml_value(fit.nominal.filter_centre_distance_mm)}",
        f"nominal_sensor_distance_mm = {_toml_value(fit.nominal.sensor_distance_mm)}",
        f"distances_mm = {_toml_value([round(float(v), 4) for v in fit.distances_mm])}",
        f"disparities_px = {_toml_value([round(float(v), 5) for v in fit.disparities_px])}",
        f"residuals_px = {_toml_value([round(float(v), 5) for v in fit.residuals_px])}",
    ]
    return "\n".join(lines) + "\n"


# --- the application side of `mca calibrate` -------------------------------------------------------------------------


class CalibrationUsageError(ValueError):
    """Options that cannot make a calibration (bad profile, sweep, deviation, camera/rail pairing)."""


@dataclass(frozen=True)
class CalibrationRequest:
    """`mca calibrate`'s options, as given (None: the config file's camera, rail and profile)."""

    out: Path  # calibrated profile TOML to write; the plot goes beside it as .png
    camera: str | None = None
    rail: str | None = None
    profile: str | None = None
    from_mm: float = -100.0
    to_mm: float = 150.0
    step_mm: float = 10.0
    shots_dir: Path | None = None  # default: OUT stem + "-sweep"
    target_distance_at_zero_mm: float | None = None  # default: the profile's focus distance + from_mm
    rail_start_mm: float = 0.0
    disparity_offset_px: float = 0.0
    feed_mm_per_min: float | None = None
    sim_deviation: str = "1.03,1.02,0.3"
    sim_scale: float = 0.25
    crosstalk: bool = True  # measure the crosstalk on the shots far from focus, and take it out before the fit


@dataclass
class CalibrationSetup:
    """A checked request: the nominal profile and lens, the sweep, where the shots go, the camera and the rail."""

    request: CalibrationRequest
    camera: str
    rail: str
    profile: CameraProfile
    nominal: LensModel
    plan: SweepPlan
    directory: Path
    camera_factory: Callable[[], Any]
    bench: SimBench | None = None  # the simulated bench when the camera is `sim`

    def describe(self) -> str:
        """The sweep in one line: range, positions, the target's distance at rail zero, the shots folder."""
        r = self.request
        return (
            f"sweep {r.from_mm:+.1f} .. {r.to_mm:+.1f} mm step {r.step_mm} mm: {len(self.plan.positions_mm)} "
            f"positions, target at {self.plan.target_distance_at_zero_mm:.1f} mm from the lens with the rail at 0; "
            f"shots in {self.directory}"
        )


@dataclass
class CalibrationRun:
    """A finished calibration: the fit, the files written, and (simulated bench) the lens it should have found."""

    setup: CalibrationSetup
    outcome: SweepOutcome
    fit: CalibrationFit
    profile_text: str  # the calibrated profile TOML, as written to `out`
    plot: np.ndarray  # the fit plot (BGR), as written to `plot_path`
    plot_path: Path
    model_error_mm: float | None = None  # simulated bench: the fitted profile's worst depth error over the sweep
    crosstalk: np.ndarray | None = None  # measured (sensor channel <- filter, unit diagonal), None: not measured
    crosstalk_shots: int = 0  # how many shots it was measured on
    crosstalk_spread: float = 0.0  # the largest difference of a shot's entry from the result
    crosstalk_applied: bool = False  # taken out before the fit and written into the profile
    residual_without_crosstalk_px: float | None = None  # the fit's residual rms with the crosstalk left in

    PARAMETERS = ("filter_centre_distance_mm", "sensor_distance_mm", "focus_distance_mm", "disparity_offset_px")
    LABELS = ("d_a (red-blue) mm", "d_ls mm", "focus distance mm", "disparity offset px (fixed)")

    def parameter_rows(self) -> list[tuple[str, float, float, float | None, float | None]]:
        """(label, nominal, fitted, sigma, simulated truth) per lens parameter; sigma None for a fixed one."""
        truth = self.setup.bench.truth if self.setup.bench is not None else None
        rows = []
        for name, label in zip(self.PARAMETERS, self.LABELS):
            sigma = self.fit.sigma.get(name) if name != "disparity_offset_px" else None
            rows.append(
                (
                    label,
                    getattr(self.fit.nominal, name),
                    getattr(self.fit.fitted, name),
                    sigma,
                    getattr(truth, name) if truth is not None else None,
                )
            )
        return rows

    def report_lines(self) -> list[str]:
        """The printed report: the fit's residuals, the table of parameters, the simulated lens check, the files."""
        fit, bench = self.fit, self.setup.bench
        lines = [
            f"fit over {len(self.outcome.points)} positions ({len(self.outcome.shot_positions_mm)} shot now): "
            f"residual rms {fit.residual_rms_px:.4f} px, max depth error {fit.max_depth_error_mm:.3f} mm"
        ]
        header = f"{'':28s}{'nominal':>12s}{'fitted':>12s}{'sigma':>10s}"
        lines.append(header + (f"{'sim truth':>12s}{'error':>9s}" if bench else ""))
        for label, nom, value, sigma, truth in self.parameter_rows():
            line = f"{label:28s}{nom:12.4f}{value:12.4f}{(f'{sigma:.2g}' if sigma is not None else '-'):>10s}"
            if truth is not None:
                error = f"{(value - truth) / truth * 100:+.3f}%" if "px" not in label else f"{value - truth:+.3f}px"
                line += f"{truth:12.4f}{error:>9s}"
            lines.append(line)
        if self.model_error_mm is not None:
            lines.append(
                "depth error of the fitted profile against the simulated lens over the sweep: "
                f"{self.model_error_mm:.3f} mm max"
            )
        lines += self.crosstalk_lines()
        lines.append(f"wrote {self.setup.request.out} and {self.plot_path}")
        return lines

    def sim_crosstalk(self) -> np.ndarray | None:
        """Simulated bench: the crosstalk it rendered, columns scaled to a unit diagonal as measured."""
        bench = self.setup.bench
        leaking = bench.deviation.crosstalk() if bench is not None else None
        if leaking is None:
            return None if bench is None else np.eye(3)
        matrix = np.asarray(leaking, np.float64)
        return matrix / np.diag(matrix)[None, :]

    def crosstalk_lines(self) -> list[str]:
        """The report's crosstalk: not measured (and why), or the matrix and whether it was taken out."""
        if not self.setup.request.crosstalk:
            return ["crosstalk: not measured (--no-crosstalk)"]
        if self.crosstalk is None:
            return [
                "crosstalk: not measured: no shot was far enough from focus for the channels' images to part "
                "(sweep farther from focus, or give it in the profile's aperture.crosstalk)"
            ]
        with_rms, without_rms = self.fit.residual_rms_px, self.residual_without_crosstalk_px
        if self.crosstalk_applied:
            verdict = (
                f"taken out before the fit and written into the profile (residual {with_rms:.4f} px; "
                f"{without_rms:.4f} px left in)"
            )
        else:
            verdict = (
                f"left in and not written: taking it out does not fit the sweep better ({without_rms:.4f} px left "
                f"in); it is below what these shots can measure"
            )
        shots = f"{self.crosstalk_shots} shot(s)"
        if self.crosstalk_shots > 1:
            shots += f" agreeing within {self.crosstalk_spread:.4f}"
        lines = [f"crosstalk (sensor channel <- filter) from {shots}, {verdict}:"]
        truth = self.sim_crosstalk()
        for name, row, k in zip(("red", "green", "blue"), self.crosstalk, range(3)):
            text = f"  {name:6s}" + "".join(f"{v:9.4f}" for v in row)
            if truth is not None:
                text += "   sim truth" + "".join(f"{v:9.4f}" for v in truth[k])
            lines.append(text)
        return lines

    def document(self) -> dict[str, Any]:
        """`mca calibrate --json`: the files, the counts, the residuals and every parameter."""
        from mca.capture.outputs import json_safe

        rows = self.parameter_rows()
        return json_safe(
            {
                "profile": str(self.setup.request.out),
                "plot": str(self.plot_path),
                "shots_dir": str(self.setup.directory),
                "positions": len(self.outcome.points),
                "shot_now": len(self.outcome.shot_positions_mm),
                "residual_rms_px": self.fit.residual_rms_px,
                "max_depth_error_mm": self.fit.max_depth_error_mm,
                "parameters": {
                    name: {"nominal": row[1], "fitted": row[2], "sigma": row[3], "sim_truth": row[4]}
                    for name, row in zip(self.PARAMETERS, rows)
                },
                "sim_model_error_mm": self.model_error_mm,
                "crosstalk": None if self.crosstalk is None else self.crosstalk.tolist(),
                "crosstalk_shots": self.crosstalk_shots,
                "crosstalk_spread": self.crosstalk_spread,
                "crosstalk_applied": self.crosstalk_applied,
                "residual_without_crosstalk_px": self.residual_without_crosstalk_px,
                "sim_crosstalk": None if (truth := self.sim_crosstalk()) is None else truth.tolist(),
            }
        )


def plan_calibration(request: CalibrationRequest) -> CalibrationSetup:
    """Fill the camera, rail and profile from the config, check the sweep and choose the camera (the simulated
    bench for `sim`); a `CalibrationUsageError` names what is wrong before anything moves."""
    from mca.capture.config import ConfigError, fill_from_config
    from mca.devices.cameras import make_sim_rig, open_camera
    from mca.devices.profiles import load_profile
    from mca.processing.camera import ProfileError

    try:
        chosen = fill_from_config(camera=request.camera, rail=request.rail, profile=request.profile)
        camera, rail = str(chosen["camera"]), str(chosen["rail"])
        profile = load_profile(str(chosen["profile"]))
        nominal = nominal_lens(profile, request.disparity_offset_px)
        at_zero = request.target_distance_at_zero_mm
        at_zero = at_zero if at_zero is not None else nominal.focus_distance_mm + request.from_mm
        plan = SweepPlan(request.from_mm, request.to_mm, request.step_mm, at_zero, request.rail_start_mm)
        deviation = SimDeviation.parse(request.sim_deviation)
    except (ConfigError, ProfileError, ValueError) as exc:
        raise CalibrationUsageError(str(exc)) from None
    out = request.out
    directory = request.shots_dir if request.shots_dir is not None else out.with_name(out.stem + "-sweep")
    bench = None
    if camera == "sim" and rail != "sim":
        raise CalibrationUsageError("--camera sim photographs the simulated rail only: use --rail sim with it")
    if camera == "sim":
        bench = SimBench(profile, plan, deviation, scale=request.sim_scale)
        factory = open_camera("sim", rig=make_sim_rig(bench.frame))
    else:
        try:
            factory = open_camera(camera)
        except ValueError as exc:
            raise CalibrationUsageError(str(exc)) from None
    return CalibrationSetup(request, camera, rail, profile, nominal, plan, directory, factory, bench)


def run_calibration(setup: CalibrationSetup, log: Callable[[str], None] = lambda text: None) -> CalibrationRun:
    """Sweep the rail, fit d_a and d_ls, and write the calibrated profile (checked by the loader) and its plot.

    Raises `CalibrationError` when the rail, the camera or the fit fails (what was shot is kept; rerun to resume)."""
    import tomllib

    import cv2

    from mca.devices.rail import RailError, open_rail
    from mca.processing.calibration import CalibrationFitError, fit_lens, plot_fit
    from mca.processing.camera import profile_from_mapping

    bench, request = setup.bench, setup.request
    try:
        options = {"sim_speedup": 200.0, "poll_interval_s": 0.01} if setup.rail == "sim" else {}
        with open_rail(setup.rail, **options) as bench_rail:
            if bench is not None:  # the simulated camera looks at the simulated rail (`plan_calibration` pairs them)
                bench.rail_runner = bench_rail.simulator  # type: ignore[attr-defined]
            outcome = run_sweep(
                setup.plan,
                setup.profile,
                setup.directory,
                camera_factory=setup.camera_factory,
                rail=bench_rail,
                log=log,
                feed_mm_per_min=request.feed_mm_per_min,
            )
    except RailError as exc:
        raise CalibrationError(f"{exc} Nothing was shot at this run's remaining positions; rerun to resume.") from exc
    points = outcome.points

    def lens_fit(measured: list[CalibrationPoint]) -> CalibrationFit:
        try:
            return fit_lens([p.distance_mm for p in measured], [p.disparity_px for p in measured], setup.nominal)
        except CalibrationFitError as exc:
            raise CalibrationError(f"{exc} ({len(measured)} points in {setup.directory})") from exc

    fit = lens_fit(points)
    crosstalk, crosstalk_shots, spread, without_rms, applied = None, 0, 0.0, None, False
    if request.crosstalk:
        crosstalk, crosstalk_shots, spread = measure_sweep_crosstalk(points, setup.directory, setup.profile, log)
    if crosstalk is not None:
        # the leak is taken out only when the sweep then fits the lens model better: its copies bend the
        # measured disparities near focus, which the model cannot follow; a leak below what the shots can
        # measure makes the fit worse when taken out, and is left in (and not written into the profile)
        unmixed = _remeasured(points, setup, crosstalk, log)
        unmixed_fit = lens_fit(unmixed)
        without_rms = fit.residual_rms_px
        applied = unmixed_fit.residual_rms_px < fit.residual_rms_px
        if applied:
            points, fit = unmixed, unmixed_fit
    text = calibrated_profile_toml(
        setup.profile, fit, setup.plan, shots_dir=str(setup.directory), crosstalk=crosstalk if applied else None
    )
    out = request.out
    profile_from_mapping(tomllib.loads(text), str(out))  # the loader accepts what we write
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    plot = plot_fit(fit, truth=bench.truth if bench is not None else None)
    plot_path = out.with_suffix(".png")
    cv2.imwrite(str(plot_path), plot)
    model_error = None
    if bench is not None:
        grid = np.linspace(min(p.distance_mm for p in points), max(p.distance_mm for p in points), 101)
        fitted = np.asarray(fit.fitted.distance_mm(bench.truth.disparity_px(grid)))
        model_error = float(np.abs(fitted - grid).max())
    return CalibrationRun(
        setup,
        outcome,
        fit,
        text,
        plot,
        plot_path,
        model_error,
        crosstalk,
        crosstalk_shots,
        spread,
        applied,
        without_rms,
    )


def _remeasured(
    points: list[CalibrationPoint], setup: CalibrationSetup, crosstalk: np.ndarray, log: Callable[[str], None]
) -> list[CalibrationPoint]:
    """The sweep's points with the target's disparity measured again on planes the crosstalk is taken out of
    (the catalogue keeps what was measured at the shot)."""
    from mca.capture.raw import RawReadError

    max_disparity_px = _search_bound_px(setup.profile, setup.plan)  # as the sweep searched
    again = []
    for i, point in enumerate(points, 1):
        path = setup.directory / point.file_name
        try:
            raw_px, disparity, across, correlation, height = measure_file(
                path, setup.profile, max_disparity_px, crosstalk
            )
        except (RawReadError, OSError, ValueError) as exc:
            raise CalibrationError(
                f"{path}: could not be measured again with the crosstalk taken out ({exc}); the sweep's "
                "shots and catalogue are kept: restore the file and rerun, or rerun with --no-crosstalk"
            ) from exc
        again.append(
            dataclasses.replace(
                point,
                disparity_raw_px=raw_px,
                disparity_px=disparity,
                across_px=across,
                correlation=correlation,
                mosaic_height_px=height,
            )
        )
        log(
            f"crosstalk out: {i}/{len(points)}  {point.position_mm:+8.1f} mm  disparity {point.disparity_px:+8.3f} -> "
            f"{disparity:+8.3f} px"
        )
    return again


def record_calibration(run: CalibrationRun, record: Path) -> None:
    """Log the fit (plot, parameters, residuals, the profile text) into the rerun recording `record`."""
    import cv2

    from mca.capture.recording import RerunRecorder

    f, fit = run.fit.fitted, run.fit
    with RerunRecorder(record) as recorder:
        recorder.record(
            "calibration",
            plot=cv2.cvtColor(run.plot, cv2.COLOR_BGR2RGB),
            filter_centre_distance_mm=f.filter_centre_distance_mm,
            sensor_distance_mm=f.sensor_distance_mm,
            focus_distance_mm=f.focus_distance_mm,
            residual_rms_px=fit.residual_rms_px,
            max_depth_error_mm=fit.max_depth_error_mm,
            residuals_px=fit.residuals_px,
            profile=run.profile_text,
            crosstalk="\n".join(run.crosstalk_lines()),
            crosstalk_applied=run.crosstalk_applied,
        )
