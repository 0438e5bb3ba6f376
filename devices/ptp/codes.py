"""PTP and Canon EOS numeric codes: operations, responses, events, object formats, device properties and their names."""

from __future__ import annotations

from enum import IntEnum


class ContainerType(IntEnum):
    COMMAND = 1
    DATA = 2
    RESPONSE = 3
    EVENT = 4


class Op(IntEnum):
    """Operation codes (standard 0x1xxx, Canon EOS 0x91xx)."""

    GET_DEVICE_INFO = 0x1001
    OPEN_SESSION = 0x1002
    CLOSE_SESSION = 0x1003
    GET_STORAGE_IDS = 0x1004
    GET_STORAGE_INFO = 0x1005
    GET_NUM_OBJECTS = 0x1006
    GET_OBJECT_HANDLES = 0x1007
    GET_OBJECT_INFO = 0x1008
    GET_OBJECT = 0x1009
    GET_THUMB = 0x100A
    DELETE_OBJECT = 0x100B
    SEND_OBJECT_INFO = 0x100C
    SEND_OBJECT = 0x100D
    INITIATE_CAPTURE = 0x100E
    GET_DEVICE_PROP_DESC = 0x1014
    GET_DEVICE_PROP_VALUE = 0x1015
    SET_DEVICE_PROP_VALUE = 0x1016
    GET_PARTIAL_OBJECT = 0x101B
    EOS_GET_STORAGE_IDS = 0x9101
    EOS_GET_STORAGE_INFO = 0x9102
    EOS_GET_OBJECT_INFO = 0x9103
    EOS_GET_OBJECT = 0x9104
    EOS_DELETE_OBJECT = 0x9105
    EOS_FORMAT_STORE = 0x9106
    EOS_GET_PARTIAL_OBJECT = 0x9107
    EOS_GET_DEVICE_INFO_EX = 0x9108
    EOS_GET_OBJECT_INFO_EX = 0x9109
    EOS_GET_THUMB_EX = 0x910A
    EOS_REMOTE_RELEASE = 0x910F
    EOS_SET_DEVICE_PROP_VALUE_EX = 0x9110
    EOS_GET_REMOTE_MODE = 0x9113
    EOS_SET_REMOTE_MODE = 0x9114
    EOS_SET_EVENT_MODE = 0x9115
    EOS_GET_EVENT = 0x9116
    EOS_TRANSFER_COMPLETE = 0x9117
    EOS_CANCEL_TRANSFER = 0x9118
    EOS_PC_HDD_CAPACITY = 0x911A
    EOS_SET_UI_LOCK = 0x911B
    EOS_RESET_UI_LOCK = 0x911C
    EOS_KEEP_DEVICE_ON = 0x911D
    EOS_REQUEST_DEVICE_PROP_VALUE = 0x9127
    EOS_REMOTE_RELEASE_ON = 0x9128
    EOS_REMOTE_RELEASE_OFF = 0x9129
    EOS_SET_REQUEST_OLC_INFO_GROUP = 0x913D
    EOS_GET_VIEWFINDER_DATA = 0x9153
    EOS_DO_AF = 0x9154
    EOS_DRIVE_LENS = 0x9155
    EOS_ZOOM = 0x9158
    EOS_ZOOM_POSITION = 0x9159
    EOS_AF_CANCEL = 0x9160


class Resp(IntEnum):
    """Response codes."""

    UNDEFINED = 0x2000
    OK = 0x2001
    GENERAL_ERROR = 0x2002
    SESSION_NOT_OPEN = 0x2003
    INVALID_TRANSACTION_ID = 0x2004
    OPERATION_NOT_SUPPORTED = 0x2005
    PARAMETER_NOT_SUPPORTED = 0x2006
    INCOMPLETE_TRANSFER = 0x2007
    INVALID_STORAGE_ID = 0x2008
    INVALID_OBJECT_HANDLE = 0x2009
    DEVICE_PROP_NOT_SUPPORTED = 0x200A
    INVALID_OBJECT_FORMAT_CODE = 0x200B
    STORE_FULL = 0x200C
    OBJECT_WRITE_PROTECTED = 0x200D
    STORE_READ_ONLY = 0x200E
    ACCESS_DENIED = 0x200F
    NO_THUMBNAIL_PRESENT = 0x2010
    STORE_NOT_AVAILABLE = 0x2013
    SPECIFICATION_BY_FORMAT_UNSUPPORTED = 0x2014
    NO_VALID_OBJECT_INFO = 0x2015
    DEVICE_BUSY = 0x2019
    INVALID_PARENT_OBJECT = 0x201A
    INVALID_DEVICE_PROP_FORMAT = 0x201B
    INVALID_DEVICE_PROP_VALUE = 0x201C
    INVALID_PARAMETER = 0x201D
    SESSION_ALREADY_OPEN = 0x201E
    TRANSACTION_CANCELLED = 0x201F
    CANON_UNKNOWN_COMMAND = 0xA001
    CANON_OPERATION_REFUSED = 0xA005
    CANON_LENS_COVER = 0xA006
    CANON_BATTERY_LOW = 0xA101
    CANON_OBJECT_NOT_READY = 0xA102


class Event(IntEnum):
    """Standard PTP event codes (interrupt endpoint / PTP/IP event channel), and Canon's 0xC101."""

    CANCEL_TRANSACTION = 0x4001
    OBJECT_ADDED = 0x4002
    OBJECT_REMOVED = 0x4003
    STORE_ADDED = 0x4004
    STORE_REMOVED = 0x4005
    DEVICE_PROP_CHANGED = 0x4006
    OBJECT_INFO_CHANGED = 0x4007
    DEVICE_INFO_CHANGED = 0x4008
    REQUEST_OBJECT_TRANSFER = 0x4009
    STORE_FULL = 0x400A
    STORAGE_INFO_CHANGED = 0x400C
    CAPTURE_COMPLETE = 0x400D
    CANON_EOS_REQUEST_GET_EVENT = 0xC101


class EosEventCode(IntEnum):
    """Record codes inside the data of a Canon EOS GetEvent (0x9116)."""

    TERMINATOR = 0x0000
    REQUEST_GET_EVENT = 0xC101
    OBJECT_ADDED_EX = 0xC181
    OBJECT_REMOVED = 0xC182
    REQUEST_GET_OBJECT_INFO_EX = 0xC183
    STORAGE_STATUS_CHANGED = 0xC184
    STORAGE_INFO_CHANGED = 0xC185
    REQUEST_OBJECT_TRANSFER = 0xC186
    OBJECT_INFO_CHANGED_EX = 0xC187
    OBJECT_CONTENT_CHANGED = 0xC188
    PROP_VALUE_CHANGED = 0xC189
    AVAIL_LIST_CHANGED = 0xC18A
    CAMERA_STATUS_CHANGED = 0xC18B
    WILL_SOON_SHUTDOWN = 0xC18D
    SHUTDOWN_TIMER_UPDATED = 0xC18E
    REQUEST_CANCEL_TRANSFER = 0xC18F
    REQUEST_OBJECT_TRANSFER_DT = 0xC190
    REQUEST_CANCEL_TRANSFER_DT = 0xC191
    STORE_ADDED = 0xC192
    STORE_REMOVED = 0xC193
    BULB_EXPOSURE_TIME = 0xC194
    RECORDING_TIME = 0xC195
    POWER_ZOOM_INFO_CHANGED = 0xC19D
    AF_RESULT = 0xC1A3
    CTG_INFO_CHECK_COMPLETE = 0xC1A4
    OLC_INFO_CHANGED = 0xC1A5
    OBJECT_ADDED_EX64 = 0xC1A7
    REQUEST_OBJECT_TRANSFER64 = 0xC1A9


class ObjectFormat(IntEnum):
    UNDEFINED = 0x3000
    ASSOCIATION = 0x3001
    SCRIPT = 0x3002
    DPOF = 0x3006
    WAV = 0x3008
    AVI = 0x300A
    DEFINED = 0x3800
    JPEG = 0x3801
    JFIF = 0x3808
    CANON_CRW = 0xB101
    CANON_CR2 = 0xB103
    CANON_MOV = 0xB104
    CANON_B105 = 0xB105
    CANON_CR3 = 0xB108
    CANON_BF02 = 0xBF02


class EosProp(IntEnum):
    """Canon EOS device property codes (the ones this stack reads or sets)."""

    APERTURE = 0xD101
    SHUTTER_SPEED = 0xD102
    ISO_SPEED = 0xD103
    EXP_COMPENSATION = 0xD104
    AUTO_EXPOSURE_MODE = 0xD105
    DRIVE_MODE = 0xD106
    METERING_MODE = 0xD107
    FOCUS_MODE = 0xD108
    WHITE_BALANCE = 0xD109
    COLOR_TEMPERATURE = 0xD10A
    PICTURE_STYLE = 0xD110
    BATTERY_POWER = 0xD111
    CAMERA_TIME = 0xD113
    AUTO_POWER_OFF = 0xD114
    OWNER = 0xD115
    MODEL_ID = 0xD116
    PTP_EXTENSION_VERSION = 0xD119
    AVAILABLE_SHOTS = 0xD11B
    CAPTURE_DESTINATION = 0xD11C
    IMAGE_FORMAT = 0xD120
    IMAGE_FORMAT_CF = 0xD121
    IMAGE_FORMAT_SD = 0xD122
    ARTIST = 0xD1D0
    COPYRIGHT = 0xD1D1
    SHUTTER_COUNTER = 0xD1AC
    SERIAL_NUMBER = 0xD1AF
    EVF_OUTPUT_DEVICE = 0xD1B0
    EVF_MODE = 0xD1B1
    OLC_INFO_VERSION = 0xD1B9
    FOCUS_INFO_EX = 0xD1D3
    LENS_NAME = 0xD1D8


class StdProp(IntEnum):
    """Standard PTP device property codes used by generic cameras."""

    BATTERY_LEVEL = 0x5001
    IMAGE_SIZE = 0x5003
    COMPRESSION_SETTING = 0x5004
    F_NUMBER = 0x5007
    EXPOSURE_TIME = 0x500D
    EXPOSURE_INDEX = 0x500F


class DataType(IntEnum):
    INT8 = 0x0001
    UINT8 = 0x0002
    INT16 = 0x0003
    UINT16 = 0x0004
    INT32 = 0x0005
    UINT32 = 0x0006
    INT64 = 0x0007
    UINT64 = 0x0008
    STR = 0xFFFF


CANON_VENDOR_ID = 0x04A9
EOS_70D_PRODUCT_ID = 0x3253
#: The vendor extension id libgphoto2 (and this stack) use for Canon bodies.
CANON_VENDOR_EXTENSION_ID = 0x0000000B
#: What EOS bodies actually send on the wire: Microsoft's id (70D, 60D, 600D, 100D, R10 ...), or MTP's.
MICROSOFT_VENDOR_EXTENSION_ID = 0x00000006
MTP_VENDOR_EXTENSION_ID = 0xFFFFFFFF
CAPTURE_DESTINATION_CARD = 2
CAPTURE_DESTINATION_RAM = 4
ALL_STORAGES = 0xFFFFFFFF
#: The first parameter of GetViewFinderData seen in traces of EOS bodies.
VIEWFINDER_DATA_PARAM = 0x00200000
#: EVF output device bits (0xD1B0): 1 the camera's screen, 2 the computer.
EVF_OUTPUT_TFT = 1
EVF_OUTPUT_PC = 2

#: Human names of operations, for `mca camera doctor` (codes not listed are shown in hex).
OP_NAMES: dict[int, str] = {
    0x1001: "GetDeviceInfo",
    0x1002: "OpenSession",
    0x1003: "CloseSession",
    0x1004: "GetStorageIDs",
    0x1005: "GetStorageInfo",
    0x1006: "GetNumObjects",
    0x1007: "GetObjectHandles",
    0x1008: "GetObjectInfo",
    0x1009: "GetObject",
    0x100A: "GetThumb",
    0x100B: "DeleteObject",
    0x100C: "SendObjectInfo",
    0x100D: "SendObject",
    0x100E: "InitiateCapture",
    0x100F: "FormatStore",
    0x1014: "GetDevicePropDesc",
    0x1015: "GetDevicePropValue",
    0x1016: "SetDevicePropValue",
    0x101B: "GetPartialObject",
    0x9101: "EOS GetStorageIDs",
    0x9102: "EOS GetStorageInfo",
    0x9103: "EOS GetObjectInfo",
    0x9104: "EOS GetObject",
    0x9105: "EOS DeleteObject",
    0x9106: "EOS FormatStore",
    0x9107: "EOS GetPartialObject",
    0x9108: "EOS GetDeviceInfoEx",
    0x9109: "EOS GetObjectInfoEx",
    0x910A: "EOS GetThumbEx",
    0x910F: "EOS RemoteRelease",
    0x9110: "EOS SetDevicePropValueEx",
    0x9113: "EOS GetRemoteMode",
    0x9114: "EOS SetRemoteMode",
    0x9115: "EOS SetEventMode",
    0x9116: "EOS GetEvent",
    0x9117: "EOS TransferComplete",
    0x9118: "EOS CancelTransfer",
    0x911A: "EOS PCHDDCapacity",
    0x911B: "EOS SetUILock",
    0x911C: "EOS ResetUILock",
    0x911D: "EOS KeepDeviceOn",
    0x9125: "EOS BulbStart",
    0x9126: "EOS BulbEnd",
    0x9127: "EOS RequestDevicePropValue",
    0x9128: "EOS RemoteReleaseOn",
    0x9129: "EOS RemoteReleaseOff",
    0x913D: "EOS SetRequestOLCInfoGroup",
    0x9151: "EOS InitiateViewfinder",
    0x9152: "EOS TerminateViewfinder",
    0x9153: "EOS GetViewFinderData",
    0x9154: "EOS DoAf",
    0x9155: "EOS DriveLens",
    0x9158: "EOS Zoom",
    0x9159: "EOS ZoomPosition",
    0x915A: "EOS SetLiveAfFrame",
    0x9160: "EOS AfCancel",
}

#: Human names of device properties (standard and Canon EOS), for `mca camera doctor`.
PROP_NAMES: dict[int, str] = {
    0x5001: "BatteryLevel",
    0x5003: "ImageSize",
    0x5004: "CompressionSetting",
    0x5007: "FNumber",
    0x500D: "ExposureTime",
    0x500F: "ExposureIndex",
    0xD049: "ModelID (MTP)",
    0xD303: "UseDeviceStage (MTP)",
    0xD402: "DeviceFriendlyName (MTP)",
    0xD406: "SessionInitiatorVersionInfo (MTP)",
    0xD407: "PerceivedDeviceType (MTP)",
    0xD101: "Aperture",
    0xD102: "ShutterSpeed",
    0xD103: "ISOSpeed",
    0xD104: "ExpCompensation",
    0xD105: "AutoExposureMode",
    0xD106: "DriveMode",
    0xD107: "MeteringMode",
    0xD108: "FocusMode",
    0xD109: "WhiteBalance",
    0xD10A: "ColorTemperature",
    0xD10B: "WhiteBalanceAdjustA",
    0xD10C: "WhiteBalanceAdjustB",
    0xD10D: "WhiteBalanceXA",
    0xD10E: "WhiteBalanceXB",
    0xD10F: "ColorSpace",
    0xD110: "PictureStyle",
    0xD111: "BatteryPower",
    0xD112: "BatterySelect",
    0xD113: "CameraTime",
    0xD114: "AutoPowerOff",
    0xD115: "Owner",
    0xD116: "ModelID",
    0xD119: "PTPExtensionVersion",
    0xD11A: "DPOFVersion",
    0xD11B: "AvailableShots",
    0xD11C: "CaptureDestination",
    0xD11D: "BracketMode",
    0xD11E: "CurrentStorage",
    0xD11F: "CurrentFolder",
    0xD120: "ImageFormat",
    0xD121: "ImageFormatCF",
    0xD122: "ImageFormatSD",
    0xD138: "AEModeDial",
    0xD1A0: "CustomFuncEx",
    0xD1A1: "MyMenu",
    0xD1A2: "MyMenuList",
    0xD1A3: "WftStatus",
    0xD1A8: "CardExtension",
    0xD1A9: "TempStatus",
    0xD1AC: "ShutterCounter",
    0xD1AF: "SerialNumber",
    0xD1B0: "EVFOutputDevice",
    0xD1B1: "EVFMode",
    0xD1B2: "DepthOfFieldPreview",
    0xD1B3: "EVFSharpness",
    0xD1B4: "EVFWBMode",
    0xD1B5: "EVFClickWBCoeffs",
    0xD1B6: "EVFColorTemp",
    0xD1B7: "ExposureSimMode",
    0xD1B8: "EVFRecordStatus",
    0xD1B9: "OLCInfoVersion",
    0xD1BA: "LvAfSystem",
    0xD1BC: "MovSize",
    0xD1BD: "LvViewTypeSelect",
    0xD1C1: "AloMode",
    0xD1CC: "DepthOfField",
    0xD1D0: "Artist",
    0xD1D1: "Copyright",
    0xD1D3: "FocusInfoEx",
    0xD1D5: "Brightness",
    0xD1D8: "LensName",
    0xD1D9: "AEB",
    0xD1DC: "LensID",
    0xD1DD: "LensID2",
}

#: Human names of the EOS event-record codes.
EOS_EVENT_NAMES: dict[int, str] = {e.value: e.name for e in EosEventCode}


def name_of(enum_type: type[IntEnum], code: int) -> str:
    """`Resp.DEVICE_BUSY` style name for a code, or its hex when unknown."""
    try:
        return enum_type(code).name
    except ValueError:
        return f"0x{code:04X}"


def op_name(code: int) -> str:
    """`0x9116 EOS GetEvent` style label for an operation code."""
    return f"0x{code:04X} {OP_NAMES.get(code, '(unknown)')}"


def prop_name(code: int) -> str:
    """`0xD11C CaptureDestination` style label for a device property code."""
    return f"0x{code:04X} {PROP_NAMES.get(code, '(unknown)')}"
