"""DBC files and profile paths that cannot be what they claim: one line, exit 2, at load, for
``run`` and for ``twin serve`` alike — never a hang on a device, a minutes-long parse, a
traceback on a symlink loop, or a garbage file's control bytes on the operator's terminal."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import pytest
from rths_hil.drivers.can.codec import MAX_DBC_BYTES, load_dbc

from rths_hil.errors import InputError
from tests.helpers.cli import one_line_exit_2

EXAMPLES = Path(__file__).resolve().parents[2] / "examples" / "controllers"


@pytest.fixture()
def lab(tmp_path):
    """A copy of the DBC profile example whose ``dbc`` key each test points elsewhere."""
    for name in ("can_dbc.toml", "can_dbc_run.toml", "lab_axis.dbc"):
        shutil.copy(EXAMPLES / name, tmp_path / name)
    return tmp_path


def _point(lab: Path, dbc: str) -> Path:
    prof = lab / "can_dbc.toml"
    lines = [
        f'dbc = "{dbc}"' if ln.startswith("dbc = ") else ln for ln in prof.read_text().splitlines()
    ]
    prof.write_text("\n".join(lines) + "\n")
    return prof


def _both(lab, capsys, *needles):
    """``run`` and ``twin serve`` refuse the profile with the same one line."""
    run = ["run", str(lab / "can_dbc_run.toml"), "--lockstep", "--duration", "0.1"]
    one_line_exit_2(run, capsys, *needles)
    serve = ["twin", "serve", "--driver", "can", "--profile", str(lab / "can_dbc.toml")]
    one_line_exit_2(serve, capsys, *needles)


def test_the_example_dbc_loads(lab):
    db = load_dbc(lab / "lab_axis.dbc")
    assert db.messages


def test_a_device_is_refused_before_it_is_read(lab, capsys):
    _point(lab, "/dev/zero")
    t0 = time.monotonic()
    _both(lab, capsys, "/dev/zero: a DBC must be a regular file, this is a device")
    assert time.monotonic() - t0 < 30  # /dev/zero read for ever before


def test_a_directory_and_a_symlink_loop_are_refused(lab, capsys):
    (lab / "adir.dbc").mkdir()
    _point(lab, "adir.dbc")
    _both(lab, capsys, "adir.dbc: a DBC must be a regular file, this is a directory")
    (lab / "loop.dbc").symlink_to("loop.dbc")
    _point(lab, "loop.dbc")
    _both(lab, capsys, "cannot load DBC", "loop.dbc: Too many levels of symbolic links")


def test_an_oversized_dbc_is_refused_before_it_is_parsed(lab, capsys):
    big = lab / "big.dbc"
    big.write_text('VERSION ""\n' + " " * MAX_DBC_BYTES)
    _point(lab, "big.dbc")
    _both(lab, capsys, f"is larger than the {MAX_DBC_BYTES} bytes accepted")


def test_a_signal_past_its_message_names_the_file_and_the_message(lab, capsys):
    (lab / "len.dbc").write_text(
        'VERSION ""\nBO_ 256 Cmd: 2 Vector__XXX\n SG_ Pos : 0|32@1- (1,0) [0|0] "m" Vector__XXX\n'
    )
    _point(lab, "len.dbc")
    _both(lab, capsys, "len.dbc", "The signal Pos does not fit in message Cmd")


def test_garbage_is_shown_escaped(lab, capsys):
    (lab / "garbage.dbc").write_bytes(b"\x01\x02garbage\x1b[31m red\x07\n")
    _point(lab, "garbage.dbc")
    run = ["run", str(lab / "can_dbc_run.toml"), "--lockstep", "--duration", "0.1"]
    err = one_line_exit_2(run, capsys, "garbage.dbc", "Invalid syntax")
    assert not any(ord(c) < 32 for c in err)  # no raw control byte reaches the terminal
    assert "\\x1b" in err


def test_a_profile_path_in_a_symlink_loop(lab, capsys):
    (lab / "ploop.toml").symlink_to("ploop.toml")
    run_cfg = lab / "can_dbc_run.toml"
    run_cfg.write_text(run_cfg.read_text().replace('"can_dbc.toml"', '"ploop.toml"'))
    one_line_exit_2(
        ["run", str(run_cfg), "--lockstep", "--duration", "0.1"], capsys,
        "ploop.toml: cannot be resolved",
    )  # fmt: skip
    one_line_exit_2(
        ["twin", "serve", "--driver", "can", "--profile", str(lab / "ploop.toml")], capsys,
        "--profile", "cannot be resolved",
    )  # fmt: skip
    with pytest.raises(InputError):
        load_dbc(lab / "ploop.toml")


# ----------------------------------------------------------------------------------------------
# DBC contents a profile cannot work with


def _edit_dbc(lab: Path, old: str, new: str) -> None:
    dbc = lab / "lab_axis.dbc"
    text = dbc.read_text()
    assert old in text
    dbc.write_text(text.replace(old, new, 1))


def test_a_dbc_unit_the_bridge_does_not_convert(lab, capsys):
    _edit_dbc(lab, '[-200000|200000] "mm" Axis', '[-200000|200000] "furlong" Axis')
    _both(lab, capsys, "roles.setpoint.signal", "the unit 'furlong'", "give its units")


def test_a_dbc_in_centimetres_is_converted_not_taken_as_metres(lab):
    from rths_hil.drivers.profile import load_profile

    mm = load_profile(lab / "can_dbc.toml").roles["setpoint"].factor
    _edit_dbc(lab, '[-200000|200000] "mm" Axis', '[-200000|200000] "cm" Axis')
    prof = lab / "can_dbc.toml"
    prof.write_text(prof.read_text() + "\n")  # a new path for the profile cache
    cm = load_profile(prof.rename(lab / "cm.toml")).roles["setpoint"].factor
    assert mm == pytest.approx(1e-3) and cm == pytest.approx(1e-2)


def test_two_messages_on_one_frame_id(lab, capsys):
    _edit_dbc(lab, "BO_ 1793 BridgeAlive", "BO_ 32 BridgeAlive")
    _both(lab, capsys, "messages AxisEStop and BridgeAlive share the frame id 0x20")


def test_a_heartbeat_on_the_estop_message(lab, capsys):
    prof = lab / "can_dbc.toml"
    text = prof.read_text()
    old = '[heartbeat]\nmessage = "BridgeAlive"\nsignal = "AliveCounter"'
    assert old in text
    prof.write_text(text.replace(old, '[heartbeat]\nmessage = "AxisEStop"\nsignal = "EStopCode"'))
    _both(lab, capsys, "heartbeat.message: AxisEStop is the e-stop's message")
