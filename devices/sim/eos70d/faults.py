"""Fault injection for the simulated EOS 70D, and the named fault scenarios (`--camera sim:SCENARIO`).

`FaultPlan` is what goes wrong on the link (armed on the USB backend or the
PTP/IP server); `SimBehaviour` (in `responder`) is how the body itself behaves.
A scenario names a combination of both; `scenario("late-settings")` returns
them, and every scenario has a test asserting one exposure per requested shot
and nothing lost.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from mca.devices.ptp.codes import Op
from mca.devices.sim.eos70d.responder import SimBehaviour


@dataclass
class FaultPlan:
    """What should go wrong, armed on a backend or PTP/IP server; each fault fires once unless noted.

    - `disconnect_after_in_bytes`: the camera vanishes after sending this many more bytes in a data phase
      of GetPartialObject/GetObject (a cable pulled mid-download).
    - `stall_op`: the next command with this operation code gets no reply at all (the host times out).
    - `busy_count`: the next N operations (other than GetEvent and the shutter release) answer DeviceBusy.
    - `short_read_bytes`: every GetPartialObject sends at most this many bytes (persistent while set).
    - `corrupt_op`: the response to the next command with this code has a broken container header.
    - `coalesce_response`: the response shares the bulk transfer with the end of the data phase (persistent).
    - `epipe_op`: before answering the next command with this code, the bulk-in endpoint stalls (libusb
      reports EPIPE) until the host clears the halt.
    - `late_reply_op` / `late_reply_s`: the reply to the next command with this code comes `late_reply_s`
      late (after the host gave up); with `ignore_cancel` the body does not drop it when the host cancels.
    - `lose_object_event_reply`: the reply to the GetEvent that carries a new file never comes (the body
      has already dequeued those events: only the card shows the file).
    - `interrupt_after_in_bytes`: the host process gets a KeyboardInterrupt (Ctrl-C) after this many
      bytes of downloads (USB only: the host thread is the one reading).
    """

    disconnect_after_in_bytes: int | None = None
    stall_op: int | None = None
    busy_count: int = 0
    short_read_bytes: int = 0
    corrupt_op: int | None = None
    coalesce_response: bool = False
    epipe_op: int | None = None
    late_reply_op: int | None = None
    late_reply_s: float = 0.0
    ignore_cancel: bool = False
    lose_object_event_reply: bool = False
    interrupt_after_in_bytes: int | None = None


DOWNLOAD_OPS = (0x1009, 0x101B, 0x9104, 0x9107)


def corrupt_container(raw: bytes) -> bytes:
    """A response container whose length field is impossible (shorter than its header)."""
    return b"\x05\x00\x00\x00" + raw[4:]


@dataclass(frozen=True)
class Scenario:
    """A named fault scenario: how the link misbehaves, how the body behaves, and what it is for."""

    name: str
    description: str
    faults: FaultPlan = field(default_factory=FaultPlan)
    behaviour: SimBehaviour = field(default_factory=SimBehaviour)
    #: Host timeouts short enough for a test of this scenario (seconds); None keeps the defaults.
    host_timeout_s: float | None = None
    #: The requested shots that should end with a file (False: the body refuses the release by design).
    shots_succeed: bool = True


def _scenarios() -> dict[str, Scenario]:
    items = [
        Scenario("none", "a well-behaved 70D"),
        Scenario(
            "vendor-id-6",
            "the wire's vendor extension id 6 (every real EOS body); the host restores Canon's 0xB",
            behaviour=SimBehaviour(vendor_extension_id=6),
        ),
        Scenario(
            "late-settings",
            "the settings arrive 300 ms late, spread over six GetEvent polls",
            behaviour=SimBehaviour(settings_delay_s=0.3, settings_polls=6),
        ),
        Scenario(
            "slow-half-press",
            "autofocus takes 6 s: the half press answers after 6 s (longer than the old 5 s timeout)",
            behaviour=SimBehaviour(half_press_s=6.0),
        ),
        Scenario(
            "late-response",
            "a GetEvent reply comes 0.5 s after the host timed out; the body ignores the cancel",
            faults=FaultPlan(late_reply_op=Op.EOS_GET_EVENT, late_reply_s=0.8, ignore_cancel=True),
            host_timeout_s=0.3,
        ),
        Scenario(
            "epipe-stall",
            "the bulk-in endpoint stalls (EPIPE) before a GetObjectInfo reply",
            faults=FaultPlan(epipe_op=Op.GET_OBJECT_INFO),
        ),
        Scenario(
            "epipe-download",
            "the bulk-in endpoint stalls (EPIPE) before a GetPartialObject reply",
            faults=FaultPlan(epipe_op=Op.EOS_GET_PARTIAL_OBJECT),
        ),
        Scenario(
            "lost-event-poll",
            "the GetEvent reply announcing the new file is lost; only the card shows it",
            faults=FaultPlan(lose_object_event_reply=True),
            host_timeout_s=0.3,
        ),
        Scenario(
            "unknown-records",
            "event lists carry records no parser knows (0xC1F6, OLC, list types 1 and 7, odd sizes)",
            behaviour=SimBehaviour(unknown_records=True),
        ),
        Scenario(
            "card-with-files", "the card already holds files in two folders", behaviour=SimBehaviour(files_on_card=6)
        ),
        Scenario(
            "busy-after-shot",
            "the body stays busy 0.4 s after each shot (card write); the next release must wait",
            behaviour=SimBehaviour(busy_after_shot_s=0.4),
        ),
        Scenario("device-busy", "the next operations answer DeviceBusy", faults=FaultPlan(busy_count=3)),
        Scenario(
            "disconnect-mid-download",
            "the cable is pulled 100 kB into a download",
            faults=FaultPlan(disconnect_after_in_bytes=100_000),
            host_timeout_s=0.3,
        ),
        Scenario(
            "no-reply",
            "a GetPartialObject gets no reply at all",
            faults=FaultPlan(stall_op=Op.EOS_GET_PARTIAL_OBJECT),
            host_timeout_s=0.3,
        ),
        Scenario(
            "short-reads", "every GetPartialObject sends at most 1000 bytes", faults=FaultPlan(short_read_bytes=1000)
        ),
        Scenario(
            "corrupt-container",
            "a GetPartialObject response has an impossible length",
            faults=FaultPlan(corrupt_op=Op.EOS_GET_PARTIAL_OBJECT),
            host_timeout_s=0.3,
        ),
        Scenario(
            "coalesced-response", "responses share a transfer with the data", faults=FaultPlan(coalesce_response=True)
        ),
        Scenario(
            "full-press-busy",
            "the full press answers DeviceBusy and nothing is taken (the EOS R10 trace)",
            behaviour=SimBehaviour(full_press_busy=True),
            shots_succeed=False,
        ),
        Scenario(
            "af-fail",
            "One-Shot AF finds no focus: the body would not fire",
            behaviour=SimBehaviour(af_result="failed", focus_mode=0),
            shots_succeed=False,
        ),
    ]
    return {s.name: s for s in items}


SCENARIOS: dict[str, Scenario] = _scenarios()


def scenario(name: str) -> Scenario:
    """A fresh copy of the named scenario (its FaultPlan is consumed as faults fire)."""
    if name not in SCENARIOS:
        raise ValueError(f"unknown simulator scenario {name!r}; choose from {', '.join(SCENARIOS)}")
    return _scenarios()[name]
