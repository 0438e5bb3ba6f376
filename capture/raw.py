"""Reads a photograph (CR2 and other raws, DNG, TIFF, PNG, JPEG, PPM) into linear colour planes plus the metadata depth needs.

For a Bayer raw the planes come straight from the mosaic, without
demosaicing: R, the mean of the two greens, and B, each at half resolution,
black level subtracted and divided by (white level - black level). RGB images
give full-resolution planes: 16-bit TIFF is taken as linear, 8-bit (and 16-bit
PNG/PPM) images as sRGB and linearised with the IEC 61966-2-1 formula.

Every failure to read a file is a `RawReadError` that names the file, the
reason and what to do; exceptions from LibRaw or the image decoders never
escape.

Hostile files are refused before they are decoded: only regular files are
opened (a FIFO would block), and an image whose header declares more pixels
than the limit (`read_policy`, default 100 MP, `MCA_MAX_MEGAPIXELS` in the
environment) is an `ImageTooLargeError` instead of a 10 GiB allocation. In
photograph mode (what `mca process` uses) an image that cannot be an MCA
photograph is a `NotAPhotographError`: one colour channel, three identical
channels, float samples outside 0..1 (a depth map in mm) or not finite, or
fewer than 16 pixels on a side.
"""

from __future__ import annotations

import contextlib
import contextvars
import errno
import math
import mmap
import os
import stat
import struct
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

import numpy as np

from mca.capture.sensors import SensorSpec, known_models, photosite_pitch_mm, sensor_for
from mca.processing.colour import CameraColour, camera_colour, srgb_decode

RAW_EXTENSIONS = {
    ".cr2": "cr2",
    ".dng": "dng",
    ".cr3": "cr3",
    ".crw": "crw",
    ".nef": "nef",
    ".arw": "arw",
    ".raf": "raf",
    ".orf": "orf",
    ".rw2": "rw2",
    ".pef": "pef",
    ".srw": "srw",
}
IMAGE_EXTENSIONS = {
    ".tif": "tiff",
    ".tiff": "tiff",
    ".png": "png",
    ".jpg": "jpeg",
    ".jpeg": "jpeg",
    ".ppm": "ppm",
    ".pgm": "ppm",
    ".pnm": "ppm",
}


class RawReadError(Exception):
    """A photograph could not be read: which file, why, and what to do about it."""

    def __init__(self, path: str | os.PathLike[str], reason: str, advice: str) -> None:
        self.path = Path(path)
        self.reason = reason
        self.advice = advice
        super().__init__(f"{self.path}: {reason}. {advice}")


class UnknownBodyError(RawReadError):
    """The photograph was read, but its camera body has no sensor profile."""


class NotARegularFileError(RawReadError):
    """A FIFO, socket, device or folder where a photograph file was expected: never opened for reading."""


class ImageTooLargeError(RawReadError):
    """The image declares more pixels than the limit (a decompression bomb, or a limit set too low)."""


class NotAPhotographError(RawReadError):
    """The file decodes, but cannot be an MCA photograph (ground truth, a grey image, a map in mm, too small)."""


# --------------------------------------------------------------------------
# What a read accepts
# --------------------------------------------------------------------------

DEFAULT_MAX_MEGAPIXELS = 100.0  # 5x a 20 MP EOS 70D frame; a 20 MP shot needs about 0.8 GiB to process
MAX_MEGAPIXELS_ENV = "MCA_MAX_MEGAPIXELS"
MIN_SIDE_PX = 16  # the smallest image side (of the planes) worth a disparity search
FLOAT_RANGE = (-0.05, 4.0)  # linear float samples beyond this are not light (a depth map in mm, disparities)
_BYTES_PER_PIXEL_LIMIT = 8  # 16-bit RGBA: no image file of N pixels needs more than 8 N bytes (+ headers)


def parse_megapixels(text: str | float, what: str = MAX_MEGAPIXELS_ENV) -> float:
    """A pixel limit in megapixels, checked: a positive finite number."""
    try:
        value = float(text)
    except (TypeError, ValueError):
        raise ValueError(f"{what}: {text!r} is not a number of megapixels (e.g. 100)") from None
    if not math.isfinite(value) or value <= 0:
        raise ValueError(f"{what}: {text!r} must be a positive number of megapixels")
    return value


def default_max_megapixels() -> float:
    """The pixel limit when none is given: `MCA_MAX_MEGAPIXELS` from the environment, else 100."""
    text = os.environ.get(MAX_MEGAPIXELS_ENV)
    return parse_megapixels(text) if text else DEFAULT_MAX_MEGAPIXELS


@dataclass(frozen=True)
class ReadPolicy:
    """What `read_raw` accepts: at most `max_pixels`; with `photograph`, only what can be an MCA photograph."""

    max_pixels: int
    photograph: bool = False


_POLICY: contextvars.ContextVar[ReadPolicy | None] = contextvars.ContextVar("mca_read_policy", default=None)


def current_policy() -> ReadPolicy:
    policy = _POLICY.get()
    return policy if policy is not None else ReadPolicy(int(default_max_megapixels() * 1e6))


@contextlib.contextmanager
def read_policy(*, max_megapixels: float | None = None, photograph: bool = False) -> Iterator[ReadPolicy]:
    """Within the block, `read_raw` refuses images over `max_megapixels` and, with `photograph`, anything that
    cannot be an MCA photograph (how `mca process` reads its inputs)."""
    limit = default_max_megapixels() if max_megapixels is None else parse_megapixels(max_megapixels, "max megapixels")
    token = _POLICY.set(ReadPolicy(int(limit * 1e6), photograph))
    try:
        yield _POLICY.get()  # type: ignore[misc]
    finally:
        _POLICY.reset(token)


def _check_pixels(p: Path, width: int, height: int, what: str = "") -> None:
    limit = current_policy().max_pixels
    if width * height > limit:
        raise ImageTooLargeError(
            p,
            f"declares {width} x {height} pixels{what} ({width * height / 1e6:.0f} MP), over the limit of "
            f"{limit / 1e6:g} MP; it was not decoded",
            f"If it is a genuine photograph, raise the limit (mca process --max-megapixels, or "
            f"{MAX_MEGAPIXELS_ENV}); a small file declaring this many pixels is a decompression bomb",
        )


@dataclass(frozen=True)
class RawMetadata:
    """What the file says about the exposure; every field is None when the file does not say."""

    make: str | None = None
    model: str | None = None
    lens_model: str | None = None
    focal_length_mm: float | None = None
    f_number: float | None = None
    iso: int | None = None
    exposure_time_s: float | None = None
    capture_time: datetime | None = None
    photosite_pitch_mm: float | None = None
    focus_distance_m: float | None = None  # math.inf when focused at infinity
    black_level: tuple[float, ...] | None = None  # per CFA colour as LibRaw lists them (R, G, B, G2)
    white_level: float | None = None
    cfa_pattern: str | None = None  # e.g. "RGGB": colours of the top-left 2x2 of the planes' source
    as_shot_wb: tuple[float, ...] | None = None  # as-shot white-balance multipliers R, G, B (LibRaw's cam_mul)
    xyz_to_camera: tuple[tuple[float, ...], ...] | None = None  # 3x3 colour matrix, XYZ to camera RGB (cam_xyz)


@dataclass
class RawFrame:
    """One photograph as linear colour planes, with where it came from."""

    planes: np.ndarray  # (H2, W2, 3) float32 in [0, 1], linear, R, G, B
    pixel_pitch_mm: float | None  # size of one plane pixel on the sensor
    source_format: str  # 'cr2', 'dng', 'tiff', 'png', 'jpeg', 'ppm', or another raw extension
    metadata: RawMetadata
    path: Path
    half_resolution: bool = False  # True when the planes are the Bayer quads of a raw
    _rgb: np.ndarray | None = field(default=None, repr=False)
    colour: CameraColour = field(default_factory=CameraColour)  # camera RGB -> sRGB for display (not for depth)

    @classmethod
    def from_planes(
        cls,
        planes: np.ndarray,
        *,
        pixel_pitch_mm: float | None = None,
        half_resolution: bool = False,
        cfa_pattern: str | None = None,
        colour: CameraColour | None = None,
        make: str | None = None,
        model: str | None = None,
        name: str = "<array>",
    ) -> RawFrame:
        """A frame from arrays already in memory (linear R, G, B planes in [0, 1]).

        `half_resolution=True` says the planes are a Bayer raw's 2x2 quads, and then `cfa_pattern`
        (e.g. "RGGB") is required: the R and B samples sit a quarter plane pixel off the G centre.
        `pixel_pitch_mm` is the size of one plane pixel on the sensor (for a Bayer raw, twice the
        photosite pitch), as `read_raw` reports it.
        """
        array = np.asarray(planes, dtype=np.float32)
        if array.ndim != 3 or array.shape[2] != 3:
            raise ValueError(f"planes must be (H, W, 3) linear R, G, B, got shape {array.shape}")
        meta = RawMetadata(make=make, model=model, cfa_pattern=cfa_pattern, photosite_pitch_mm=None)
        return cls(
            array,
            pixel_pitch_mm,
            "array",
            meta,
            Path(name),
            half_resolution=half_resolution,
            colour=colour or CameraColour(),
        )

    def demosaiced_rgb(self) -> np.ndarray:
        """Full-resolution linear RGB (H, W, 3) float32 in [0, 1]: LibRaw's AHD demosaic for raws.

        Same scaling as the planes (black subtracted, divided by white - black,
        no white balance, camera colour space); no rotation is applied.
        """
        if self._rgb is not None:
            return self._rgb
        return _demosaic_raw(self)


# --------------------------------------------------------------------------
# Public entry points
# --------------------------------------------------------------------------


def read_raw(path: str | os.PathLike[str]) -> RawFrame:
    """Read the photograph at `path` into linear R, G, B planes and its metadata.

    Raises RawReadError naming the file when it is missing, empty, a folder,
    unreadable, truncated, not what its extension says, or not decodable.
    """
    p = Path(path)
    head = _check_file(p)
    kind = _detect_format(p, head)
    if kind in ("jpeg", "png", "ppm"):
        frame = _read_8bit_style(p, kind)
    elif kind == "tiff":
        frame = _read_tiff(p)
    else:
        frame = _read_with_libraw(p, kind)
    if current_policy().photograph:
        check_photograph_planes(p, frame.planes)
    return frame


def check_photograph_planes(p: Path, planes: np.ndarray) -> None:
    """Raise `NotAPhotographError` unless (H, W, 3) linear planes can be an MCA photograph: big enough, with
    finite samples, not one value everywhere, and not three identical channels (a grey image)."""
    height, width = planes.shape[:2]
    if min(height, width) < MIN_SIDE_PX:
        raise NotAPhotographError(
            p,
            f"is too small for depth recovery: {width} x {height} pixels (colour planes), "
            f"at least {MIN_SIDE_PX} on each side are needed",
            "Pass the full-size photograph",
        )
    if not np.isfinite(planes).all():
        raise NotAPhotographError(
            p, "has samples that are not finite (NaN or infinity)", "Pass the photograph, not a computed map"
        )
    first = planes[..., 0]
    if np.array_equal(first, planes[..., 1]) and np.array_equal(first, planes[..., 2]):
        if float(first.min()) == float(first.max()):
            raise NotAPhotographError(
                p, f"has one value in every pixel ({float(first.min()):g}): no image content", "Check the exposure"
            )
        raise NotAPhotographError(
            p,
            "has three identical colour channels (a grey image): an MCA photograph shows the scene through three "
            "colour filters",
            "Pass the colour photograph from the camera, not a grey or converted copy",
        )


def _refuse_source_samples(p: Path, arr: np.ndarray) -> None:
    """In photograph mode: refuse decoded samples that cannot be a photograph (one channel, floats not in 0..1)."""
    if not current_policy().photograph:
        return
    channels = 1 if arr.ndim == 2 else int(arr.shape[-1]) if arr.ndim == 3 else 0
    if channels < 3:
        raise NotAPhotographError(
            p,
            f"has {'one colour channel' if channels <= 1 else 'two channels (grey and alpha)'} "
            f"({arr.dtype} samples): a grey image, a label map or a depth map, not an MCA colour photograph",
            "Pass the colour photograph from the camera; ground truth written by `mca simulate` is not an input",
        )
    if arr.dtype.kind == "f":
        finite = np.isfinite(arr)
        if not finite.any():
            raise NotAPhotographError(p, "has no finite sample (all NaN)", "Pass a photograph")
        if not finite.all():
            raise NotAPhotographError(
                p,
                f"has {int((~finite).sum())} samples that are NaN or infinite: a computed map, not a photograph",
                "Pass the photograph from the camera",
            )
        low, high = float(arr.min()), float(arr.max())
        if low < FLOAT_RANGE[0] or high > FLOAT_RANGE[1]:
            raise NotAPhotographError(
                p,
                f"has float samples from {low:g} to {high:g}, not linear light in 0..1 "
                "(a depth map in mm or a disparity map?)",
                "Pass the photograph; export float TIFFs as linear values in 0..1",
            )


def require_known_body(frame: RawFrame, known: Iterable[str] | None = None) -> SensorSpec:
    """The sensor of the body that took `frame`; raises UnknownBodyError naming the model if it has no profile.

    `known` limits the accepted bodies further (e.g. to those with a camera
    profile); by default any body in `capture.sensors` is accepted.
    """
    model = frame.metadata.model
    spec = sensor_for(model, frame.metadata.make)
    allowed = None if known is None else {m.lower() for m in known}
    if spec is not None and (allowed is None or spec.model.lower() in allowed):
        return spec
    listed = sorted(allowed) if allowed is not None else known_models()
    who = f"'{model}'" if model else "an unnamed camera (the file has no Make/Model)"
    raise UnknownBodyError(
        frame.path,
        f"was taken with {who}, which has no camera profile",
        f"Known bodies: {', '.join(listed)}. Add the body's sensor size and active pixels to "
        "capture/sensors.py and a profile for it, or pass --pixel-pitch-mm explicitly",
    )


srgb_to_linear = srgb_decode  # IEC 61966-2-1 decoding (processing/colour.py)


# --------------------------------------------------------------------------
# File checks and format detection
# --------------------------------------------------------------------------


_FILE_KINDS = {
    stat.S_IFIFO: "a FIFO (named pipe)",
    stat.S_IFSOCK: "a socket",
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFDIR: "a folder",
}


def regular_file_descriptor(path: str | os.PathLike[str]) -> int:
    """A descriptor of `path` opened for reading without ever blocking (as a FIFO would).

    Raises `NotARegularFileError` for FIFOs, sockets, devices and folders, `OSError` when it cannot
    be opened (missing, permission denied, a symbolic-link loop: errno ELOOP).
    """
    fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        mode = os.fstat(fd).st_mode
        if not stat.S_ISREG(mode):
            kind = _FILE_KINDS.get(stat.S_IFMT(mode), "not a regular file")
            raise NotARegularFileError(
                path,
                f"is {kind}, not a photograph file",
                "Skipped: give regular image files (CR2, DNG, TIFF, PNG, JPEG)",
            )
        os.set_blocking(fd, True)
        return fd
    except BaseException:
        os.close(fd)
        raise


def _open_binary(path: Path) -> Any:
    return os.fdopen(regular_file_descriptor(path), "rb")


def _check_file(p: Path) -> bytes:
    """First bytes of the file, after checking it exists, is a file, is readable and is not empty."""
    if not p.exists():
        if p.is_symlink():
            try:
                os.stat(p)
            except OSError as e:
                if e.errno == errno.ELOOP:
                    raise RawReadError(
                        p, "is a symbolic link that loops back on itself", "Fix or remove the link"
                    ) from None
            raise RawReadError(p, "is a symbolic link to a file that does not exist", "Fix or remove the link")
        raise RawReadError(
            p, "no such file", "Check the path; the file may not have been downloaded from the camera yet"
        )
    if p.is_dir():
        raise RawReadError(
            p, "is a folder, not an image file", "Pass one photograph (.CR2, .DNG, .tif, .png, .jpg, .ppm)"
        )
    try:
        with _open_binary(p) as f:
            head = f.read(64)
    except PermissionError:
        raise RawReadError(
            p, "cannot be read: permission denied", "Check the file's permissions (chmod u+r) or run as its owner"
        ) from None
    except OSError as e:
        raise RawReadError(p, f"cannot be read: {e.strerror or e}", "Check the disk and copy the file again") from None
    size = p.stat().st_size
    limit = current_policy().max_pixels * _BYTES_PER_PIXEL_LIMIT + (64 << 20)
    if size > limit:
        raise ImageTooLargeError(
            p,
            f"is {size / 2**20:.0f} MiB, more than any image within the limit of "
            f"{current_policy().max_pixels / 1e6:g} MP needs",
            f"If it is a genuine photograph, raise the limit (mca process --max-megapixels, or {MAX_MEGAPIXELS_ENV})",
        )
    if not head:
        raise RawReadError(
            p,
            "is empty (0 bytes)",
            "The transfer from the camera probably failed; download or take the photograph again",
        )
    return head


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def image_size_px(data: bytes, kind: str) -> tuple[int, int] | None:
    """(width, height) an image file declares in its header (PNG IHDR, JPEG SOF, PPM), without decoding it;
    None when the header does not say (a damaged file: the decoder then fails on its own)."""
    if kind == "png":
        if len(data) >= 24 and data[12:16] == b"IHDR":
            return struct.unpack(">II", data[16:24])
        return None
    if kind == "jpeg":
        at = 2
        while at + 9 <= len(data) and data[at] == 0xFF:
            marker = data[at + 1]
            if marker == 0xFF:
                at += 1
                continue
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7:
                at += 2
                continue
            length = struct.unpack(">H", data[at + 2 : at + 4])[0]
            if marker in _JPEG_SOF:
                height, width = struct.unpack(">HH", data[at + 5 : at + 9])
                return width, height
            if marker in (0xDA, 0xD9) or length < 2:
                return None
            at += 2 + length
        return None
    if kind == "ppm":
        tokens: list[bytes] = []
        for line in data[:1024].split(b"\n"):
            tokens += line.split(b"#", 1)[0].split()
            if len(tokens) >= 3:
                break
        if len(tokens) >= 3 and tokens[1].isdigit() and tokens[2].isdigit():
            return int(tokens[1]), int(tokens[2])
        return None
    return None


def _magic_kind(head: bytes) -> str | None:
    if head.startswith(b"\xff\xd8\xff"):
        return "jpeg"
    if head.startswith(b"\x89PNG\r\n\x1a\n"):
        return "png"
    if head[:2] in (b"P5", b"P6", b"P3", b"P2") and len(head) > 2 and head[2:3].isspace():
        return "ppm"
    if head[:4] in (b"II*\0", b"MM\0*"):
        return "cr2" if head[8:10] == b"CR" else "tiff-structure"
    if head[4:12] == b"ftypcrx ":
        return "cr3"
    return None


def _detect_format(p: Path, head: bytes) -> str:
    ext = p.suffix.lower()
    magic = _magic_kind(head)
    named = RAW_EXTENSIONS.get(ext) or IMAGE_EXTENSIONS.get(ext)
    if ext in RAW_EXTENSIONS:
        if magic in ("jpeg", "png", "ppm"):
            raise RawReadError(
                p,
                f"is named {p.suffix} but holds a {magic.upper()} image, not a camera raw",
                f"Use the raw file from the camera, or rename this one to .{'jpg' if magic == 'jpeg' else magic} to process it as an sRGB image",
            )
        if named == "cr2" and magic not in ("cr2", "tiff-structure"):
            raise RawReadError(
                p,
                "is named .CR2 but does not start like a Canon CR2 (TIFF header)",
                "The file is damaged or is not a CR2; copy it from the camera again",
            )
        if named == "cr2" and magic == "tiff-structure":
            return "dng" if _is_dng(p) else "cr2"
        return named or "raw"
    if magic in ("jpeg", "png", "ppm"):
        return magic
    if magic == "cr2":
        return "cr2"
    if magic == "tiff-structure":
        return "dng" if _is_dng(p) else "tiff"
    if magic == "cr3":
        return "cr3"
    if named:
        return named
    raise RawReadError(
        p,
        "is not a format mca reads (no CR2/DNG/TIFF/PNG/JPEG/PPM signature)",
        "Pass a camera raw (.CR2, .DNG), a 16-bit linear TIFF, or an 8-bit PNG/JPEG/PPM",
    )


# --------------------------------------------------------------------------
# TIFF/Exif metadata (pure parsing, bounded; malformed metadata is ignored)
# --------------------------------------------------------------------------

_TYPE_FORMAT = {
    1: "B",
    2: "c",
    3: "H",
    4: "I",
    5: "II",
    6: "b",
    7: "B",
    8: "h",
    9: "i",
    10: "ii",
    11: "f",
    12: "d",
    13: "I",
}
_TYPE_SIZE = {1: 1, 2: 1, 3: 2, 4: 4, 5: 8, 6: 1, 7: 1, 8: 2, 9: 4, 10: 8, 11: 4, 12: 8, 13: 4}
_MAX_ENTRIES = 1000
_MAX_IFDS = 32


@dataclass
class _Ifd:
    tags: dict[int, Any]
    raw: dict[int, tuple[int, int, int]]  # tag -> (type, count, value offset) for locating data


class _Tiff:
    """The IFD chain, Exif IFD and (for Canon) maker-note IFD of a TIFF structure in `buf`."""

    def __init__(self, buf: Any, base: int = 0) -> None:
        self.buf = buf
        self.base = base
        bo = bytes(buf[base : base + 2])
        if bo not in (b"II", b"MM"):
            raise ValueError("not a TIFF structure")
        self.e = "<" if bo == b"II" else ">"
        self.ifds: list[_Ifd] = []
        offset = self._u32(base + 4)
        seen: set[int] = set()
        while offset and offset not in seen and len(self.ifds) < _MAX_IFDS:
            seen.add(offset)
            ifd, offset = self._ifd(base + offset)
            self.ifds.append(ifd)
        self.exif = self._sub(self.ifds[0], 0x8769) if self.ifds else None
        self.makernote: _Ifd | None = None
        make = str(self.ifds[0].tags.get(0x010F, "")) if self.ifds else ""
        if self.exif and make.lower().startswith("canon") and 0x927C in self.exif.raw:
            _, _, at = self.exif.raw[0x927C]
            try:
                self.makernote, _ = self._ifd(at)
            except (ValueError, struct.error, IndexError):
                self.makernote = None

    def _u32(self, at: int) -> int:
        return struct.unpack(self.e + "I", bytes(self.buf[at : at + 4]))[0]

    def _sub(self, ifd: _Ifd, tag: int) -> _Ifd | None:
        if tag not in ifd.tags:
            return None
        try:
            return self._ifd(self.base + int(_first(ifd.tags[tag])))[0]
        except (ValueError, struct.error, IndexError):
            return None

    def _ifd(self, at: int) -> tuple[_Ifd, int]:
        if at + 2 > len(self.buf):
            raise ValueError(f"IFD at byte {at} lies beyond the end of the file")
        n = struct.unpack(self.e + "H", bytes(self.buf[at : at + 2]))[0]
        if n > _MAX_ENTRIES or at + 2 + 12 * n + 4 > len(self.buf):
            raise ValueError(f"IFD at byte {at} is cut off or implausible ({n} entries)")
        tags: dict[int, Any] = {}
        raw: dict[int, tuple[int, int, int]] = {}
        for i in range(n):
            e = at + 2 + 12 * i
            tag, typ, count = struct.unpack(self.e + "HHI", bytes(self.buf[e : e + 8]))
            size = _TYPE_SIZE.get(typ)
            if size is None:
                continue
            nbytes = size * count
            vat = e + 8 if nbytes <= 4 else self.base + self._u32(e + 8)
            raw[tag] = (typ, count, vat)
            if nbytes > 1 << 16 or vat + nbytes > len(self.buf):
                continue  # large or out-of-file values are located via `raw`, not decoded
            data = bytes(self.buf[vat : vat + nbytes])
            if typ == 2:
                tags[tag] = data.split(b"\0", 1)[0].decode("latin-1").strip()
            elif typ == 7:
                tags[tag] = data
            else:
                fmt = _TYPE_FORMAT[typ]
                vals = struct.unpack(self.e + fmt * count, data)
                if typ in (5, 10):
                    vals = tuple(vals[k] / vals[k + 1] if vals[k + 1] else math.nan for k in range(0, len(vals), 2))
                tags[tag] = vals
        return _Ifd(tags, raw), self._u32(at + 2 + 12 * n)


def _first(v: Any) -> Any:
    return v[0] if isinstance(v, tuple) and v else v


def _tiff_from_jpeg(buf: bytes) -> _Tiff | None:
    """The Exif TIFF structure inside a JPEG's APP1 segment, if any."""
    at = 2
    while at + 4 <= len(buf) and buf[at] == 0xFF:
        marker = buf[at + 1]
        length = struct.unpack(">H", buf[at + 2 : at + 4])[0]
        if marker == 0xE1 and buf[at + 4 : at + 10] == b"Exif\0\0":
            return _Tiff(buf, at + 10)
        if marker in (0xDA, 0xD9):
            break
        at += 2 + length
    return None


def _tiff_from_png(buf: bytes) -> _Tiff | None:
    at = 8
    while at + 8 <= len(buf):
        length, kind = struct.unpack(">I4s", buf[at : at + 8])
        if kind == b"eXIf":
            return _Tiff(buf[at + 8 : at + 8 + length], 0)
        if kind == b"IDAT":
            break
        at += 12 + length
    return None


def _metadata(tiff: _Tiff | None, image_width_px: int | None = None) -> dict[str, Any]:
    """RawMetadata fields from IFD0, Exif and Canon maker notes."""
    if tiff is None or not tiff.ifds:
        return {}
    ifd0 = tiff.ifds[0].tags
    exif = tiff.exif.tags if tiff.exif else {}
    notes = tiff.makernote.tags if tiff.makernote else {}

    def text(v: Any) -> str | None:
        return v.strip() or None if isinstance(v, str) else None

    def number(v: Any) -> float | None:
        v = _first(v)
        return float(v) if isinstance(v, (int, float)) and math.isfinite(v) and v > 0 else None

    make = text(ifd0.get(0x010F))
    model = text(ifd0.get(0x0110)) or text(ifd0.get(0xC614))
    stamp = text(exif.get(0x9003)) or text(ifd0.get(0x0132))
    capture_time = None
    if stamp:
        try:
            capture_time = datetime.strptime(stamp[:19], "%Y:%m:%d %H:%M:%S")
        except ValueError:
            capture_time = None
    focus = number(exif.get(0x9206))
    info = notes.get(0x0093)
    # Canon FileInfo (maker-note tag 0x0093, int16 words, word 0 its length in bytes): FocusDistanceUpper is
    # word 20 and FocusDistanceLower word 21, in cm (ExifTool's Canon::FileInfo table; word 19 is LiveViewShooting)
    if focus is None and isinstance(info, tuple) and len(info) > 21 and info[20]:
        upper, lower = info[20], info[21] or info[20]
        focus = math.inf if upper >= 65535 else (upper + lower) / 200.0  # cm -> m, middle of the range
    iso = _first(exif.get(0x8827))
    pitch = photosite_pitch_mm(model, make)
    if pitch is None:
        res = number(exif.get(0xA20E))
        unit = {2: 25.4, 3: 10.0, 4: 1.0}.get(int(_first(exif.get(0xA210, (2,)))))
        if res and unit:
            pitch = unit / res  # Exif FocalPlaneXResolution: pixels per unit
    return dict(
        make=make,
        model=model,
        lens_model=text(exif.get(0xA434)) or text(notes.get(0x0095)),
        focal_length_mm=number(exif.get(0x920A)),
        f_number=number(exif.get(0x829D)),
        iso=int(iso) if isinstance(iso, int) and iso > 0 else None,
        exposure_time_s=number(exif.get(0x829A)),
        capture_time=capture_time,
        photosite_pitch_mm=pitch,
        focus_distance_m=focus,
    )


def _is_dng(p: Path) -> bool:
    try:
        with _open_binary(p) as f, mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
            t = _Tiff(m)
            return bool(t.ifds) and 0xC612 in t.ifds[0].raw
    except (ValueError, OSError, struct.error):
        return False


def _check_tiff_extent(p: Path, tiff: _Tiff, size: int, kind: str) -> None:
    """Raise if any strip or tile of the file points past its end (a truncated download)."""
    for ifd in tiff.ifds + [i for i in _sub_ifds(tiff) if i is not None]:
        for off_tag, len_tag in ((0x0111, 0x0117), (0x0144, 0x0145), (0x0201, 0x0202)):
            offs, lens = ifd.tags.get(off_tag), ifd.tags.get(len_tag)
            if offs is None or lens is None:
                continue
            offs = offs if isinstance(offs, tuple) else (offs,)
            lens = lens if isinstance(lens, tuple) else (lens,)
            # a damaged file can give these tags any type (text, rationals): only whole numbers locate data
            end = max((o + n for o, n in zip(offs, lens) if isinstance(o, int) and isinstance(n, int)), default=0)
            if end > size:
                raise RawReadError(
                    p,
                    f"is truncated: its image data runs to byte {end} but the file has only {size} bytes",
                    "The copy from the camera was interrupted; download the photograph again",
                )


def _sub_ifds(tiff: _Tiff) -> list[_Ifd | None]:
    out: list[_Ifd | None] = []
    for ifd in tiff.ifds:
        subs = ifd.tags.get(0x014A)
        for off in subs if isinstance(subs, tuple) else ():
            try:
                out.append(tiff._ifd(tiff.base + int(off))[0])
            except (ValueError, struct.error, IndexError):
                out.append(None)
    return out


def _read_tiff_structure(p: Path, kind: str) -> _Tiff:
    try:
        with _open_binary(p) as f:
            size = os.fstat(f.fileno()).st_size
            with mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ) as m:
                tiff = _Tiff(m)  # values are decoded while parsing; nothing refers to `m` afterwards
    except (ValueError, struct.error) as e:
        raise RawReadError(
            p,
            f"has a damaged {kind.upper()} structure ({e})",
            "The file is truncated or corrupt; copy it from the camera again",
        ) from None
    except OSError as e:
        raise RawReadError(p, f"cannot be read: {e.strerror or e}", "Check the disk and copy the file again") from None
    if not tiff.ifds:
        raise RawReadError(p, f"has no image directory (damaged {kind.upper()})", "Copy the file from the camera again")
    _check_tiff_extent(p, tiff, size, kind)
    for ifd in tiff.ifds + [i for i in _sub_ifds(tiff) if i is not None]:
        width, height = _first(ifd.tags.get(0x0100)), _first(ifd.tags.get(0x0101))
        if isinstance(width, int) and isinstance(height, int):
            _check_pixels(p, width, height)
    return tiff


# --------------------------------------------------------------------------
# Raws through LibRaw
# --------------------------------------------------------------------------


def _libraw_failure(p: Path, kind: str, e: Exception) -> RawReadError:
    name = type(e).__name__
    detail = e.args[0] if e.args else ""
    message = detail.decode("utf-8", "replace") if isinstance(detail, bytes) else str(detail or name)
    if "Unsupported" in name:
        return RawReadError(
            p,
            f"is not a raw format LibRaw can decode ({kind.upper()}; LibRaw: {message})",
            "Convert it to DNG or 16-bit linear TIFF, or check that it really is a camera raw",
        )
    if "IO" in name or "Data" in name:
        return RawReadError(
            p,
            f"raw data could not be decoded ({name}: {message}); the file is probably truncated or damaged",
            "Copy the photograph from the camera again",
        )
    return RawReadError(
        p,
        f"LibRaw could not read it ({name}: {message})",
        "Copy the photograph from the camera again, or convert it to DNG",
    )


def _read_with_libraw(p: Path, kind: str) -> RawFrame:
    import rawpy

    tiff = _read_tiff_structure(p, kind) if kind in ("cr2", "dng") else None
    meta = _metadata(tiff)
    try:
        with rawpy.imread(str(p)) as raw:
            return _frame_from_libraw(p, kind, raw, meta)
    except RawReadError:
        raise
    except rawpy.LibRawError as e:
        raise _libraw_failure(p, kind, e) from None
    except Exception as e:  # a hostile file can make the decoder fail in any way: say so, never a traceback
        raise RawReadError(
            p,
            f"could not be decoded as {kind.upper()} ({type(e).__name__}: {e})",
            "Copy the photograph from the camera again",
        ) from None


def _levels(raw: Any) -> tuple[np.ndarray, float]:
    """Per-colour black levels (indexed like raw_colors) and the white (saturation) level."""
    black = np.asarray(raw.black_level_per_channel, dtype=np.float64)
    whites = getattr(raw, "camera_white_level_per_channel", None)
    white = float(raw.white_level)
    if whites is not None and len(whites) and min(whites) > 0:
        white = float(min(whites))  # the camera's own saturation level (Canon SpecularWhiteLevel)
    return black, white


def _frame_from_libraw(p: Path, kind: str, raw: Any, meta: dict[str, Any]) -> RawFrame:
    sizes = raw.sizes  # from the header: known before LibRaw unpacks (allocates) anything
    _check_pixels(p, int(sizes.raw_width), int(sizes.raw_height), " in its raw data")
    black, white = _levels(raw)
    desc = raw.color_desc.decode("ascii", "replace")
    pattern = raw.raw_pattern
    make = meta.get("make")
    model = meta.get("model")
    pitch = meta.get("photosite_pitch_mm") or photosite_pitch_mm(model, make)
    bayer = (
        pattern is not None
        and pattern.shape == (2, 2)
        and raw.num_colors == 3
        and sorted(desc[int(c)] for c in pattern.reshape(-1)) == ["B", "G", "G", "R"]
    )
    fields = dict(meta, photosite_pitch_mm=pitch, black_level=tuple(float(b) for b in black), white_level=white)
    wb, xyz_to_camera = _libraw_colour(raw)
    fields.update(as_shot_wb=wb, xyz_to_camera=xyz_to_camera)
    colour = camera_colour(wb, None if xyz_to_camera is None else np.array(xyz_to_camera), who=model or kind.upper())
    if not bayer:
        rgb = _postprocess(raw, black, white)
        fields["cfa_pattern"] = None
        return RawFrame(rgb, pitch, kind, RawMetadata(**fields), p, half_resolution=False, _rgb=rgb, colour=colour)
    visible = raw.raw_image_visible
    h2, w2 = visible.shape[0] // 2, visible.shape[1] // 2
    planes = np.zeros((h2, w2, 3), dtype=np.float32)
    for dy in range(2):
        for dx in range(2):
            c = int(pattern[dy, dx])
            letter = desc[c]
            sub = visible[dy : 2 * h2 : 2, dx : 2 * w2 : 2].astype(np.float32)
            scaled = (sub - np.float32(black[c])) / np.float32(white - black[c])
            if letter == "G":
                planes[..., 1] += np.float32(0.5) * scaled
            else:
                planes[..., "RGB".index(letter)] = scaled
    np.clip(planes, 0.0, 1.0, out=planes)
    fields["cfa_pattern"] = "".join(desc[int(c)] for c in pattern.reshape(-1))
    return RawFrame(
        planes, 2 * pitch if pitch else None, kind, RawMetadata(**fields), p, half_resolution=True, colour=colour
    )


def _libraw_colour(raw: Any) -> tuple[tuple[float, ...] | None, tuple[tuple[float, ...], ...] | None]:
    """As-shot white-balance multipliers (R, G, B) and the XYZ-to-camera matrix, as LibRaw reports them.

    `camera_whitebalance` is LibRaw's cam_mul (R, G, B, G2; zero when the file has none);
    `rgb_xyz_matrix` its cam_xyz (from the file for DNG, else LibRaw's table of cameras; zero when unknown).
    """
    wb = None
    try:
        mul = [float(v) for v in raw.camera_whitebalance][:3]
        if len(mul) == 3 and all(math.isfinite(v) and v > 0 for v in mul):
            wb = (mul[0], mul[1], mul[2])
    except (AttributeError, TypeError, ValueError):
        wb = None
    matrix = None
    try:
        cam_xyz = np.asarray(raw.rgb_xyz_matrix, dtype=np.float64)[:3, :3]
        if cam_xyz.shape == (3, 3) and np.isfinite(cam_xyz).all() and np.abs(cam_xyz).sum() > 0:
            matrix = tuple(tuple(float(v) for v in row) for row in cam_xyz)
    except (AttributeError, TypeError, ValueError):
        matrix = None
    return wb, matrix


def _postprocess(raw: Any, black: np.ndarray, white: float) -> np.ndarray:
    """LibRaw's demosaic with no scaling or white balance, then the planes' scaling done here."""
    import rawpy

    rgb = raw.postprocess(
        gamma=(1, 1),
        no_auto_bright=True,
        no_auto_scale=True,  # output is raw - black, in raw units
        output_bps=16,
        use_camera_wb=False,
        use_auto_wb=False,
        user_wb=[1.0, 1.0, 1.0, 1.0],
        output_color=rawpy.ColorSpace.raw,
        adjust_maximum_thr=0.0,
        user_flip=0,
    )
    b = black if black.size >= 4 else np.resize(black, 4)
    span = np.array([white - b[0], white - (b[1] + b[3]) / 2, white - b[2]], dtype=np.float32)
    return np.clip(rgb.astype(np.float32) / span, 0.0, 1.0)


def _demosaic_raw(frame: RawFrame) -> np.ndarray:
    import rawpy

    p = frame.path
    try:
        with rawpy.imread(str(p)) as raw:
            black, white = _levels(raw)
            return _postprocess(raw, black, white)
    except rawpy.LibRawError as e:
        raise _libraw_failure(p, frame.source_format, e) from None
    except (OSError, ValueError, MemoryError) as e:
        raise RawReadError(
            p,
            f"could not be demosaiced ({type(e).__name__}: {e})",
            "Check that the file is still in place and complete",
        ) from None


# --------------------------------------------------------------------------
# RGB images
# --------------------------------------------------------------------------


def _to_rgb(arr: np.ndarray, p: Path | None = None) -> np.ndarray:
    if 0 not in arr.shape:
        if arr.ndim == 2:
            return np.repeat(arr[..., None], 3, axis=-1)
        if arr.ndim == 3 and arr.shape[-1] >= 3:
            return arr[..., :3]
        if arr.ndim == 3 and arr.shape[-1] in (1, 2):  # grey, grey + alpha
            return np.repeat(arr[..., :1], 3, axis=-1)
    raise RawReadError(
        p or Path("?"),
        f"holds an image of shape {arr.shape}, not rows x columns (x colours)",
        "The file is damaged or not a photograph; export it again as RGB",
    )


SRGB_FILE_COLOUR = CameraColour(source="the file is sRGB-encoded: its decoded values are linear sRGB already")
LINEAR_TIFF_COLOUR = CameraColour(
    source="assumed: a 16-bit or float TIFF carries no camera colour data; taken as linear sRGB, white-balanced"
)


def _rgb_frame(p: Path, kind: str, rgb: np.ndarray, meta: dict[str, Any], colour: CameraColour) -> RawFrame:
    rgb = np.ascontiguousarray(rgb, dtype=np.float32)
    spec = sensor_for(meta.get("model"), meta.get("make"))
    pitch = None
    if spec is not None:
        pitch = spec.width_mm / max(rgb.shape[0], rgb.shape[1])  # the image's long side spans the sensor width
    elif meta.get("photosite_pitch_mm"):
        pitch = meta["photosite_pitch_mm"]
    return RawFrame(rgb, pitch, kind, RawMetadata(**meta), p, half_resolution=False, _rgb=rgb, colour=colour)


def _read_8bit_style(p: Path, kind: str) -> RawFrame:
    import cv2

    try:
        with _open_binary(p) as f:
            data = f.read()
    except OSError as e:
        raise RawReadError(p, f"cannot be read: {e.strerror or e}", "Check the file and its permissions") from None
    if kind == "jpeg" and b"\xff\xd9" not in data[-65536:]:
        raise RawReadError(p, "is a truncated JPEG (no end-of-image marker)", "Copy or export the image again")
    declared = image_size_px(data, kind)
    if declared is not None:
        _check_pixels(p, *declared)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error:
        img = None
    if img is None:
        raise RawReadError(
            p,
            f"could not be decoded as {kind.upper()}; the file is damaged or truncated",
            "Export or copy the image again",
        )
    _check_pixels(p, int(img.shape[1]), int(img.shape[0]))
    _refuse_source_samples(p, img)
    if img.ndim == 3 and img.shape[-1] >= 3:
        img = cv2.cvtColor(img[..., :3], cv2.COLOR_BGR2RGB)
    rgb = _to_rgb(img, p)
    scale = 255.0 if rgb.dtype == np.uint8 else 65535.0
    linear = srgb_to_linear(rgb.astype(np.float32) / np.float32(scale))
    tiff = None
    try:
        tiff = _tiff_from_jpeg(data) if kind == "jpeg" else _tiff_from_png(data) if kind == "png" else None
    except (ValueError, struct.error, IndexError):
        tiff = None
    return _rgb_frame(p, kind, linear, _metadata(tiff), SRGB_FILE_COLOUR)


def _read_tiff(p: Path) -> RawFrame:
    import tifffile

    tiff = _read_tiff_structure(p, "tiff")
    try:
        with tifffile.TiffFile(p) as tf:
            page = tf.pages[0]
            _check_pixels(p, int(getattr(page, "imagewidth", 0)), int(getattr(page, "imagelength", 0)))
            arr = page.asarray()
            if arr.ndim == 3 and getattr(page, "planarconfig", None) == tifffile.PLANARCONFIG.SEPARATE:
                arr = np.moveaxis(arr, 0, -1)
    except RawReadError:
        raise
    except Exception as e:  # tifffile fails on hostile files with many exception types
        raise RawReadError(
            p, f"could not be decoded as TIFF ({e})", "Export the image again as an uncompressed 16-bit RGB TIFF"
        ) from None
    _refuse_source_samples(p, arr)
    rgb = _to_rgb(arr, p)
    colour = LINEAR_TIFF_COLOUR
    if rgb.dtype == np.uint16:
        linear = rgb.astype(np.float32) / np.float32(65535)  # 16-bit TIFF: linear
    elif rgb.dtype == np.uint8:
        linear = srgb_to_linear(rgb.astype(np.float32) / np.float32(255))
        colour = SRGB_FILE_COLOUR
    elif rgb.dtype.kind == "f":
        linear = np.clip(np.nan_to_num(rgb.astype(np.float32)), 0.0, 1.0)
    else:
        raise RawReadError(
            p, f"has {rgb.dtype} samples, which mca does not read", "Export it as 16-bit unsigned linear TIFF"
        )
    return _rgb_frame(p, "tiff", linear, _metadata(tiff), colour)
