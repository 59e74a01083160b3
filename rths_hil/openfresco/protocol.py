"""OpenFresco's remote-test wire protocol, server side (an experimental site over TCP).

Two clients speak it:

``elem-server``
    OpenSees' ``genericClient`` element (``element genericClient tag -node … -dof … -server
    port host``), the client side of OpenFresco's ``SimAppElemServer``
    (OpenSees ``SRC/element/generic/GenericClient.cpp``).
``generic-tcp``
    OpenFresco's ``expControl GenericTCP`` (``ECGenericTCP.cpp``): OpenFresco keeps its
    ExperimentalSite and ExperimentalSetup and hands the actuator commands to us.

Both open the connection with an **ID** of 11 int32 (native byte order)::

    sizeCtrl[disp, vel, accel, force, time], sizeDaq[disp, vel, accel, force, time], dataSize

and then exchange **frames** of ``dataSize`` float64 (native byte order, no header) in both
directions. The action code is element 0 of every client frame (OpenFresco ``FrescoGlobals.h``):

==== ====================== ==================================================================
code action                 payload / reply
==== ====================== ==================================================================
1    open                   ignored (as ``SimAppElemServer`` does)
2    setup                  ignored (as ``SimAppElemServer`` does)
3    setTrialResponse       the control blocks packed from index 1 (no reply)
4    execute                no reply
5    commitState            no reply
6    getDaqResponse         reply: the DAQ blocks packed from index 0
7    getDisp                reply: displacement block (elem-server: element DOFs)
8    getVel                 reply: velocity block
9    getAccel               reply: acceleration block
10   getForce               reply: force block (elem-server: element DOFs)
11   getTime                reply: time block
12   getInitialStiff        reply: nb×nb matrix, column-major (elem-server)
13   getTangentStiff        reply: nb×nb matrix, column-major (elem-server)
14   getDamp                reply: nb×nb matrix, column-major (elem-server)
15   getMass                reply: nb×nb matrix, column-major (elem-server)
99   DIE                    the client is done; the server closes
==== ====================== ==================================================================

The ``genericClient`` element with ``nb`` element DOFs sends the ID
``(nb, nb, nb, 0, 1,  0, 0, 0, nb, 0,  dataSize)`` with ``dataSize ≥ max(1 + 3·nb + 1, nb²)``
(256 unless ``-dataSize`` says otherwise). Its setTrialResponse frame carries ``disp, vel,
accel`` (``nb`` values each) from index 1, then the analysis time.
"""

from __future__ import annotations

import sys
from dataclasses import dataclass

import numpy as np

from ..errors import InputError

__all__ = [
    "ACTIONS",
    "BLOCKS",
    "COMMIT",
    "DIE",
    "EXECUTE",
    "FRAME_DTYPE",
    "GET_ACCEL",
    "GET_DAMP",
    "GET_DAQ",
    "GET_DISP",
    "GET_FORCE",
    "GET_INITIAL_STIFF",
    "GET_MASS",
    "GET_TANGENT_STIFF",
    "GET_TIME",
    "GET_VEL",
    "ID_BYTES",
    "ID_DTYPE",
    "MAX_DATA_SIZE",
    "OPEN",
    "PROTOCOLS",
    "SETUP",
    "SET_TRIAL",
    "SessionID",
    "client_id",
]

OPEN = 1
SETUP = 2
SET_TRIAL = 3
EXECUTE = 4
COMMIT = 5
GET_DAQ = 6
GET_DISP = 7
GET_VEL = 8
GET_ACCEL = 9
GET_FORCE = 10
GET_TIME = 11
GET_INITIAL_STIFF = 12
GET_TANGENT_STIFF = 13
GET_DAMP = 14
GET_MASS = 15
DIE = 99

#: Action code → name (OpenFresco ``FrescoGlobals.h``, ``OF_RemoteTest_*``).
ACTIONS: dict[int, str] = {
    OPEN: "open",
    SETUP: "setup",
    SET_TRIAL: "setTrialResponse",
    EXECUTE: "execute",
    COMMIT: "commitState",
    GET_DAQ: "getDaqResponse",
    GET_DISP: "getDisp",
    GET_VEL: "getVel",
    GET_ACCEL: "getAccel",
    GET_FORCE: "getForce",
    GET_TIME: "getTime",
    GET_INITIAL_STIFF: "getInitialStiff",
    GET_TANGENT_STIFF: "getTangentStiff",
    GET_DAMP: "getDamp",
    GET_MASS: "getMass",
    DIE: "DIE",
}

#: The five response blocks in the order they are packed (``OF_Resp_*``).
BLOCKS = ("disp", "vel", "accel", "force", "time")

PROTOCOLS = ("elem-server", "generic-tcp")

#: OpenSees' ``Channel::sendID`` writes C ints, ``sendVector`` C doubles, both native.
_ORDER = "<" if sys.byteorder == "little" else ">"
ID_DTYPE = np.dtype(_ORDER + "i4")
FRAME_DTYPE = np.dtype(_ORDER + "f8")
ID_BYTES = 11 * ID_DTYPE.itemsize

#: Largest dataSize accepted (a garbage ID must not make the server allocate gigabytes).
MAX_DATA_SIZE = 1 << 20


@dataclass(frozen=True)
class SessionID:
    """The 11-int ID a client sends first, validated for one protocol flavour.

    Attributes
    ----------
    ctrl, daq : tuple of int
        Block sizes ``(disp, vel, accel, force, time)`` the client sends (control) and expects
        back (DAQ).
    data_size : int
        Number of float64 in every frame, both directions.
    protocol : str
        ``"elem-server"`` or ``"generic-tcp"``.
    """

    ctrl: tuple[int, int, int, int, int]
    daq: tuple[int, int, int, int, int]
    data_size: int
    protocol: str

    @property
    def frame_bytes(self) -> int:
        """Bytes in one frame."""
        return self.data_size * FRAME_DTYPE.itemsize

    @property
    def nb(self) -> int:
        """Number of element DOFs (elem-server) or control displacements (generic-tcp)."""
        return self.ctrl[0]

    def ctrl_offsets(self) -> dict[str, slice]:
        """Where each control block sits in a setTrialResponse frame (from index 1)."""
        return _offsets(self.ctrl, 1)

    def daq_offsets(self) -> dict[str, slice]:
        """Where each DAQ block sits in a getDaqResponse reply (from index 0)."""
        return _offsets(self.daq, 0)

    def as_tuple(self) -> tuple[int, ...]:
        """The 11 ints as sent."""
        return (*self.ctrl, *self.daq, self.data_size)

    @classmethod
    def parse(cls, raw: bytes, protocol: str, n_actuators: int | None = None) -> SessionID:
        """Decode and validate the ID; :class:`InputError` with one line saying what is wrong.

        Parameters
        ----------
        raw : bytes
            The first 44 bytes the client sent.
        protocol : str
            Expected flavour (the config's ``openfresco.protocol``).
        n_actuators : int, optional
            For ``generic-tcp``: the number of channels the site drives (must equal the control
            displacement size).
        """
        if protocol not in PROTOCOLS:
            raise InputError(f"openfresco.protocol must be one of {PROTOCOLS}, got {protocol!r}")
        if len(raw) != ID_BYTES:
            raise InputError(
                f"client ID has {len(raw)} bytes, expected {ID_BYTES} (11 int32); "
                "is the client an OpenSees genericClient or OpenFresco GenericTCP?"
            )
        ints = np.frombuffer(raw, dtype=ID_DTYPE).astype(int).tolist()
        ctrl = tuple(ints[0:5])
        daq = tuple(ints[5:10])
        size = ints[10]
        shown = "(" + ", ".join(str(i) for i in ints) + ")"
        if any(v < 0 for v in ints):
            raise InputError(f"client ID {shown}: negative sizes")
        if not 1 <= size <= MAX_DATA_SIZE:
            raise InputError(f"client ID {shown}: dataSize {size} outside 1 … {MAX_DATA_SIZE}")
        need_in = 1 + sum(ctrl)
        need_out = sum(daq)
        if protocol == "elem-server":
            nb = ctrl[0]
            expect = (nb, nb, nb, 0, 1, 0, 0, 0, nb, 0)
            if nb < 1 or (*ctrl, *daq) != expect:
                raise InputError(
                    f"client ID {shown} is not an OpenSees genericClient's (expected "
                    f"(nb, nb, nb, 0, 1, 0, 0, 0, nb, 0, dataSize)); with openfresco.protocol = "
                    "'generic-tcp' the server expects OpenFresco's expControl GenericTCP"
                )
            need_out = max(need_out, nb * nb)
        else:
            if ctrl[0] < 1:
                raise InputError(
                    f"client ID {shown}: GenericTCP must control displacements "
                    "(-ctrlModes 1 …); this site commands displacement"
                )
            if daq[0] < 1 and daq[3] < 1:
                raise InputError(f"client ID {shown}: GenericTCP asks for no DAQ data")
            if n_actuators is not None and ctrl[0] != n_actuators:
                raise InputError(
                    f"client ID {shown}: {ctrl[0]} control displacements, but the site drives "
                    f"{n_actuators} actuator channel(s)"
                )
            for name, a in (("disp", daq[0]), ("force", daq[3])):
                if a not in (0, ctrl[0]):
                    raise InputError(
                        f"client ID {shown}: DAQ {name} size {a}, expected 0 or {ctrl[0]}"
                    )
        if size < max(need_in, need_out):
            raise InputError(
                f"client ID {shown}: dataSize {size} is smaller than the "
                f"{max(need_in, need_out)} values a frame must carry"
            )
        return cls(ctrl, daq, size, protocol)  # type: ignore[arg-type]


def _offsets(sizes: tuple[int, ...], start: int) -> dict[str, slice]:
    out: dict[str, slice] = {}
    i = start
    for name, n in zip(BLOCKS, sizes, strict=True):
        if n:
            out[name] = slice(i, i + n)
            i += n
    return out


def client_id(
    ctrl: tuple[int, ...], daq: tuple[int, ...], data_size: int = 256
) -> bytes:  # for tests and the benchmark's scripted client
    """Encode an ID as a client would send it."""
    return np.asarray([*ctrl, *daq, data_size], dtype=ID_DTYPE).tobytes()
