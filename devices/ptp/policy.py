"""Timeouts and retry budgets of the PTP host stack, in one place, with libgphoto2-like values.

Every number a transport, `Camera` or the tethering session waits or retries
by comes from a `PtpPolicy`; tests shrink the times with `replace(...)`.
Retries are allowed only for operations that are safe to repeat
(`SAFE_TO_REPEAT`): the shutter release is never repeated by the stack.
"""

from __future__ import annotations

from dataclasses import dataclass

from mca.devices.ptp.codes import Op


@dataclass(frozen=True)
class PtpPolicy:
    """How long to wait and how often to retry; defaults follow libgphoto2's camlibs/ptp2 (read for facts)."""

    #: OpenSession on a Canon body (libgphoto2: 1.5 s, "0.5 was too low"); then `transaction_timeout_s`.
    start_timeout_s: float = 1.5
    #: OpenSession attempts, with a USB device reset after an I/O failure (libgphoto2: 3).
    open_session_tries: int = 3
    #: Any transaction once the session is open (libgphoto2: 20 s; some bodies answer after 15 s).
    transaction_timeout_s: float = 20.0
    #: The release commands: a half press runs the autofocus, up to 8 s with a slow lens (libgphoto2: 100 s).
    capture_timeout_s: float = 100.0
    #: Polling GetEvent for the new file after the release (libgphoto2 EOS_CAPTURE_TIMEOUT: 90 s).
    object_wait_s: float = 90.0
    #: Back-off between empty polls: +50 ms per poll up to 200 ms, reset by any event (libgphoto2).
    poll_step_s: float = 0.05
    poll_max_s: float = 0.2
    #: Events polled between half and full press for the autofocus result (libgphoto2: 500 ms).
    focus_wait_s: float = 0.5
    #: Start-up: keep polling until every setting the body lists has been reported (libgphoto2 polls until
    #: the list is empty, then 10 x 50 ms more for the EVF output device; a 70D spreads them over polls).
    settle_s: float = 3.0
    #: A second file of a RAW+JPEG shot follows the first within this time.
    second_file_wait_s: float = 15.0
    #: The camera reported "busy" before a release: wait this long for it to become ready.
    ready_wait_s: float = 10.0
    #: KeepDeviceOn every 10 s while tethered (libgphoto2).
    keep_alive_s: float = 10.0
    #: Replies to earlier transactions (late answers after a timeout) discarded within one transaction.
    stale_replies_max: int = 16
    #: A stalled (EPIPE) bulk endpoint: clear the halt and retry once, only if nothing was read yet (libgphoto2).
    stall_retries: int = 1
    #: DeviceBusy on an operation that is safe to repeat: attempts and the back-off between them.
    busy_retries: int = 8
    busy_backoff_s: float = 0.05
    busy_backoff_max_s: float = 1.0
    #: A timeout or broken container on an operation that is safe to repeat: recover the link and repeat.
    transient_retries: int = 3
    #: After a timeout: wait this long for Get Device Status to say OK before a device reset.
    recover_wait_s: float = 2.0
    #: Reconnect attempts after the camera went away, with exponential back-off up to 2 s.
    reconnect_attempts: int = 5
    #: GetViewFinderData answers "not ready" (0xA102 / busy) for up to 3 s after live view starts (libgphoto2).
    live_view_ready_s: float = 3.0
    #: A data phase is streamed in pieces of at most this size (GetPartialObject blocks; libgphoto2: 1 MiB).
    download_block_bytes: int = 1024 * 1024


DEFAULT_POLICY = PtpPolicy()

#: Operations a host may repeat without side effects beyond the first: reads, mode switches, settings.
#: Never here: EOS RemoteRelease / RemoteReleaseOn (the shutter), InitiateCapture, BulbStart/End, DeleteObject,
#: SendObject. RemoteReleaseOn(1) (the half press) is repeated only by `Camera`, which knows it is a half press.
SAFE_TO_REPEAT = frozenset(
    {
        Op.GET_DEVICE_INFO,
        Op.GET_STORAGE_IDS,
        Op.GET_STORAGE_INFO,
        Op.GET_NUM_OBJECTS,
        Op.GET_OBJECT_HANDLES,
        Op.GET_OBJECT_INFO,
        Op.GET_OBJECT,
        Op.GET_THUMB,
        Op.GET_DEVICE_PROP_DESC,
        Op.GET_DEVICE_PROP_VALUE,
        Op.SET_DEVICE_PROP_VALUE,
        Op.GET_PARTIAL_OBJECT,
        Op.EOS_GET_STORAGE_IDS,
        Op.EOS_GET_STORAGE_INFO,
        Op.EOS_GET_OBJECT_INFO,
        Op.EOS_GET_OBJECT,
        Op.EOS_GET_PARTIAL_OBJECT,
        Op.EOS_GET_DEVICE_INFO_EX,
        Op.EOS_GET_OBJECT_INFO_EX,
        Op.EOS_SET_DEVICE_PROP_VALUE_EX,
        Op.EOS_SET_REMOTE_MODE,
        Op.EOS_SET_EVENT_MODE,
        Op.EOS_GET_EVENT,
        Op.EOS_PC_HDD_CAPACITY,
        Op.EOS_KEEP_DEVICE_ON,
        Op.EOS_REQUEST_DEVICE_PROP_VALUE,
        Op.EOS_REMOTE_RELEASE_OFF,
        Op.EOS_SET_REQUEST_OLC_INFO_GROUP,
        Op.EOS_GET_VIEWFINDER_DATA,
        Op.EOS_AF_CANCEL,
        Op.EOS_SET_UI_LOCK,
        Op.EOS_RESET_UI_LOCK,
    }
)
#: The shutter: sent once per requested shot, whatever happens next.
RELEASE_OPS = frozenset({Op.EOS_REMOTE_RELEASE, Op.EOS_REMOTE_RELEASE_ON, Op.INITIATE_CAPTURE})


def is_safe_to_repeat(op: int) -> bool:
    return op in SAFE_TO_REPEAT
