"""``rths-hil run``: run a real-time hybrid simulation through a driver (and its twin).

``rths-hil run [CONFIG.toml] [--lockstep] [--duration S] [--out DIR] [--set key=value]...
[--watch]``

Without a configuration it runs the embedded default (the FEI paper's NEES-711 setup over the CAN
driver on python-can's virtual bus to an in-process twin, paced at 1024 Hz for 30 s). Prints a
live status line, then the summary; writes the run directory (record, events, metadata,
``summary.json``, ``report.png``). Exit codes: 0 completed, 2 bad input, 3 safety trip (e-stop
sent; one line on stderr names the rule), 130 operator stop (Ctrl-C, SIGTERM or SIGHUP: the
actuators hold, then the controllers are disabled). A channel without a twin is real hardware:
the run needs ``--confirm-hardware`` (or ``loop.confirm_hardware = true``) and is refused in
lockstep unless ``driver.stepped`` says the controller advances one step per command.
``--watch`` also starts ``rths-hil watch`` on the run directory (the live view in the browser,
a separate process that reads the record) and prints its URL.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from ..config import to_toml
from ..units import parse_time
from .options import (
    add_command,
    add_config_arguments,
    add_confirm_hardware,
    add_out_dir,
    config_from_args,
    out_dir,
)


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``run`` to the top-level parser."""
    p = add_command(
        sub,
        "run",
        __doc__,
        main,
        help="run an RTHS test through a driver (default: NEES-711 setup on a CAN twin)",
    )
    add_config_arguments(p, "loop.fs=2048")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="virtual time: as fast as the actuator answers (default: loop.mode)",
    )
    p.add_argument("--paced", action="store_true", help="wall-clock pacing (default: loop.mode)")
    p.add_argument(
        "--duration", metavar="S", help="simulated time to run, e.g. 10 or 10s (0 = whole record)"
    )
    add_out_dir(p, "run", "output.dir")
    p.add_argument(
        "--show-config",
        action="store_true",
        help="print the resolved configuration as TOML and exit",
    )
    p.add_argument("--no-plot", action="store_true", help="do not write report.png")
    p.add_argument("-q", "--quiet", action="store_true", help="no live line, no summary")
    p.add_argument(
        "--watch",
        action="store_true",
        help="also start `rths-hil watch` on the run (live view in the browser; prints the URL)",
    )
    p.add_argument(
        "--watch-port", type=int, default=8050, metavar="PORT", help="port of --watch (8050)"
    )
    add_confirm_hardware(p, "the run")


class _Console:
    """A console stream that a closed terminal cannot break: once a write or flush fails (the
    terminal or the pipe went away: EIO, EPIPE), the rest is dropped and the test goes on —
    the record, the events and ``summary.json`` are where nothing is lost."""

    def __init__(self, stream) -> None:
        self._stream = stream
        self.gone = False

    def write(self, text: str) -> int:
        if not self.gone:
            try:
                return self._stream.write(text)
            except (OSError, ValueError):
                self.gone = True
        return len(text)

    def flush(self) -> None:
        if not self.gone:
            try:
                self._stream.flush()
            except (OSError, ValueError):
                self.gone = True

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def _tolerant_console() -> None:
    """Make stdout, stderr and the log handlers on them survive a closed terminal."""
    import logging

    for name in ("stdout", "stderr"):
        old = getattr(sys, name)
        if old is None or isinstance(old, _Console):
            continue
        new = _Console(old)
        setattr(sys, name, new)
        for h in logging.getLogger().handlers:
            if isinstance(h, logging.StreamHandler) and h.stream is old:
                h.setStream(new)


def _mode_and_duration(args: argparse.Namespace) -> tuple[str | None, float | None]:
    """The loop mode (``--lockstep``, ``--paced`` or the configuration's) and ``--duration``."""
    from ..errors import InputError

    if args.lockstep and args.paced:
        raise InputError("--lockstep and --paced exclude each other")
    mode = "lockstep" if args.lockstep else "paced" if args.paced else None
    duration = None
    if args.duration is not None:
        duration = parse_time(args.duration, "--duration")
        if duration < 0:
            raise InputError(f"--duration must be >= 0 s, got {args.duration!r}")
    return mode, duration


def _announce(loop: Any, run_dir: Path, site: bool) -> None:
    """The run's first lines on stderr: mode, span, rate, drivers, record, link budget."""
    from ..linkbudget import format_loads

    span = f"{loop.n_steps / loop.fs:.1f} s"
    drivers = ", ".join(dict.fromkeys(ch.driver_name for ch in loop.plan.channels))
    if site:
        span = f"until the client ends (at most {span})"
    twin = " + twin" if loop.twin_enabled else ""
    print(
        f"rths-hil run: {loop.mode} {span} at {loop.fs:g} Hz, "
        f"driver{'s' if ', ' in drivers else ''} {drivers}{twin}, record in {run_dir}",
        file=sys.stderr,
    )
    for line in format_loads(loop.plan.links).splitlines():  # the link budget
        print(f"rths-hil run: {line}", file=sys.stderr)
    if loop.mode == "paced":
        _host_line()


def main(args: argparse.Namespace) -> int:
    """Run the test; return the exit code."""
    from ..hybrid import RTHSLoop
    from ..hybrid.phases import preflight, require_confirmation
    from ..report import LiveLine, format_summary, plot_report, summarize
    from ..stopping import OperatorStop

    cfg = config_from_args(args)
    if args.show_config:
        sys.stdout.write(to_toml(cfg))
        return 0
    mode, duration = _mode_and_duration(args)
    if args.watch:
        from ..errors import require

        require("live", "rths-hil run --watch")
    run_dir = out_dir(args, empty=False, pattern=cfg["output"]["dir"])
    _tolerant_console()  # from here on hardware may move: a closed terminal must not stop it
    live = None if args.quiet or cfg["loop"]["console"] <= 0 else LiveLine(sys.stderr)
    loop = RTHSLoop(cfg, run_dir, live=live, mode=mode, duration=duration)
    require_confirmation(loop.plan, args.confirm_hardware, "run")
    preflight(loop.plan)
    watcher = None
    if args.watch:
        watcher = _start_watcher(run_dir, args.watch_port, cfg["loop"]["cpu"])
    site: Any = loop.structure if hasattr(loop.structure, "paste_lines") else None
    if not args.quiet:
        _announce(loop, run_dir, site is not None)
    if site is not None:  # structure.kind = "openfresco": listen, say what to paste, then wait
        host, port = site.listen()
        py, tcl = site.paste_lines()
        o = cfg["openfresco"]
        print(
            f"rths-hil run: experimental site ({o['protocol']}, {o['timing']}) listening on "
            f"{host}:{port}; in OpenSees:\n  OpenSeesPy: {py}\n  Tcl:        {tcl}",
            file=sys.stderr,
            flush=True,
        )
    try:
        result = loop.run()
    finally:
        if live is not None:
            live.finish()
        if watcher is not None:
            _stop_watcher(watcher, run_dir)
    del loop  # the run's arrays (ground motion, lateness) are not needed for the summary
    result.lateness = result.ready = None  # type: ignore[assignment]
    # the controllers are handed back: a stop signal now lets the summary and the report be
    # written (they are the test's result), then the command exits 130
    try:
        with OperatorStop() as stop:
            summary = summarize(run_dir)
            if cfg["output"]["plot"] and not args.no_plot and result.steps > 1:
                plot_report(run_dir, summary=summary)
    except OSError as exc:  # e.g. the disk filled up: the record and events are what is kept
        summary = None
        print(
            f"rths-hil run: cannot write the summary or report in {run_dir}: {exc.strerror or exc}",
            file=sys.stderr,
        )
    if not args.quiet and summary is not None:
        print(format_summary(summary))
    if result.status == "trip" and result.trip is not None:
        t = result.trip
        print(
            f"rths-hil run: e-stop: {t.rule}: {t.reason} at t = {t.time:.4f} s (step {t.step}); "
            f"record in {run_dir}",
            file=sys.stderr,
        )
    elif result.status == "operator_stop":
        print(
            f"rths-hil run: operator stop at t = {result.steps / result.fs:.3f} s; record in "
            f"{run_dir}",
            file=sys.stderr,
        )
    if stop.signal is not None and result.exit_code == 0:
        print(
            f"rths-hil run: {stop.signal} while the summary and report were written; both are "
            f"in {run_dir}",
            file=sys.stderr,
        )
        return 130
    return result.exit_code


def _host_line() -> None:
    """The last ``rths-hil check-host`` verdict, when this computer has one."""
    import time

    from ..checkhost import cached_verdict

    v = cached_verdict()
    if v and isinstance(v.get("line"), str):
        when = time.strftime("%Y-%m-%d %H:%M", time.localtime(float(v.get("time", 0))))
        print(f"rths-hil run: {v['line']} (rths-hil check-host, {when})", file=sys.stderr)


def _keep_off(loop_cpu: int) -> None:
    """In the watcher's process before it starts: when the loop is pinned to a CPU
    (``loop.cpu``), keep the watcher (and the threads it starts) on the other CPUs."""
    import os

    others = set(os.sched_getaffinity(0)) - {loop_cpu}
    if loop_cpu >= 0 and others:
        os.sched_setaffinity(0, others)


def _start_watcher(run_dir: Path, port: int, loop_cpu: int = -1):
    """Start ``rths-hil watch RUN_DIR`` beside the run; wait until it listens (≤ 15 s).

    The watcher is its own process in its own session (Ctrl-C in this terminal stops the run,
    not the view), off the loop's CPU when ``loop.cpu`` pins it (:func:`_keep_off`; the
    watcher lowers its own priority to nice 10); it prints its URL itself. If it cannot start
    (port in use), it says why and the run goes on without it.
    """
    import functools
    import os
    import socket
    import subprocess
    import time

    if port == 0:  # any free port: choose it here, to know where to wait for the watcher
        from ..watch.server import _free_port

        port = _free_port("127.0.0.1")
    cmd = [
        sys.executable,
        "-m",
        "rths_hil",
        "watch",
        str(run_dir),
        "--port",
        str(port),
        "--quiet",
        "--parent",
        str(os.getpid()),
    ]
    proc = subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        start_new_session=True,
        preexec_fn=functools.partial(_keep_off, int(loop_cpu)),
    )
    t_end = time.monotonic() + 15.0
    while time.monotonic() < t_end and proc.poll() is None:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                return proc
        except OSError:
            time.sleep(0.1)
    if proc.poll() is None:
        print("rths-hil run: the live view is slow to start; going on", file=sys.stderr)
        return proc
    print("rths-hil run: no live view (rths-hil watch could not start)", file=sys.stderr)
    return None


def _stop_watcher(proc, run_dir: Path) -> None:
    """Let open pages show the final state, then end the watcher."""
    import subprocess
    import time

    time.sleep(0.6)  # three refreshes of the page
    proc.terminate()
    try:
        proc.wait(5)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    print(f"rths-hil run: live view closed; replay with: rths-hil watch {run_dir}", file=sys.stderr)
