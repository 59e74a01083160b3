"""CANopen driver: a CiA 402 servo drive or a CiA 408 hydraulic axis, through ``canopen``.

The bridge is the CANopen NMT master and SYNC producer; the controller is node ``node_id``.
Everything of CiA 301 — SDO, NMT, PDO mapping, SYNC, heartbeat, EMCY — goes through the
``canopen`` library (:class:`canopen.Network`, :class:`canopen.RemoteNode`) over a python-can bus
(``virtual`` in tests, ``socketcan``/``pcan``/``kvaser`` … on a real bus).

**Start-up** (:meth:`CANopenDriver.open`): read the device type 0x1000 and the identity 0x1018
by SDO and check them against the profile (the low 16 bits of 0x1000 must be 402 or 408;
``vendor_id`` / ``product_code`` when given); NMT pre-operational; write the profile's mode
object (402: 0x6060 = 8, cyclic synchronous position; 408: 0x6042 = 1, set-point via bus), the
device's heartbeat producer time 0x1017 (``controller_heartbeat``) and, when given, its heartbeat
consumer 0x1016 (``device_watchdog``: the bridge's heartbeat, node ``bridge_node_id``); the PDO
mapping (:meth:`CANopenDriver._map_pdos`): with ``configure_pdo = true`` (the default) the
driver's own is written by SDO —

* RPDO1 (COB-ID 0x200 + node, synchronous): control word 0x6040 + position set-point
  (402: target position 0x607A; 408: axis position set-point 0x6600:01), 6 bytes;
* TPDO1 (0x180 + node, every SYNC): status word 0x6041 + actual position (402: 0x6064;
  408: 0x6601:01), 6 bytes;
* TPDO2 (0x280 + node, every SYNC): the measured force (``force_object``: 0x2100, the
  manufacturer-specific INTEGER32 of the project's twins, where the EDS has it, else the torque
  actual 0x6077; ``""`` for none) —

unless the EDS has the mapping objects read-only (a fixed mapping) or the device refuses the
writes with an SDO abort; then, and with ``configure_pdo = false``, the device's own mapping is
used. Either way the mapping is read back from the device by SDO and the objects are taken from
whichever PDO carries them; the torque actual (per mille of the rated torque 0x6076, read by
SDO) is scaled to N by ``force_per_torque``; a device that maps no force gives NaN. Then NMT
operational. A PDO longer than 8 bytes, an EDS without one of the objects, a device mapping no
control word / set-point / status word / actual position, a wrong device type or identity is
refused with one line (:class:`~rths_hil.errors.InputError`, exit 2).

**Each step** (the base class's contract: :meth:`~..base.Driver.send` →
:meth:`CANopenDriver._send_raw`, :meth:`~..base.Driver.receive` →
:meth:`CANopenDriver._recv_internal`): RPDO1 with the control word and the set-point, then one
SYNC, sent by the bus (:class:`CANopenBus`) as soon as every axis on it has written its RPDO
(or when the first axis waits for its step's feedback, if one did not send), so several axes on
one bus share one SYNC per step. The
SYNC is the step clock: the devices apply the RPDO received before it and answer with their
TPDOs. The feedback of step ``k`` is the TPDO set received after SYNC ``k`` (TPDOs carry no
sequence number: a TPDO that comes after the next SYNC is taken for the next step's, see
``docs/canopen.md``). The RPDO is packed and the TPDOs unpacked by one precompiled ``struct``
each (:class:`Layout`), checked at start-up against the library's encoding and decoding of its
PDO maps (:meth:`Layout.check`; the library stays the authority on the mapping).
Positions are counts on the wire (``counts_per_m``), forces counts of ``newtons_per_count``.
The base class owns the receive deadline, the timeouts, the sequence rules and the counters.

**State machine.** The control word of each step follows the device's last reported state one
transition at a time (402: shutdown → switch on → enable operation; 408: active), so the run's
first ``enable=True`` steps bring the drive into operation without a jump (the first set-point
must be within ``start_tolerance`` of the actual position read at arming). :meth:`estop` sends
the profile's e-stop word at once (402 quick stop 0x0002 → QUICK STOP ACTIVE; 408 hold 0x0003,
latched by the driver since the 408 FSA has no quick-stop state) with its own SYNC, and repeats
it every step until a command with ``enable=False`` acknowledges it (402: disable voltage →
SWITCH ON DISABLED). :meth:`arm` resets a fault (402 fault reset 0x0080, 408 bit 3, each a
rising edge) and brings the device to holding (402 SWITCHED ON, 408 HOLD) by SDO. At a normal
end :meth:`close` hands the device back disabled by its own sequence (402 shutdown → disable
voltage: SWITCH ON DISABLED; 408 DISABLED), after an e-stop it leaves the latch; it clears the
device's heartbeat consumer 0x1016:01 when it set it (the bridge's heartbeat stops), and always
ends with NMT stop.

**Status.** 402 OPERATION ENABLED → ``ENABLED``, QUICK STOP ACTIVE → ``ESTOP_ACTIVE``, FAULT
(REACTION ACTIVE) → ``FAULT``; 408 ACTIVE → ``ENABLED``, HOLD after the e-stop →
``ESTOP_ACTIVE``, FAULT * → ``FAULT``. An EMCY with a non-zero error code sets ``FAULT`` (and
``WATCHDOG`` for 0x8130, heartbeat / life-guard error) until the next arming; the code is logged,
counted in the driver's stats (``emcy``) and named by :meth:`fault_text`, which the loop adds to
its controller trip. The controller's heartbeat (``controller_heartbeat``): when none came for
``controller_heartbeat_timeout`` (1 s), :meth:`_recv_internal` raises
:class:`~..base.LinkDown` (counted ``heartbeat_lost``): the receive returns nothing, so the loop's
watchdog — which counts time — trips.

Connection keys: ``eds`` (required: the controller's EDS file), ``node_id`` (1–127),
``device_profile`` (``cia402`` / ``cia408``), ``interface``, ``channel``, ``bitrate``,
``bus_options``, ``counts_per_m``, ``force_object``, ``newtons_per_count``, ``force_per_torque``,
``bridge_node_id``,
``heartbeat_period``, ``controller_heartbeat``, ``controller_heartbeat_timeout``,
``device_watchdog``, ``start_tolerance``, ``sdo_timeout``, ``vendor_id``, ``product_code``,
``configure_pdo`` (documented in ``docs/canopen.md``).
"""

from ..can import options as can_options
from ..protocol import Protocol
from . import linkbudget
from .device import CANopenStats
from .driver import CANopenDriver
from .linkbudget import axes_that_fit, link_load, step_frames
from .network import CANopenBus
from .od import (
    BRIDGE_NODE_ID,
    EMCY_HEARTBEAT,
    ESTOP_SETTLE,
    FORCE_OBJECT,
    NMT_OPERATIONAL,
    RATED_TORQUE,
    SYNC_ID,
    TORQUE_ACTUAL,
    load_od,
    parse_object,
)
from .pdo import Layout

__all__ = [
    "BRIDGE_NODE_ID",
    "EMCY_HEARTBEAT",
    "ESTOP_SETTLE",
    "FORCE_OBJECT",
    "NMT_OPERATIONAL",
    "PROTOCOL",
    "RATED_TORQUE",
    "SYNC_ID",
    "TORQUE_ACTUAL",
    "CANopenBus",
    "CANopenDriver",
    "CANopenStats",
    "Layout",
    "axes_that_fit",
    "link_load",
    "load_od",
    "parse_object",
    "step_frames",
]

#: The CANopen protocol's planning facts (:mod:`rths_hil.drivers.protocol`): the hooks of its link
#: model (:mod:`.linkbudget`) and what else differs from the defaults.
PROTOCOL = Protocol.from_hooks(
    "canopen",
    CANopenDriver,
    linkbudget,
    path_keys=("eds",),
    serve_options=can_options.serve_options,
)
