"""``rths-hil watch``: follow a run in the browser, live or as a replay.

``rths-hil watch [RUN_DIR | --latest] [--port 8050] [--host 127.0.0.1]``

Serves a page (Bokeh server, scripts from the installed package: works offline) that follows the
run directory's crash-safe record as the loop writes it, in this separate process: the loop does
not know it is watched. A finished or killed run replays with a time slider. The page's only
action is the operator stop (with a confirmation), which sends the run SIGINT, as Ctrl-C does.
Binds 127.0.0.1 unless ``--host`` says otherwise; then the URL carries a token (printed).
Stop the watcher with Ctrl-C (exit 0).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import time
from pathlib import Path

from .options import add_command


def register(sub: argparse._SubParsersAction) -> None:
    """Add ``watch`` to the top-level parser."""
    p = add_command(
        sub,
        "watch",
        __doc__,
        main,
        help="live view of a run in the browser (replay of a finished one)",
    )
    p.add_argument("run_dir", nargs="?", metavar="RUN_DIR", help="run directory to follow")
    p.add_argument(
        "--latest", action="store_true", help="follow the newest run under --runs (default: runs)"
    )
    p.add_argument(
        "--runs",
        metavar="DIR",
        help="where --latest looks (default: the parent of output.dir, i.e. runs)",
    )
    p.add_argument("--port", type=int, default=8050, help="TCP port (default 8050; 0 = any free)")
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to bind (default 127.0.0.1; any other address requires the printed token)",
    )
    p.add_argument(
        "--no-stop", action="store_true", help="no operator-stop button on the page (view only)"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="print only the URL and errors")
    # used by `rths-hil run --watch`: exit some time after the run's process is gone
    p.add_argument("--parent", type=int, default=None, help=argparse.SUPPRESS)


def latest_run(base: Path) -> Path:
    """The newest run directory under ``base`` (by the modification time of its metadata)."""
    from ..errors import InputError

    if not base.is_dir():
        raise InputError(f"--latest: {base} does not exist (no run recorded here yet)")
    best, best_t = None, -1.0
    for d in base.iterdir():
        for name in ("meta.json", "record.npy"):
            p = d / name
            try:
                t = p.stat().st_mtime if name == "meta.json" else p.stat().st_ctime
            except OSError:
                continue
            if t > best_t:
                best, best_t = d, t
            break
    if best is None:
        raise InputError(f"--latest: no run directory under {base}")
    return best


def _runs_base(args: argparse.Namespace) -> Path:
    if args.runs:
        return Path(args.runs)
    from ..config import load_config

    pattern = load_config(None)["output"]["dir"]
    p = Path(pattern)
    return p.parent if "{" in p.name else p


def main(args: argparse.Namespace) -> int:
    """Serve the page until Ctrl-C; return the exit code."""
    from ..errors import InputError, require

    require("live", "rths-hil watch")
    from ..watch.server import LOCAL_HOSTS, WatchServer

    if args.latest and args.run_dir:
        raise InputError("give RUN_DIR or --latest, not both")
    if not args.latest and not args.run_dir:
        raise InputError("give a run directory (RUN_DIR) or --latest")
    run_dir = latest_run(_runs_base(args)) if args.latest else Path(args.run_dir)

    quiet = args.quiet
    # a closed browser tab is not an error worth a line in the operator's terminal
    logging.getLogger("bokeh.server.views.ws").setLevel(logging.ERROR)

    def say(line: str) -> None:
        if not quiet:
            print(f"rths-hil watch: {line}", file=sys.stderr, flush=True)

    try:
        # the watcher yields to the loop when both want the CPU: nice 10 (or lower priority)
        os.setpriority(os.PRIO_PROCESS, 0, max(10, os.getpriority(os.PRIO_PROCESS, 0)))
    except OSError:
        pass
    server = WatchServer(
        run_dir, host=args.host, port=args.port, allow_stop=not args.no_stop, notify=say
    )
    server.start()
    if args.parent is not None:  # started by `rths-hil run --watch`
        print(f"rths-hil run: live view at {server.url}", file=sys.stderr)
    else:
        print(f"rths-hil watch: {server.url} follows {run_dir} (Ctrl-C to stop)", file=sys.stderr)
    if args.host not in LOCAL_HOSTS:
        print(
            f"rths-hil watch: warning: listening on {args.host}: anyone who can reach this "
            "address and has the URL with its token can see the run and stop it",
            file=sys.stderr,
        )
    sys.stderr.flush()
    server.ctx.state()  # the run's state in the terminal (missing, empty, running …)
    if args.parent is not None:
        _exit_after_parent(server, args.parent)
    server.run_forever()
    return 0


def _exit_after_parent(server, pid: int, linger: float = 30.0) -> None:
    """Stop serving ``linger`` s after process ``pid`` is gone (the run that started us)."""
    gone_at: list[float] = []

    def check() -> None:
        try:
            os.kill(pid, 0)
            alive = True
        except ProcessLookupError:
            alive = False
        except PermissionError:
            alive = True
        if alive:
            return
        if not gone_at:
            gone_at.append(time.monotonic())
        elif time.monotonic() - gone_at[0] > linger:
            server._server.io_loop.stop()

    from tornado.ioloop import PeriodicCallback

    PeriodicCallback(check, 1000).start()
