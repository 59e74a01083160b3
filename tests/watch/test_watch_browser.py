"""``rths-hil watch`` in a real browser: headless Chromium (Debian ``chromium``) against real runs.

The page is driven over the DevTools protocol (:mod:`rths_hil.watch.browser`): the test reads
the Bokeh models of the page, takes screenshots and clicks with real mouse events. The runs are
paced (wall clock) at 256 Hz, slow enough to watch.
"""

from __future__ import annotations

import io
import json
import os
import queue
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from rths_hil.records.recorder import header_row_count, read_run
from rths_hil.watch.browser import Browser, chromium_path
from rths_hil.watch.source import RunFollower
from tests.helpers.watch_records import stability_value, write_run

# The live page follows a paced run: those tests run apart from the parallel tests, one at a
# time (the "timing" marker, pyproject.toml; make test). Replays of finished records and the
# page's messages run with the parallel tests.
timing = pytest.mark.timing

FS = 256
# the run must not stop for reasons this test does not inject (a loaded CI machine is late)
PACED = [
    "--paced",
    "--set", f"loop.fs={FS}",
    "--set", "compensation.alpha=7.4",  # 25 ms at 256 Hz
    "--set", "loop.console=0",
    "--set", "output.plot=false",
    "--set", "safety.max_overruns=1000000",
    "--set", "safety.watchdog_missed=1000000",
    "--set", "safety.fei_delay_tol=0",
    "--set", "safety.fei_amplitude_tol=0",
    "--set", "safety.kf_gain_min=-100",
    "--set", "safety.kf_gain_max=100",
]  # fmt: skip

# These tests must run wherever the suite runs (`make test` installs Chromium through
# scripts/system-deps.sh); a machine without it fails here with the reason.
if chromium_path() is None:  # pragma: no cover - only on a machine set up by hand
    raise RuntimeError("the browser tests need Chromium: run `bash scripts/system-deps.sh`")


@pytest.fixture(scope="module")
def browser():
    with Browser(width=1200, height=1500) as b:
        yield b


_LINES: dict[int, queue.Queue] = {}


def _follow_stderr(proc: subprocess.Popen) -> subprocess.Popen:
    """Collect the process's stderr lines in a queue (a thread; select() on a buffered pipe
    misses lines already read into the buffer)."""
    q: queue.Queue = queue.Queue()
    _LINES[proc.pid] = q
    lines: list[str] = []
    proc.stderr_lines = lines

    def pump() -> None:
        for line in proc.stderr:
            lines.append(line)
            q.put(line.rstrip("\n"))

    threading.Thread(target=pump, daemon=True).start()
    return proc


def _read_line(proc: subprocess.Popen, timeout: float = 60.0) -> str:
    try:
        return _LINES[proc.pid].get(timeout=timeout)
    except queue.Empty:
        raise AssertionError(f"no line from the process (exit code {proc.poll()})") from None


def _err(proc: subprocess.Popen) -> str:
    proc.wait()
    time.sleep(0.1)
    return "".join(proc.stderr_lines)


def _start_watch(run_dir: Path, *extra: str) -> tuple[subprocess.Popen, str]:
    proc = _follow_stderr(
        subprocess.Popen(
            [sys.executable, "-m", "rths_hil", "watch", str(run_dir), "--port", "0", *extra],
            stderr=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            text=True,
        )
    )
    line = _read_line(proc)
    m = re.search(r"(http://\S+)", line)
    assert m, line
    return proc, m.group(1)


def _stop(proc: subprocess.Popen) -> str:
    proc.terminate()
    try:
        proc.wait(10)
    except subprocess.TimeoutExpired:
        proc.kill()
    return _err(proc)


def _open(browser: Browser, url: str) -> None:
    browser.goto(url)
    browser.wait_for(
        "!!(window.Bokeh && Bokeh.documents.length && "
        "(Bokeh.documents[0].get_model_by_name('state') || "
        "Bokeh.documents[0].get_model_by_name('forbidden')))",
        timeout=60,
    )


def _state(browser: Browser) -> str:
    return re.sub("<[^>]+>", "", browser.model("state", "text") or "")


def _wait_state(browser: Browser, needle: str, timeout: float = 60.0) -> str:
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        s = _state(browser)
        if needle in s:
            return s
        time.sleep(0.1)
    raise AssertionError(f"page state never showed {needle!r}: {_state(browser)!r}")


def _last_t(browser: Browser, source: str = "window") -> float:
    t = browser.column(source, "t") or []
    return float(t[-1]) if t else float("nan")


def _pixels(png: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"), dtype=np.int16)


def _wall_t0(run_dir: Path) -> float:
    for line in (run_dir / "events.jsonl").read_text().splitlines():
        e = json.loads(line)
        if e["kind"] == "clock":
            return float(e["wall_t0"])
    raise AssertionError("no clock event")


def _growing_record(run_dir: Path) -> np.ndarray:
    """The rows of a record still being written (read as the watcher reads it: up to the
    header's count, which never counts a row not on disk; ``read_run`` is for a whole file)."""
    f = RunFollower(run_dir)
    f.poll()
    assert f.record is not None
    return np.array(f.record[: f.rows])


def _sent_at(run_dir: Path, t: float) -> float:
    """Wall-clock time at which the row of loop time ``t`` was sent."""
    rec = _growing_record(run_dir)
    k = round(t * FS)
    return _wall_t0(run_dir) + t + float(rec["lateness"][k])


def _local_only(requests: list[str], url: str) -> None:
    host = url.split("/")[2]
    for r in requests:
        assert r.startswith((f"http://{host}/", f"ws://{host}/", "data:", "about:")), r


WD_TIMEOUT = 2.0  # s: the wall-clock watchdog of the live runs (generous on a loaded machine)
S_WINDOW = 0.5  # s: the stability indicator's window in the live run (S valid from 1.5 s)

#: ``loop.cpu`` of the shared live run: the last CPU (the CI machines have two or more).
LOOP_CPU = max(os.sched_getaffinity(0))

_RENDERED_Y = (
    "(() => { const m = Bokeh.documents[0].get_model_by_name(%s);"
    " return m.renderers.filter(r => r.glyph && r.glyph.y && r.glyph.y.field)"
    ".map(r => r.glyph.y.field); })()"
)
_BANDS = (
    "(() => { const m = Bokeh.documents[0].get_model_by_name(%s);"
    " return m.center.filter(a => a.bottom !== undefined && a.top !== undefined"
    " && a.bottom !== null && typeof a.bottom === 'number').map(a => [a.bottom, a.top]); })()"
)
_S_SPANS = (
    "(() => { const m = Bokeh.documents[0].get_model_by_name(%s);"
    " return m.center.filter(a => a.location !== undefined && a.dimension === 'width')"
    ".map(a => [a.name, a.location]); })()"
)


def _open_once(browser: Browser, url: str) -> None:
    """Open ``url`` unless the page already shows it (tests sharing a page)."""
    if browser.eval("location.href") != url:
        _open(browser, url)


def _wait_t(browser: Browser, t: float, source: str = "window", timeout: float = 30.0) -> float:
    """Wait until the page's 10 s window reaches loop time ``t``; return its last time."""
    t_end = time.monotonic() + timeout
    while not _last_t(browser, source) >= t and time.monotonic() < t_end:  # NaN: no rows yet
        time.sleep(0.05)
    return _last_t(browser, source)


def _columns(browser: Browser, source: str, *cols: str) -> list[list]:
    """Columns of the ColumnDataSource ``source``, read at once (a refresh may stream rows
    onto a source, or replace it, between two reads)."""
    return browser.eval(
        f"(() => {{ const m = Bokeh.documents[0].get_model_by_name({json.dumps(source)});"
        " const c = k => Array.from((m && (m.data.get ? m.data.get(k) : m.data[k])) || []);"
        f" return {json.dumps(list(cols))}.map(c); }})()"
    )


def _s_shown(browser: Browser, ch: str = "") -> tuple[np.ndarray, np.ndarray]:
    """Time and S of the stability plot's rows in the page (NaN where S is not valid)."""
    t, s = _columns(browser, "fei" + (f"_{ch}" if ch else ""), "t", "s")
    return np.array(t, dtype=float), np.array([np.nan if v is None else v for v in s], float)


def _check_s_plot(browser: Browser, cfg: dict, ch: str = "") -> None:
    """The stability plot draws the ``s`` column, with the rule's warning and limit as lines."""
    sfx = f"_{ch}" if ch else ""
    assert browser.eval(_RENDERED_Y % json.dumps(f"stability{sfx}")) == ["s"]
    levels = dict(browser.eval(_S_SPANS % json.dumps(f"stability{sfx}")))
    safety = cfg["safety"]
    assert levels == {
        f"s_warn{sfx}": pytest.approx(safety["stability_warn"]),
        f"s_limit{sfx}": pytest.approx(safety["stability_limit"]),
    }, levels


@pytest.fixture(scope="module")
def live_run(tmp_path_factory):
    """One paced ``rths-hil run --watch`` (60 s, the loop on :data:`LOOP_CPU`), shared by the
    tests of the live page; ended by the stop-button test (or killed at the end)."""
    run_dir = tmp_path_factory.mktemp("live") / "run"
    run = _follow_stderr(subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "run", *PACED, "--duration", "60", "--out",
         str(run_dir), "-q", "--watch", "--watch-port", "0", "--set", f"loop.cpu={LOOP_CPU}",
         "--set", f"safety.watchdog_timeout={WD_TIMEOUT}",
         "--set", f"safety.stability_window={S_WINDOW}"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
    ))  # fmt: skip
    try:
        line = _read_line(run)
        m = re.search(r"live view at (http://\S+)", line)
        assert m, line
        yield run, m.group(1), run_dir
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()


@timing
def test_live_paced_run_plots_and_stability_move(browser, live_run, tmp_path):
    _, url, run_dir = live_run
    n_req = len(browser.requests)
    _open_once(browser, url)
    _wait_state(browser, "RUNNING")
    # S is valid from 1.5 s (a window of 0.5 s, once the structure has moved for a window)
    t1 = _wait_t(browser, 1.8)
    title = browser.model("title", "text")
    assert ">Actuator<" in title  # one unnamed actuator, not the driver's name
    assert "displacement control · tracked: displacement (mm)" in title
    cfg = json.loads((run_dir / "meta.json").read_text())["config"]
    _check_s_plot(browser, cfg)
    shot1, t1 = browser.screenshot(tmp_path / "live1.png"), _last_t(browser)
    lag = time.time() - _sent_at(run_dir, t1)
    ts1, s1 = _s_shown(browser)
    t2 = _wait_t(browser, t1 + 1.0)
    assert t2 > t1 + 0.8, (t1, t2)
    # the plots moved: the displacement plots (top of the page) differ in many pixels (a
    # loaded browser paints a moment after its data changed: a few more screenshots)
    top = slice(140, 560)
    t_end = time.monotonic() + 5
    while True:
        shot2 = browser.screenshot(tmp_path / "live2.png")
        a, b = _pixels(shot1), _pixels(shot2)
        changed = (np.abs(a[top] - b[top]).sum(axis=2) > 30).mean()
        if changed > 0.01 or time.monotonic() > t_end:
            break
        time.sleep(0.3)
    assert changed > 0.01, changed
    # the page shows rows sent a moment ago (its refresh rate and lag are measured by
    # benchmarks/bench_watch.py: timing is not a unit test on a shared machine)
    assert lag > 0
    # the S plot moved on with the loop, and shows the record's S at each of its times
    t_end = time.monotonic() + 10
    while (ts2 := _s_shown(browser)[0]).size and ts2[-1] < ts1[-1] + 0.8:
        assert time.monotonic() < t_end, (ts1[-1], ts2[-1])
        time.sleep(0.05)
    ts2, s2 = _s_shown(browser)
    valid = ts2[np.isfinite(s2)]
    assert valid.size and valid[-1] >= ts1[-1] + 0.8, (ts1[-1], valid[-1:])
    rec = _growing_record(run_dir)
    for ts, s in ((ts1, s1), (ts2, s2)):
        k = np.round(ts * FS).astype(int)
        np.testing.assert_array_equal(s, rec["stability"][k])
    # the limit bars: the wall-clock feedback watchdog at least one period between replies (a
    # reply per step) and well under the timeout; S as a share of its limit (1.5), its peak
    # at least that of the S shown first and at most that of the whole record
    t_end = time.monotonic() + 10
    while "stability S" not in (
        bars := dict(zip(*_columns(browser, "bars", "limit", "peak"), strict=True))
    ):
        assert time.monotonic() < t_end, bars
        time.sleep(0.1)
    assert 0.99 / FS / WD_TIMEOUT <= bars["feedback watchdog"] < 1.0, bars
    s_all = _growing_record(run_dir)["stability"]
    lo, hi = np.nanmax(np.maximum(s1, 0.0)) / 1.5, np.nanmax(np.maximum(s_all, 0.0)) / 1.5
    assert lo - 1e-12 <= bars["stability S"] <= hi + 1e-12, (lo, bars, hi)
    # everything the page loaded came from the watcher itself (no CDN)
    _local_only(browser.requests[n_req:], url)
    assert any("/static/js/bokeh" in r for r in browser.requests)


def _child_with(pid: int, word: str) -> int:
    """The pid of the child process of ``pid`` whose command line contains ``word``."""
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            cmd = (d / "cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        if ppid == pid and word.encode() in cmd:
            return int(d.name)
    raise AssertionError(f"no child of {pid} runs {word!r}")


@timing
def test_stop_button_ends_a_paced_run_with_exit_130_and_a_complete_record(browser, live_run):
    run, url, run_dir = live_run
    _open_once(browser, url)
    _wait_state(browser, "RUNNING")
    # the loop runs on its CPU; the live view at nice 10, on the other CPUs
    assert os.sched_getaffinity(run.pid) == {LOOP_CPU}
    watcher = _child_with(run.pid, "watch")
    assert os.getpriority(os.PRIO_PROCESS, watcher) == max(10, os.getpriority(os.PRIO_PROCESS, 0))
    assert LOOP_CPU not in os.sched_getaffinity(watcher)
    assert os.sched_getaffinity(watcher) == set(range(os.cpu_count())) - {LOOP_CPU}
    # the confirmation comes first; cancelling it sends nothing
    browser.click_button("Operator stop…")
    browser.click_button("Cancel")
    time.sleep(0.3)
    assert run.poll() is None
    browser.click_button("Operator stop…")
    browser.click_button("Yes, stop the run")
    code = run.wait(30)
    err = _err(run)
    assert code == 130, err
    assert "operator stop" in err and "Traceback" not in err
    data = read_run(run_dir)
    end = data.events[-1]
    assert end["kind"] == "end" and end["status"] == "operator_stop"
    stop = next(e for e in data.events if e["kind"] == "operator_stop")
    assert stop["signal"] == "SIGINT"
    # complete: every step up to the stop is in the record, flushed, in order
    n = end["step"]
    assert header_row_count(run_dir / "record.npy") == len(data.record) == n > FS
    np.testing.assert_array_equal(data.record["step"], np.arange(n))


@timing
def test_nan_from_the_sensor_turns_the_banner_into_the_e_stop(browser, tmp_path):
    run_dir = tmp_path / "run"
    fault_step = FS  # NaN from the sensor at t = 1 s: the nan rule trips
    # the watcher and the run start together (the page's wait for a run directory that does
    # not exist yet is test_missing_empty_and_unreadable_run_directories_are_messages)
    run = _follow_stderr(subprocess.Popen(
        [sys.executable, "-m", "rths_hil", "run", *PACED, "--duration", "20", "--out",
         str(run_dir), "-q", "--set", f"twin.faults=nan={fault_step}",
         "--set", f"safety.watchdog_timeout={WD_TIMEOUT}"],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True,
    ))  # fmt: skip
    watch, url = _start_watch(run_dir)
    try:
        _open(browser, url)
        # the e-stop: the banner names the rule, the time and the step (from the trip event, while
        # the run still shuts down), and the run exits with 3
        state = _wait_state(browser, "E-STOP", timeout=60)
        assert "nan" in state and f"step {fault_step}" in state and "t = 1.000 s" in state
        assert state.lower().count("e-stop") == 1, state  # not "E-STOP — e-stop: …"
        browser.screenshot(tmp_path / "estop.png")
        t_end = time.monotonic() + 30
        while (events := browser.column("events", "kind") or [])[-1:] != ["end"]:
            assert time.monotonic() < t_end, events
            time.sleep(0.1)
        assert events[-3:] == ["trip", "estop", "end"], events
        assert run.wait(30) == 3, _err(run)
    finally:
        if run.poll() is None:
            run.kill()
            run.wait()
        err = _stop(watch)
    assert "Traceback" not in err


@pytest.fixture(scope="module")
def two_channel(tmp_path_factory):
    """A watcher on a killed two-channel record of 16 s (no end event), shared by the replay
    tests, on another address than the default (127.0.0.2, a loopback address but not the
    default one): its pages need the token."""
    mp = pytest.MonkeyPatch()
    try:
        run_dir = write_run(tmp_path_factory.mktemp("two") / "two", mp, ["left", "right"],
                            seconds=16, end=None)  # fmt: skip
    finally:
        mp.undo()
    # the channel "right" is force-controlled (its tracked quantity is its measured force)
    meta = json.loads((run_dir / "meta.json").read_text())
    meta["channels"] = [{"name": "left", "control": "displacement"}, {"name": "right"}]
    meta["config"]["actuators"] = [{"name": "right", "control": {"mode": "force"}}]
    (run_dir / "meta.json").write_text(json.dumps(meta))
    watch, url = _start_watch(run_dir, "--host", "127.0.0.2")
    try:
        yield run_dir, url, watch
    finally:
        err = _stop(watch)
        assert "Traceback" not in err


def test_replay_of_a_multi_channel_record_with_the_slider(browser, two_channel):
    _, url, _ = two_channel
    _open_once(browser, url)
    assert "KILLED" in _wait_state(browser, "KILLED")
    left, right = browser.model("title_left", "text"), browser.model("title_right", "text")
    assert "Actuator left" in left and "displacement control" in left and "(mm)" in left
    assert "Actuator right" in right and "force control" in right and "force (kN)" in right
    browser.click_button("follow the end")
    assert _wait_t(browser, 16 - 1 / 256 - 0.05, "window_left") == pytest.approx(
        16 - 1 / 256, abs=0.05
    )
    # each channel's tracked quantity is what was written: the measured displacement of
    # "left" (amplitude 4 mm) in mm, the measured force of the force channel "right"
    # (2e5 N/m · 2 mm = 0.4 kN) in kN, its target in kN too
    for ch, amp in (("left", 4.0), ("right", 0.4)):
        m = np.array(browser.column(f"window_{ch}", "measured"), dtype=float)
        assert np.nanmax(np.abs(m)) == pytest.approx(amp, rel=0.01)
    x = np.array(browser.column("window_right", "target"), dtype=float)
    assert np.nanmax(np.abs(x)) == pytest.approx(0.002e-3, rel=0.01)
    # replay: move the slider back to 12 s; the window and the S plot follow it
    browser.eval("Bokeh.documents[0].get_model_by_name('slider').value = 12.0")
    t_end = time.monotonic() + 10
    while time.monotonic() < t_end and not (
        abs(_last_t(browser, "window_left") - 12.0) <= 0.1
        and abs(_last_t(browser, "fei_right") - 12.0) <= 0.1
        and "replay" in (browser.model("info", "text") or "")
    ):
        time.sleep(0.05)
    t = np.array(browser.column("window_left", "t"))
    assert t[-1] == pytest.approx(12.0, abs=0.1) and t[0] == pytest.approx(2.0, abs=0.1)
    info = re.sub("<[^>]+>", "", browser.model("info", "text"))
    assert "replay: window ends at 12.00 s" in info
    # each channel's S plot shows that channel's S at its times, over the replayed window
    for ch in ("left", "right"):
        ts, s = _s_shown(browser, ch)
        assert ts[-1] == pytest.approx(12.0, abs=0.1) and ts[0] == pytest.approx(2.0, abs=0.1)
        np.testing.assert_allclose(s, [stability_value(x, ch) for x in ts], rtol=1e-12)
    # no stop button for a run nobody is writing
    assert browser.model("stop", "visible") is False


def test_kalman_and_stability_have_their_own_plots_and_bands(browser, two_channel):
    """The Kalman delay (measured vs command, ≈ the actuator's lag) is not drawn over the FEI
    delay's ±tolerance band: it has its own plot against ``safety.kf_delay_max``; S has its
    own plot with the rule's levels; the displacements are in mm and the force in kN."""
    run_dir, url, _ = two_channel
    _open_once(browser, url)
    _wait_state(browser, "KILLED")
    t_end = time.monotonic() + 20
    while not browser.column("loop_left", "force") and time.monotonic() < t_end:
        time.sleep(0.1)
    cfg = json.loads((run_dir / "meta.json").read_text())["config"]
    fei_d = browser.eval(_RENDERED_Y % json.dumps("fei_d_left"))
    kalman = browser.eval(_RENDERED_Y % json.dumps("kalman_left"))
    assert "d" in fei_d and "kf_d" not in fei_d and "s" not in fei_d, fei_d
    assert "kf_d" in kalman and "kf_g" in kalman, kalman
    for ch in ("left", "right"):
        _check_s_plot(browser, cfg, ch)
    bands_d = browser.eval(_BANDS % json.dumps("fei_d_left"))
    bands_k = browser.eval(_BANDS % json.dumps("kalman_left"))
    tol, kmax = cfg["safety"]["fei_delay_tol"] * 1e3, cfg["safety"]["kf_delay_max"] * 1e3
    assert bands_d == [[pytest.approx(-tol), pytest.approx(tol)]], bands_d
    assert bands_k == [[pytest.approx(-kmax), pytest.approx(kmax)]], bands_k
    # mm and kN: the written amplitudes are 4 mm and 2e5 N/m · 4 mm = 0.8 kN
    m = np.array(browser.column("window_left", "measured"), dtype=float)
    f = np.array(browser.column("loop_left", "force"), dtype=float)
    assert np.nanmax(np.abs(m)) == pytest.approx(4.0, rel=0.01)
    assert np.nanmax(np.abs(f)) == pytest.approx(0.8, rel=0.01)


def test_other_address_needs_the_token(browser, two_channel):
    _, url, watch = two_channel
    assert "?token=" in url
    _open(browser, url.split("?")[0])
    assert browser.model("forbidden", "text") and browser.model("state", "text") is None
    _open(browser, url.split("?")[0] + "?token=wrong")
    assert browser.model("forbidden", "text")
    _open(browser, url)
    assert "KILLED" in _wait_state(browser, "KILLED")
    assert "warning: listening on 127.0.0.2" in "".join(watch.stderr_lines)


def test_missing_empty_and_unreadable_run_directories_are_messages(browser, tmp_path):
    empty = tmp_path / "empty"
    watch, url = _start_watch(empty)
    try:
        # missing directory: one clear line in the terminal and on the page, no traceback
        line = _read_line(watch)
        assert "does not exist (yet): waiting" in line, line
        _open(browser, url)
        assert "WAITING" in _wait_state(browser, "does not exist")
        empty.mkdir()
        assert "has no run record (record.npy) yet" in _read_line(watch)
        _wait_state(browser, "has no run record")
        (empty / "record.npy").write_bytes(b"garbage, not a record")
        assert "UNREADABLE" in _wait_state(browser, "unreadable record")
    finally:
        err = _stop(watch)
    assert "Traceback" not in err
