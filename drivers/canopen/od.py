"""The constants of the bridge's CANopen side and the object dictionary: the EDS read by the
``canopen`` library, object names (``"0x6064"``, ``"0x6600:1"``) and the connection keys'
quantities checked one by one.
"""

from __future__ import annotations

import logging
import math
import os
import time
from typing import Any

import can
import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from rths_hil.errors import InputError
from rths_hil.units import parse_length, parse_time

from ..base import Status

log = logging.getLogger(__package__)

#: Default node id of the bridge (its heartbeat is 0x700 + this).
BRIDGE_NODE_ID = 127
#: SYNC COB-ID (CiA 301).
SYNC_ID = 0x80
#: Heartbeat NMT state byte of an operational node.
NMT_OPERATIONAL = 0x05
#: EMCY error code of a heartbeat / life-guard event (CiA 301).
EMCY_HEARTBEAT = 0x8130
#: longest wait after an e-stop for the device to report it before the next command (s)
ESTOP_SETTLE = 0.1
#: the measured force of the project's twins (manufacturer-specific INTEGER32)
FORCE_OBJECT = (0x2100, 0)
#: CiA 402 torque actual value (INTEGER16, per mille of the motor rated torque 0x6076)
TORQUE_ACTUAL = (0x6077, 0)
#: CiA 402 motor rated torque (UNSIGNED32, mN·m; mN for a linear motor)
RATED_TORQUE = (0x6076, 0)
_WATCHDOG = int(Status.WATCHDOG)
_ESTOP = int(Status.ESTOP_ACTIVE)
_FAULT = int(Status.FAULT)
_S32 = (-(2**31), 2**31 - 1)
_BUS_ERRORS = (can.CanError, OSError, ValueError, ImportError, NotImplementedError)
_SDO_ERRORS = (SdoAbortedError, SdoCommunicationError)
_perf = time.perf_counter
#: a TPDO of the current SYNC that has not come yet
_MISSING = object()


def parse_object(text: Any, what: str) -> tuple[int, int]:
    """``"0x6064"`` or ``"0x6600:1"`` (or an int) → (index, sub-index)."""
    if isinstance(text, int) and not isinstance(text, bool):
        return int(text), 0
    s = str(text).strip()
    idx, _, sub = s.partition(":")
    try:
        return int(idx, 0), int(sub, 0) if sub else 0
    except ValueError:
        raise InputError(
            f"canopen: {what}: {text!r} is not an object index like 0x2100 or 0x6600:1"
        ) from None


def _quantity(key: str, value: Any, unit: str) -> Any:
    """A time (s) or length (m) key given as a string with its unit (``"0.1 s"``, ``"1mm"``)
    read to SI; anything else as it is (checked by the caller)."""
    if isinstance(value, str):
        return (parse_time if unit == "s" else parse_length)(value, f"canopen: {key}")
    return value


def _identity(key: str, value: Any) -> int | None:
    """``vendor_id`` / ``product_code``: an integer, or a string such as ``"0x0000A3C7"``."""
    if value is None:
        return None
    if isinstance(value, int) and not isinstance(value, bool) and 0 <= value <= 0xFFFFFFFF:
        return value
    if isinstance(value, str):
        try:
            v = int(value.strip(), 0)
        except ValueError:
            v = -1
        if 0 <= v <= 0xFFFFFFFF:
            return v
    raise InputError(
        f"canopen: {key} must be an UNSIGNED32 like 0x0000A3C7 (0x1018), got {value!r}"
    )


def _check_bitrate(bitrate: Any) -> None:
    """``bitrate``: None (the interface's) or a positive whole number of bit/s."""
    if bitrate is None:
        return
    if (
        isinstance(bitrate, bool)
        or not isinstance(bitrate, int | float)
        or not (math.isfinite(bitrate) and bitrate > 0 and float(bitrate).is_integer())
    ):
        raise InputError(f"canopen: bitrate must be a positive integer (bit/s), got {bitrate!r}")


def load_od(eds: str | os.PathLike[str], node_id: int) -> canopen.ObjectDictionary:
    """The object dictionary of an EDS file; one line when it cannot be read."""
    path = os.fspath(eds)
    if not os.path.exists(path):
        raise InputError(f"canopen: eds: no such file {path!r}")
    if not os.path.isfile(path):
        raise InputError(f"canopen: eds {path!r} is not a regular file (an EDS text file)")
    try:
        return canopen.import_od(path, node_id)
    except Exception as exc:  # the EDS parser raises anything from configparser to KeyError
        raise InputError(f"canopen: eds {path!r} cannot be read: {exc}") from None


def _variable(
    od: canopen.ObjectDictionary, obj: tuple[int, int], path: str, what: str
) -> ODVariable:
    index, sub = obj
    try:
        entry = od[index]
        if isinstance(entry, ODRecord | ODArray):
            entry = entry[sub]
        elif sub:  # a VAR has only sub-index 0
            raise KeyError(sub)
    except KeyError:
        raise InputError(
            f"canopen: eds {path!r} has no object 0x{index:04X}:{sub:02X} ({what})"
        ) from None
    if not isinstance(entry, ODVariable):  # pragma: no cover - defensive
        raise InputError(f"canopen: eds {path!r}: 0x{index:04X}:{sub:02X} ({what}) is not a value")
    return entry
