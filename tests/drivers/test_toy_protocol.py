"""A protocol added the way a newcomer adds one, no edit of the core. Outside rths_hil: one
folder (a Driver subclass, its :class:`~rths_hil.drivers.protocol.Protocol` descriptor and its
twin endpoint) and two entry points. Inside it, as the shipped protocols are: one folder under
``drivers/`` (its package, with ``PROTOCOL``, and its profile format) and one endpoint module
that declares its ``TWIN``, found by the registries with no list edited. The link budget plans
it from its descriptor and ``rths-hil run`` runs it in lockstep against its twin; the record
carries exactly what the twin sent."""

from __future__ import annotations

import importlib
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from rths_hil.cli import main
from rths_hil.errors import InputError
from rths_hil.records.recorder import read_run

QUIET = ["--set", "loop.console=0", "-q"]
ROOT = Path(__file__).resolve().parents[2]

# The toy wire, little-endian, over UDP on the loopback interface: a command is type 0xC1, seq
# u32, enable u8, displacement i32 in µm (10 bytes); a feedback 0xF1, seq u32, status u8,
# displacement i32 in µm, force i32 in 0.1 N (14 bytes); e-stop 0xE5 and heartbeat 0x48 one
# byte. Its link model: 10-bit characters on a line of ``rate`` bit/s.
_DRIVER = """
import select
import socket
import struct
import time

from rths_hil.drivers.base import Driver, Feedback, LinkDown
from rths_hil.drivers.protocol import Protocol
from rths_hil.errors import InputError
from rths_hil.linkbudget import LinkLoad

COMMAND = struct.Struct("<BIBi")
FEEDBACK = struct.Struct("<BIBii")
UM = 1e-6
DN = 0.1


class ToyDriver(Driver):
    name = "toy"
    command_lsb = UM
    honours_deadline = True

    def __init__(self, host="127.0.0.1", port=9000, rate=None):
        super().__init__()
        self.host, self.port, self.rate = str(host), int(port), rate
        self._sock = None

    def open(self):
        if self._sock is None:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.connect((self.host, self.port))
            sock.setblocking(False)
            self._sock = sock

    def close(self):
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _write(self, data):
        try:
            self._sock.send(data)
        except (OSError, AttributeError):
            self.stats.send_errors += 1

    def _send_raw(self, seq, displacement, enable):
        self._write(COMMAND.pack(0xC1, seq, int(enable), round(displacement / UM)))

    def _recv_internal(self, deadline):
        if self._sock is None:
            raise LinkDown("toy driver closed")
        left = max(deadline - time.perf_counter(), 0.0)
        if not select.select((self._sock,), (), (), left)[0]:
            return None
        try:
            data = self._sock.recv(64)
        except OSError:
            self.stats.disconnects += 1
            return None
        if len(data) != FEEDBACK.size or data[0] != 0xF1:
            self.stats.count_malformed("bad_frame")
            return None
        _, seq, status, d, f = FEEDBACK.unpack(data)
        return Feedback(seq, d * UM, f * DN, status)

    def estop(self):
        self.stats.estops += 1
        self._write(bytes([0xE5]))

    def heartbeat(self):
        self._write(bytes([0x48]))


def link_key(connection):
    c = connection or {}
    return f"toy {c.get('host', '127.0.0.1')}:{c.get('port', 9000)}"


def link_load(connection, channels_on_link, fs, *, heartbeat_hz=0.0):
    bits = 10 * (COMMAND.size + FEEDBACK.size)
    rate = (connection or {}).get("rate")
    if rate is None:
        return LinkLoad(link_key(connection), None, "toy line without a rate, not checked",
                        channels=channels_on_link, fs=fs, kind="toy")
    return LinkLoad(
        link_key(connection), channels_on_link * bits * fs / rate,
        f"{channels_on_link} x {bits} bits at {fs:g} Hz", channels=channels_on_link, fs=fs,
        kind="toy", rate=float(rate), per_channel=bits / rate,
    )


def link_advice(load, limit):
    return [f"a toy line of >= {load.rate * load.load / limit:.0f} bit/s"]


def check_sharing(channels):
    seen = {}
    for _, name, conn, twin in channels:
        if twin and not conn.get("port"):
            continue
        key = link_key(conn)
        if key in seen:
            raise InputError(f"actuators: channels {seen[key]!r} and {name!r} share {key}")
        seen[key] = name


def serve_options(group):
    group.add_argument("--toy-rate", type=int, default=None, help="toy: line rate (bit/s)")


PROTOCOL = Protocol(name="toy", driver=ToyDriver, link_key=link_key, link_load=link_load,
                    link_advice=link_advice, check_sharing=check_sharing,
                    serve_options=serve_options)
"""

_TWIN = """
import select
import socket

from rths_hil.sim_backends.endpoints.base import TwinEndpoint

from . import COMMAND, DN, FEEDBACK, UM

#: Every feedback the twin put on the wire: (seq, status, displacement µm, force 0.1 N).
SENT = []


class ToyTwin(TwinEndpoint):
    name = "toy"
    seq_bits = None

    @classmethod
    def connection_from_args(cls, args):
        return {"rate": args.toy_rate}

    def __init__(self, controller, host="127.0.0.1", port=0, rate=None):
        super().__init__(controller)
        self.host, self.port, self.rate = host, int(port), rate
        self._sock = None
        self._peer = None

    def _setup(self):
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.bind((self.host, self.port))
        port = self._sock.getsockname()[1]
        self.connection = {"host": self.host, "port": port, "rate": self.rate}
        self.where = f"toy udp {self.host}:{port}"

    def _teardown(self):
        sock, self._sock = self._sock, None
        if sock is not None:
            sock.close()

    def _serve_once(self, timeout):
        if self._sock is None or not select.select((self._sock,), (), (), timeout)[0]:
            return
        data, self._peer = self._sock.recvfrom(64)
        ctl = self.controller
        if len(data) == COMMAND.size and data[0] == 0xC1:
            _, seq, enable, d = COMMAND.unpack(data)
            self.emit(ctl.command(seq, d * UM, bool(enable)))
        elif data == bytes([0xE5]):
            ctl.estop()
        elif data == bytes([0x48]):
            ctl.heartbeat()

    def _encode(self, seq, displacement, force, status):
        d, f = round(displacement / UM), round(force / DN)
        SENT.append((seq, status, d, f))
        return [FEEDBACK.pack(0xF1, seq, status & 0xFF, d, f)]

    def _corrupt(self, frame):
        return frame[:-1]

    def _write(self, frame):
        if self._sock is not None and self._peer is not None:
            self._sock.sendto(frame, self._peer)
"""


@pytest.fixture
def toy_package(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The newcomer's folder ``toy_proto/`` (driver, descriptor, twin) and the dist-info that
    ``pip install`` writes for its two entry points."""
    site = tmp_path / "site"
    pkg = site / "toy_proto"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(textwrap.dedent(_DRIVER))
    (pkg / "twin.py").write_text(textwrap.dedent(_TWIN))
    info = site / "toy_proto-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: toy-proto\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(
        "[rths_hil.drivers]\ntoy = toy_proto:PROTOCOL\n\n"
        "[rths_hil.twins]\ntoy = toy_proto.twin:ToyTwin\n"
    )
    monkeypatch.syspath_prepend(str(site))
    importlib.invalidate_caches()
    yield site
    for mod in ("toy_proto", "toy_proto.twin"):
        sys.modules.pop(mod, None)


def test_the_core_names_no_toy() -> None:
    """The core ships no trace of the toy protocol: what the tests below find, the entry
    points or the folders they add brought (and took away again)."""
    from rths_hil.drivers.profile import protocol_key
    from rths_hil.drivers.registry import BUILTIN, available, profile_formats
    from rths_hil.sim_backends.registry import TWINS, available_twins

    assert "toy" not in BUILTIN and "toy" not in TWINS and "toy" not in available()
    assert "toy" not in available_twins() and "toy" not in profile_formats()
    assert "toy" not in protocol_key().choices


def test_the_link_budget_plans_the_toy_from_its_descriptor(toy_package: Path, capsys) -> None:
    from rths_hil.drivers.registry import driver_class, protocol

    from rths_hil.linkbudget import check_links, link_key, link_load

    assert driver_class("toy").__name__ == "ToyDriver"
    assert protocol("toy").path_keys == ()
    # 10-bit characters: command 1+4+1+4 = 10 bytes, feedback 1+4+1+4+4 = 14 bytes per step
    bits = 10 * (10 + 14)
    three = link_load("toy", {"rate": 1_000_000}, 3, 1000.0)
    assert three.link == link_key("toy", {"rate": 1_000_000}) == "toy 127.0.0.1:9000"
    assert three.load == pytest.approx(3 * bits * 1000.0 / 1e6)  # 0.72: under 80 %
    check_links([three])
    four = link_load("toy", {"rate": 1_000_000}, 4, 1000.0)  # 0.96
    # what fits: 0.8 / (4 · 240 µs) = 833 Hz; ⌊0.8 / 0.24⌋ = 3 channels; 1e6 · 0.96 / 0.8
    with pytest.raises(
        InputError,
        match=r"96 % loaded .*a loop rate ≤ 833 Hz; ≤ 3 channels per link; "
        r"a toy line of >= 1200000 bit/s",
    ):
        check_links([four])
    # the plan asks the same: one channel at 1024 Hz on a 100 kbit/s toy line is 246 % loaded
    code = main(["run", "--lockstep", "--duration", "0.1", "--out", str(toy_package / "o"),
                 *QUIET, "--set", "driver.name=toy",
                 "--set", "driver.connection={rate=100000}"])  # fmt: skip
    err = capsys.readouterr().err
    assert code == 2, err
    assert f"is {bits * 1024 / 1e5 * 100:.0f} % loaded" in err and "a toy line of" in err


def test_the_toy_runs_in_lockstep_against_its_twin(toy_package: Path, tmp_path: Path) -> None:
    """The record's measured displacement and force are the twin's frames, decoded: the values
    the twin put on the wire for the step (in µm and 0.1 N), step by step."""
    out = tmp_path / "run"
    args = ["run", "--lockstep", "--duration", "1", "--out", str(out), *QUIET]
    args += ["--set", "driver.name=toy", "--set", "driver.connection={rate=10000000}"]
    assert main(args) == 0
    import toy_proto.twin as twin

    _check_record(out, twin.SENT)


def _check_record(out: Path, replies: list[tuple[int, int, int, int]]) -> None:
    """The record of the 1 s run in ``out`` is the twin's ``replies`` (its ``SENT``)."""
    rec = read_run(out).record
    assert len(rec) == 1024 and bool(np.all(rec["feedback_ok"]))
    sent = {seq: (d, f) for seq, _, d, f in replies}  # the last reply of each sequence
    seqs = np.array(sorted(sent))
    # the run's steps are the last 1024 commands before the hand-back: find the step-0 sequence
    # as the one whose reply sequence reproduces the record (the start phase runs before it)
    d_um = np.array([sent[s][0] for s in seqs])
    f_dn = np.array([sent[s][1] for s in seqs])
    meas = np.round(rec["measured"] / 1e-6).astype(np.int64)
    starts = [
        i for i in range(len(seqs) - len(rec) + 1) if np.array_equal(d_um[i : i + len(rec)], meas)
    ]
    assert len(starts) == 1, starts
    i0 = starts[0]
    np.testing.assert_array_equal(rec["measured"], d_um[i0 : i0 + len(rec)] * 1e-6)
    np.testing.assert_array_equal(rec["force"], f_dn[i0 : i0 + len(rec)] * 0.1)
    assert np.ptp(d_um[i0 : i0 + len(rec)]) > 50  # the twin moved (µm): not a constant record


def test_a_protocol_registered_at_run_time(toy_package: Path) -> None:
    """The registry's public API takes a descriptor too (no entry point): the link budget asks
    it, and after ``unregister`` the name is unknown again."""
    import dataclasses

    import toy_proto
    from rths_hil.drivers.registry import available, register, unregister

    from rths_hil.linkbudget import link_load

    register(dataclasses.replace(toy_proto.PROTOCOL, name="toy2"))
    try:
        assert available()["toy2"] == "(registered)"
        ld = link_load("toy2", {"rate": 480_000}, 2, 500.0)  # 2 × 240 bits × 500 Hz / 480 kbit/s
        assert ld.load == pytest.approx(0.5) and ld.link == "toy 127.0.0.1:9000"
    finally:
        unregister("toy2")
    assert "toy2" not in available()
    assert link_load("toy2", {"rate": 480_000}, 2, 500.0).load is None  # unknown: not checked


# The built-in way: the same driver as the package ``rths_hil.drivers.toy`` (a folder under
# drivers/) with its profile format, and the same twin as the endpoint module
# ``rths_hil.sim_backends.endpoints.toy``, which declares itself.
_PROFILE_FORMAT = """
from dataclasses import dataclass

from rths_hil.drivers.profile import ProfileFormat, check_keys, top_keys
from rths_hil.keys import Key

FORMAT = "toy"  # the format is the package's name
FILE_KEYS = top_keys({"rate": Key("int", None, lo=1, doc="the toy line's rate")})


@dataclass(frozen=True)
class ToyProfile(ProfileFormat):
    source: str
    actions: dict
    rate: int | None
    protocol: str = FORMAT


def load(source, data, base):
    top = check_keys(source, data, FILE_KEYS, "")
    return ToyProfile(source, dict(top["actions"]), top["rate"])
"""

_BUILTIN_TWIN = _TWIN.replace(
    "from . import COMMAND, DN, FEEDBACK, UM",
    "from rths_hil.drivers.toy import COMMAND, DN, FEEDBACK, UM\n"
    "\nfrom ..registry import TwinEntry",
) + textwrap.dedent(
    """
    TWIN = TwinEntry("rths_hil.sim_backends.endpoints.toy:ToyTwin", seq_bits=None)
    """
)


@pytest.fixture
def builtin_toy(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """The toy added as a shipped protocol is: ``drivers/toy/`` (``__init__.py``: the driver
    and ``PROTOCOL``; ``profile_format.py``) and ``sim_backends/endpoints/toy.py`` (the twin
    and its ``TWIN``), their folders appended to the packages' ``__path__`` (no registry
    edited); the registries' caches cleared before and after."""
    import rths_hil.drivers as drivers
    import rths_hil.sim_backends.endpoints as endpoints
    from rths_hil.drivers import registry

    pkg = tmp_path / "drivers" / "toy"
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(textwrap.dedent(_DRIVER))
    (pkg / "profile_format.py").write_text(textwrap.dedent(_PROFILE_FORMAT))
    eps = tmp_path / "endpoints"
    eps.mkdir()
    (eps / "toy.py").write_text(textwrap.dedent(_BUILTIN_TWIN))
    monkeypatch.setattr(drivers, "__path__", [*drivers.__path__, str(pkg.parent)])
    monkeypatch.setattr(endpoints, "__path__", [*endpoints.__path__, str(eps)])
    importlib.invalidate_caches()
    registry.clear_cache()
    yield tmp_path
    monkeypatch.undo()
    for mod in ("rths_hil.drivers.toy", "rths_hil.drivers.toy.profile_format",
                "rths_hil.sim_backends.endpoints.toy"):  # fmt: skip
        sys.modules.pop(mod, None)
    registry.clear_cache()


def test_a_builtin_style_toy_is_found_without_a_registry_edit(builtin_toy: Path) -> None:
    """The registries find the toy's folder and its endpoint module beside the shipped ones."""
    from rths_hil.drivers.profile import protocol_key
    from rths_hil.drivers.registry import available, builtin, profile_formats, protocol
    from rths_hil.sim_backends.registry import available_twins, builtin_twins, twin_class

    assert list(builtin()) == ["can", "canopen", "modbus", "serial", "toy"]
    assert available()["toy"] == builtin()["toy"] == "rths_hil.drivers.toy:PROTOCOL"
    assert protocol("toy").driver.__module__ == "rths_hil.drivers.toy"
    assert builtin_twins()["toy"] == "rths_hil.sim_backends.endpoints.toy"
    assert available_twins()["toy"] == "rths_hil.sim_backends.endpoints.toy:TWIN"
    cls, entry = twin_class("toy")
    assert cls.__name__ == "ToyTwin" and entry.seq_bits is None
    assert profile_formats()["toy"] == "rths_hil.drivers.toy.profile_format:load"
    assert protocol_key().choices == ("can", "modbus", "toy")


def test_a_builtin_style_toy_runs_in_lockstep_against_its_twin(
    builtin_toy: Path, tmp_path: Path
) -> None:
    """``rths-hil run`` runs the toy found in its folder against the twin its endpoint module
    declares: the record is what that twin sent."""
    out = tmp_path / "run"
    args = ["run", "--lockstep", "--duration", "1", "--out", str(out), *QUIET]
    args += ["--set", "driver.name=toy", "--set", "driver.connection={rate=10000000}"]
    assert main(args) == 0
    twin = sys.modules["rths_hil.sim_backends.endpoints.toy"]
    _check_record(out, twin.SENT)


def test_a_builtin_style_toy_profile_format(builtin_toy: Path) -> None:
    """A profile of the toy's format is read by its package's ``profile_format``; a profile of
    no format names the toy's among the choices, in one line."""
    from rths_hil.drivers.profile import load_profile

    good = builtin_toy / "toy.toml"
    good.write_text('protocol = "toy"\nrate = 9600\n[roles]\n[status]\n[actions.estop]\ncoil = 1\n')
    prof = load_profile(good)
    assert type(prof).__name__ == "ToyProfile" and prof.protocol == "toy" and prof.rate == 9600
    bad = builtin_toy / "bad.toml"
    bad.write_text('protocol = "toi"\n')
    with pytest.raises(InputError) as exc:
        load_profile(bad)
    assert str(exc.value) == (
        f"profile {bad}: protocol: must be one of can, modbus, toy, got 'toi'"
    )


@pytest.mark.timing
def test_the_toy_twin_served_with_its_own_option(toy_package: Path) -> None:
    """``twin serve`` lists the option the toy's descriptor declares, and serves the toy's twin
    as its own process with it: the listen line carries the rate, the toy driver in this
    process steps the twin (a command answered with its sequence number)."""
    import json
    import os
    import signal
    import subprocess

    import toy_proto

    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(toy_package), str(ROOT)]))
    cmd = [sys.executable, "-m", "rths_hil", "twin", "serve", "--driver", "toy"]
    helped = subprocess.run([*cmd, "--help"], capture_output=True, text=True, env=env, cwd=ROOT)
    assert helped.returncode == 0, helped.stderr
    assert "toy options:" in helped.stdout and "--toy-rate" in helped.stdout
    proc = subprocess.Popen([*cmd, "--toy-rate", "250000"], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)  # fmt: skip
    try:
        line = proc.stdout.readline()
        assert "toy twin listening on toy udp 127.0.0.1:" in line, proc.stderr.read()
        conn = json.loads(line.split(" connection ", 1)[1])
        assert conn["rate"] == 250000 and conn["port"] > 0
        drv = toy_proto.ToyDriver(**conn)
        drv.open()
        try:
            drv.send(7, 0.0, enable=False)
            fb = drv.receive(5.0)
        finally:
            drv.close()
        assert fb is not None and fb.seq == 7
    finally:
        proc.send_signal(signal.SIGINT)
        rc = proc.wait(timeout=10)
    assert rc == 0, proc.stderr.read()
