"""Fuzzing every parser that takes outside bytes: only the documented error types come out, memory stays bounded.

The parsers and their documented errors:

| outside bytes | public parser | documented error |
|---|---|---|
| PTP containers | `codec.parse_container`, `parse_header`, `parse_params` | `ProtocolError` |
| PTP datasets | `datasets.parse_device_info`, `parse_storage_info`, `parse_object_info`, `parse_prop_desc`, `parse_prop_value` | `ProtocolError` |
| EOS event lists | `events.parse_eos_events` | `ProtocolError` |
| PTP/IP packets | `ptpip_packets.parse_packet_header`, `parse_init_command_request`, `parse_init_command_ack`, `parse_operation_request`, `parse_operation_response`, `parse_event_packet`, `parse_start_data` | `ProtocolError` |
| CR2 / TIFF / PNG / JPEG / PPM files | `capture.raw.read_raw`, `capture.raw.image_size_px` | `RawReadError` (none for `image_size_px`) |
| camera profiles | `devices.profiles.load_profile_file`, `processing.camera.profile_from_mapping` | `ProfileError` |
| the config file | `capture.config.read_config_file` + `apply_file` | `ConfigError` |
| the rail's serial line | `grbl_protocol.LineSplitter.feed`, `parse_line` | `GrblProtocolError` |

Inputs are valid encodings with bytes flipped, 32-bit length fields set to edge values, pieces
inserted, deleted, cut and appended, or random bytes; for the TOML files, valid documents with
values replaced by values of any type. Each parser sees `MCA_FUZZ_EXAMPLES` inputs (200 in the
main suite; the CI fuzz job of `.ci/run` runs 10,000 with `-m fuzz`). Memory is bounded twice:
the address space is limited to what the process has plus 1 GiB (an unbounded allocation fails
the test as a `MemoryError`), and the peak of Python allocations per parse is measured
(tracemalloc) against a bound. The counts are printed for the closing note.

Only public parse functions are called, so the tests keep working while their insides change.
"""

from __future__ import annotations

import contextlib
import io
import logging
import os
import resource
import struct
import tracemalloc
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

pytestmark = pytest.mark.fuzz

EXAMPLES = int(os.environ.get("MCA_FUZZ_EXAMPLES", "200"))
FUZZ_SETTINGS = settings(
    max_examples=EXAMPLES, deadline=None, database=None, suppress_health_check=list(HealthCheck), print_blob=True
)
EXTRA_ADDRESS_SPACE = 1 << 30
SMALL_PEAK = 8 << 20  # a parse of a few kB must not allocate more than this
IMAGE_PEAK = 96 << 20  # an image of at most 1 MP (the limit set below) as float planes, with copies

RESULTS: dict[str, tuple[int, int]] = {}  # parser family -> (inputs, peak bytes)


# --- the machinery --------------------------------------------------------------------------------------------------


def _vm_size() -> int:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))


@contextlib.contextmanager
def bounded_memory() -> Iterator[None]:
    """Limit this process's address space to its size now plus 1 GiB for the block (Linux)."""
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    limit = _vm_size() + EXTRA_ADDRESS_SPACE
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


class Meter:
    """Counts the inputs each parser saw and the largest Python allocation peak of a single parse (tracemalloc,
    traced only while the parser runs)."""

    def __init__(self, family: str) -> None:
        self.family = family
        self.inputs: dict[str, int] = {}
        self.peak = 0

    def __call__(self, name: str, parse: Callable[[], object], allowed: tuple[type[BaseException], ...]) -> None:
        self.inputs[name] = self.inputs.get(name, 0) + 1
        tracemalloc.start()
        try:
            parse()
        except allowed:
            pass
        finally:
            self.peak = max(self.peak, tracemalloc.get_traced_memory()[1])
            tracemalloc.stop()


@contextlib.contextmanager
def fuzzing(family: str, peak_bound: int) -> Iterator[Meter]:
    meter = Meter(family)
    with bounded_memory():
        yield meter
    RESULTS[family] = (min(meter.inputs.values(), default=0), meter.peak)
    counts = ", ".join(f"{name} {count}" for name, count in sorted(meter.inputs.items()))
    print(f"\nfuzz {family}: {counts} inputs; peak {meter.peak / 2**20:.2f} MiB of Python allocations per parse")
    assert meter.peak <= peak_bound, f"{family}: a parse allocated {meter.peak} bytes"
    if EXAMPLES >= 10_000:
        short = {name: count for name, count in meter.inputs.items() if count < 10_000}
        assert not short, f"{family}: fewer than 10,000 inputs for {short}"


EDGE_U32 = (0, 1, 2, 7, 8, 11, 12, 13, 0xFF, 0xFFFF, 0x10000, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF)


@st.composite
def mutated(draw: st.DrawFn, seeds: list[bytes], max_random: int = 512) -> bytes:
    """A seed with a few mutations, or random bytes."""
    if draw(st.integers(0, 9)) == 0:
        return draw(st.binary(max_size=max_random))
    data = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(0, 6))):
        op = draw(st.integers(0, 4))
        at = draw(st.integers(0, max(0, len(data))))
        if op == 0 and data:
            data[at % len(data)] = draw(st.integers(0, 255))
        elif op == 1 and len(data) >= 4:
            at = min(at, len(data) - 4)
            value = draw(st.sampled_from(EDGE_U32)) if draw(st.booleans()) else draw(st.integers(0, 0xFFFFFFFF))
            data[at : at + 4] = struct.pack("<I" if draw(st.booleans()) else ">I", value)
        elif op == 2:
            data[at:at] = draw(st.binary(min_size=1, max_size=16))
        elif op == 3 and data:
            del data[at : at + draw(st.integers(1, 64))]
        elif op == 4 and len(data) >= 2:
            data[min(at, len(data) - 2) : min(at, len(data) - 2) + 2] = struct.pack(
                "<H", draw(st.sampled_from((0, 1, 0xFF, 0x7FFF, 0xFFFF)))
            )
    if draw(st.booleans()):
        data = data[: draw(st.integers(0, len(data)))]
    return bytes(data) + draw(st.binary(max_size=8))


# --- PTP ------------------------------------------------------------------------------------------------------------


def _ptp_seeds() -> dict[str, list[bytes]]:
    from mca.devices.ptp.codec import pack_command, pack_data, pack_event, pack_response
    from mca.devices.ptp.datasets import (
        DevicePropDesc,
        ObjectInfo,
        StorageInfo,
        pack_device_info,
        pack_object_info,
        pack_prop_desc,
        pack_prop_value,
        pack_storage_info,
    )
    from mca.devices.ptp.events import (
        EosObjectAdded,
        EosRequestObjectTransfer,
        pack_eos_events,
    )
    from mca.devices.ptp.ptpip_packets import (
        pack_event_packet,
        pack_init_command_ack,
        pack_init_command_request,
        pack_operation_request,
        pack_operation_response,
        pack_start_data,
    )
    from mca.devices.sim.eos70d.responder import SimEos70D

    sim = SimEos70D()
    guid = bytes(range(16))
    return {
        "containers": [
            pack_command(0x1002, 0, (1,)),
            pack_response(0x2001, 5, (1, 2, 3)),
            pack_event(0x4002, 0, (0x91000001,)),
            pack_data(0x1009, 7, b"\x01\x02\x03" * 20),
        ],
        "datasets": [
            pack_device_info(sim.device_info()),
            pack_storage_info(StorageInfo(max_capacity_bytes=16 << 30, free_space_bytes=1 << 30, description="SD")),
            pack_object_info(ObjectInfo(filename="IMG_0001.CR2", capture_date="20240101T120000")),
            pack_prop_desc(DevicePropDesc(0x500F, 4, True, 100, 400, "enum", allowed=(100, 200, 400))),
            pack_prop_desc(DevicePropDesc(0x5001, 2, False, 100, 80, "range", 0, 100, 1)),
            pack_prop_value(0xFFFF, "Canon EOS 70D"),
            pack_prop_value(0x4006, (1, 2, 3)),
        ],
        "eos_events": [
            pack_eos_events(sim.all_props_events()),
            pack_eos_events(
                [
                    EosObjectAdded(0x91000001, 0x20001, 0xB103, 25_000_000, 0x90000002, "IMG_0042.CR2"),
                    EosRequestObjectTransfer(5, 0xB103, 1234, "IMG_0001.CR2"),
                ]
            ),
        ],
        "ptpip": [
            pack_init_command_request(guid, "mca"),
            pack_init_command_ack(1, guid, "Canon EOS 70D"),
            pack_operation_request(0x1002, 1, (1,)),
            pack_operation_response(0x2001, 1, (5,)),
            pack_event_packet(0x4002, 1, (7,)),
            pack_start_data(3, 25_000_000),
        ],
    }


SEEDS = _ptp_seeds()


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_containers(data: st.DataObject, meter: Meter) -> None:
    from mca.devices.ptp.codec import ProtocolError, parse_container, parse_header, parse_params

    raw = data.draw(mutated(SEEDS["containers"] + SEEDS["datasets"]))
    for parse in (parse_container, parse_header, parse_params):
        meter(parse.__name__, lambda parse=parse: parse(raw), (ProtocolError,))


def test_fuzz_ptp_containers() -> None:
    with fuzzing("PTP containers", SMALL_PEAK) as meter:
        _fuzz_containers(meter=meter)


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_datasets(data: st.DataObject, meter: Meter) -> None:
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.datasets import (
        parse_device_info,
        parse_object_info,
        parse_prop_desc,
        parse_prop_value,
        parse_storage_info,
    )

    raw = data.draw(mutated(SEEDS["datasets"]))
    datatype = data.draw(st.sampled_from((0x0002, 0x0004, 0x0006, 0x4006, 0xFFFF, 0x1234)))
    for parse in (parse_device_info, parse_storage_info, parse_object_info, parse_prop_desc):
        meter(parse.__name__, lambda parse=parse: parse(raw), (ProtocolError,))
    meter("parse_prop_value", lambda: parse_prop_value(raw, datatype), (ProtocolError,))


def test_fuzz_ptp_datasets() -> None:
    with fuzzing("PTP datasets", SMALL_PEAK) as meter:
        _fuzz_datasets(meter=meter)


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_eos_events(data: st.DataObject, meter: Meter) -> None:
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.events import parse_eos_events

    raw = data.draw(mutated(SEEDS["eos_events"], max_random=2048))
    meter("parse_eos_events", lambda: parse_eos_events(raw), (ProtocolError,))


def test_fuzz_eos_event_lists() -> None:
    with fuzzing("EOS event lists", SMALL_PEAK) as meter:
        _fuzz_eos_events(meter=meter)


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_ptpip(data: st.DataObject, meter: Meter) -> None:
    from mca.devices.ptp.codec import ProtocolError
    from mca.devices.ptp.ptpip_packets import (
        parse_event_packet,
        parse_init_command_ack,
        parse_init_command_request,
        parse_operation_request,
        parse_operation_response,
        parse_packet_header,
        parse_start_data,
    )

    packet = data.draw(mutated(SEEDS["ptpip"]))
    body = packet[8:]
    meter("parse_packet_header", lambda: parse_packet_header(packet), (ProtocolError,))
    for parse in (
        parse_init_command_request,
        parse_init_command_ack,
        parse_operation_request,
        parse_operation_response,
        parse_event_packet,
        parse_start_data,
    ):
        meter(parse.__name__, lambda parse=parse: parse(body), (ProtocolError,))


def test_fuzz_ptpip_packets() -> None:
    with fuzzing("PTP/IP packets", SMALL_PEAK) as meter:
        _fuzz_ptpip(meter=meter)


# --- image files ----------------------------------------------------------------------------------------------------


def _image_seeds() -> dict[str, list[bytes]]:
    import cv2
    import tifffile

    from mca.devices.sim.cr2 import Cr2Metadata, cr2_bytes

    rng = np.random.default_rng(13)
    mosaic = rng.integers(2048, 15000, size=(32, 48), dtype=np.uint16)
    rgb8 = rng.integers(0, 255, size=(24, 32, 3), dtype=np.uint8)
    tiff16, tiff_float = io.BytesIO(), io.BytesIO()
    tifffile.imwrite(tiff16, rgb8.astype(np.uint16) * 257, photometric="rgb")
    tifffile.imwrite(tiff_float, rgb8.astype(np.float32) / 255, photometric="rgb")
    return {
        ".CR2": [cr2_bytes(mosaic, metadata=Cr2Metadata(), preview=False)],
        ".tif": [tiff16.getvalue(), tiff_float.getvalue()],
        ".png": [cv2.imencode(".png", rgb8)[1].tobytes(), cv2.imencode(".png", rgb8[..., 0])[1].tobytes()],
        ".jpg": [cv2.imencode(".jpg", rgb8)[1].tobytes()],
        ".ppm": [cv2.imencode(".ppm", rgb8)[1].tobytes()],
    }


IMAGE_SEEDS = _image_seeds()
logging.getLogger("tifffile").setLevel(logging.CRITICAL)  # it logs every damaged tag it meets


@pytest.fixture(scope="module")
def image_folder(tmp_path_factory) -> Path:
    shm = Path("/dev/shm")
    if shm.is_dir() and os.access(shm, os.W_OK):
        folder = shm / f"mca-fuzz-{os.getpid()}"
        folder.mkdir(exist_ok=True)
        yield folder
        for child in folder.iterdir():
            child.unlink()
        folder.rmdir()
    else:
        yield tmp_path_factory.mktemp("fuzz-images")


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_images(data: st.DataObject, meter: Meter, folder: Path) -> None:
    from mca.capture.raw import RawReadError, image_size_px, read_policy, read_raw

    suffix = data.draw(st.sampled_from(sorted(IMAGE_SEEDS)))
    raw = data.draw(mutated(IMAGE_SEEDS[suffix], max_random=4096))
    kind = {".CR2": "cr2", ".tif": "tiff", ".png": "png", ".jpg": "jpeg", ".ppm": "ppm"}[suffix]

    def probe() -> None:
        size = image_size_px(raw, kind)  # documented to raise nothing
        assert size is None or (isinstance(size, tuple) and len(size) == 2)

    meter("image_size_px", probe, ())
    path = folder / f"fuzz{suffix}"
    path.write_bytes(raw)
    photograph = data.draw(st.booleans())

    def parse() -> None:
        with read_policy(max_megapixels=1.0, photograph=photograph):
            read_raw(path)

    meter("read_raw", parse, (RawReadError,))


def test_fuzz_image_headers(image_folder: Path) -> None:
    with fuzzing("CR2/TIFF/PNG/JPEG/PPM files", IMAGE_PEAK) as meter:
        _fuzz_images(meter=meter, folder=image_folder)


# --- TOML files: profiles and the config ----------------------------------------------------------------------------

HOSTILE_VALUES = (
    None,
    True,
    False,
    0,
    -1,
    2**63 - 1,
    -(2**63),
    0.0,
    -0.0,
    1e-300,
    1e300,
    -1e300,
    float("nan"),
    float("inf"),
    float("-inf"),
    "",
    " ",
    "x",
    "~nobody-here/x",
    "a\x00b",
    "../../etc",
    "1e300",
    [],
    [0.0],
    [1e300, 0],
    [0.0, 0.0, 0.0],
    [[1, 0, 0], [0, 1, 0], [0, 0, 0]],
    {},
    {"x": 1},
)
# Values of any type: mostly the hostile ones above (cheap to draw), sometimes freshly generated ones.
ANY_VALUE = st.one_of(
    st.sampled_from(HOSTILE_VALUES),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(-(2**63), 2**63 - 1),
    st.text(max_size=12),
    st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=4),
)


def _replace_leaves(draw: st.DrawFn, value: object) -> object:
    """A copy of a parsed TOML document with some values replaced by values of any type, some keys dropped."""
    if isinstance(value, dict):
        out = {}
        for key, item in value.items():
            choice = draw(st.integers(0, 9))
            if choice == 0:
                continue  # dropped
            out[key] = draw(ANY_VALUE) if choice == 1 else _replace_leaves(draw, item)
        if draw(st.integers(0, 9)) == 0:
            out[draw(st.text(max_size=8))] = draw(ANY_VALUE)
        return out
    if isinstance(value, list):
        return [draw(ANY_VALUE) if draw(st.integers(0, 4)) == 0 else _replace_leaves(draw, v) for v in value]
    return draw(ANY_VALUE) if draw(st.integers(0, 3)) == 0 else value


def _text_mutation(draw: st.DrawFn, text: str) -> bytes:
    data = bytearray(text.encode("utf-8"))
    for _ in range(draw(st.integers(1, 4))):
        at = draw(st.integers(0, len(data)))
        op = draw(st.integers(0, 2))
        if op == 0:
            data[at:at] = draw(st.sampled_from([b"=", b"[", b"]", b'"', b"\n", b"1e300", b"-0", b"nan", b"\xff", b"#"]))
        elif op == 1:
            del data[at : at + draw(st.integers(1, 12))]
        else:
            data[at:at] = draw(st.binary(max_size=6))
    return bytes(data)


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_profiles(data: st.DataObject, meter: Meter, folder: Path) -> None:
    import tomllib

    from mca.devices.profiles import BUILTIN_DIR, load_profile_file
    from mca.processing.camera import ProfileError, profile_from_mapping

    name = data.draw(st.sampled_from(["paper-70d.toml", "bando2008.toml"]))
    text = (BUILTIN_DIR / name).read_text()
    document = _replace_leaves(data.draw, tomllib.loads(text))
    meter("profile_from_mapping", lambda: profile_from_mapping(document, "fuzz"), (ProfileError,))
    path = folder / "profile.toml"
    path.write_bytes(_text_mutation(data.draw, text))
    meter("load_profile_file", lambda: load_profile_file(path), (ProfileError,))


def test_fuzz_profiles(tmp_path: Path) -> None:
    with fuzzing("profiles", SMALL_PEAK) as meter:
        _fuzz_profiles(meter=meter, folder=tmp_path)


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_config(data: st.DataObject, meter: Meter, folder: Path) -> None:
    import tomllib

    from mca.capture.config import Config, ConfigError, apply_file, read_config_file

    text = (Path(__file__).resolve().parents[1] / "deploy" / "config.example.toml").read_text()
    path = folder / "config.toml"
    document = _replace_leaves(data.draw, tomllib.loads(text))
    meter("apply_file", lambda: apply_file(Config(), path, document), (ConfigError,))
    path.write_bytes(_text_mutation(data.draw, text))
    meter("read_config_file", lambda: apply_file(Config(), path, read_config_file(path)), (ConfigError,))


def test_fuzz_config(tmp_path: Path) -> None:
    with fuzzing("config", SMALL_PEAK) as meter:
        _fuzz_config(meter=meter, folder=tmp_path)


# --- the rail's serial line -----------------------------------------------------------------------------------------

GRBL_SEEDS = [
    b"ok\r\n",
    b"error:22\r\n",
    b"ALARM:2\r\n",
    b"Grbl 1.1h ['$' for help]\r\n",
    b"<Idle|MPos:-300.000,0.000,0.000|FS:0,0|WCO:0.000,0.000,0.000>\r\n",
    b"<Hold:1|MPos:-12.500,0.000,0.000|FS:600,0>\r\n",
    b"$130=300.000\r\n$23=0\r\n",
    b"[MSG:'$H'|'$X' to unlock]\r\n",
]


@FUZZ_SETTINGS
@given(data=st.data())
def _fuzz_grbl(data: st.DataObject, meter: Meter) -> None:
    from mca.devices.rail.grbl_protocol import GrblProtocolError, LineSplitter, parse_line

    raw = data.draw(mutated(GRBL_SEEDS))

    def parse() -> None:
        splitter = LineSplitter()
        cut = data.draw(st.integers(0, len(raw)))
        for chunk in (raw[:cut], raw[cut:]):
            for line in splitter.feed(chunk):
                parse_line(line)

    meter("LineSplitter.feed + parse_line", parse, (GrblProtocolError,))


def test_fuzz_grbl_lines() -> None:
    with fuzzing("GRBL serial lines", SMALL_PEAK) as meter:
        _fuzz_grbl(meter=meter)
