"""Per-channel online evaluators on the step path: streaming FEI, exact FEI cross-check.

:class:`StreamingFEI` pushes one sample pair per step (the streaming OnlineFEI's fast path);
:class:`ExactFEI` evaluates the exact FEI every ``hop`` samples, synchronously (lockstep) or in a
worker process (paced) so its FFT work never sits on the step path. Every exact value carries
the step at which its window ended, so the record and the report place it there (not at the
step its result came back from the worker).
"""

from __future__ import annotations

import contextlib
import math
import os
import struct
import subprocess
import sys

import numpy as np

from ..fei import OnlineFEI

__all__ = ["MAX_HELD_SHARE", "ExactFEI", "StreamingFEI"]

#: A streaming FEI window in which more than this share of the measured samples are held
#: (missed replies: the loop repeats the last good measurement) is not valid: the FEI rule
#: neither trips nor counts on it. Below it the window is valid and its share of held samples
#: is recorded next to it (``fei_held``), the confidence a reader gives it. A 40 ms pause of
#: the controller is 1 % of a 4 s window.
MAX_HELD_SHARE = 0.1


class StreamingFEI:
    """Per-sample streaming FEI (OnlineFEI ``method="streaming"``, hop 1).

    Uses :meth:`OnlineFEI.push`, the evaluator's one-sample fast path (no result arrays per
    call; :meth:`OnlineFEI.update` with a one-sample block allocates a result of seven arrays,
    ≈ 26 µs). :attr:`latest` holds the newest window's (amplitude, delay, f_eq, valid);
    :attr:`held` counts the held samples in the current window (:data:`MAX_HELD_SHARE`).
    """

    def __init__(self, fs: float, window_s: float) -> None:
        self.online = OnlineFEI(fs, window_s, hop=1, method="streaming")
        self.N = self.online.N
        self._push = self.online.push
        self.latest = (math.nan, math.nan, math.nan, False)
        self.held = 0
        self._ring = bytearray(self.N)  # 1: the sample in this slot of the window was held
        self._i = 0
        self._max_held = MAX_HELD_SHARE * self.N

    @property
    def held_share(self) -> float:
        """Share of held samples in the current window (0 … 1)."""
        return self.held / self.N

    def push(self, target: float, measured: float, held: bool = False) -> bool:
        """Push one sample pair; True when a window completed (see :attr:`latest`).

        ``held``: ``measured`` is the last good measurement repeated (no reply this step).
        """
        ring = self._ring
        i = self._i
        new = 1 if held else 0
        n = self.held + new - ring[i]
        ring[i] = new
        self.held = n
        self._i = i + 1 if i + 1 < self.N else 0
        res = self._push(target, measured)
        if res is None:
            return False
        if n > self._max_held and res[3]:
            res = (res[0], res[1], res[2], False)
        self.latest = res
        return True


#: amplitude, delay, f_eq, valid (0/1), windows so far, step at which the window ended
_EXACT_RESULT = struct.Struct("<4dqq")


def exact_worker_main() -> None:  # pragma: no cover - runs in the worker process
    """Exact-FEI worker process: ``fs window_s hop`` in argv, blocks on stdin, results out.

    Each block is ``2·hop`` float64 (target then measured); each completed window is answered
    with one :data:`_EXACT_RESULT` record (the first record, with ``windows = -1``, says ready);
    the window's end step is ``round(t_end · fs)`` (the stream starts at step 0).
    End of input (the loop finished or was killed) ends the process.
    """
    fs, window_s, hop = float(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    with contextlib.suppress(AttributeError, OSError):  # not under the loop's RT priority
        os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
    with contextlib.suppress(AttributeError, OSError):  # and off a loop pinned to one CPU
        pinned = os.sched_getaffinity(0)
        others = set(range(os.cpu_count() or 1)) - pinned
        if len(pinned) == 1 and others:
            os.sched_setaffinity(0, others)
    online = OnlineFEI(fs, window_s, hop=hop, method="exact")
    warm = OnlineFEI(fs, window_s, hop=hop, method="exact")  # FFT plans and caches
    t = np.arange(online.N + hop) / fs
    warm.update(np.sin(6.0 * t), np.sin(6.0 * t - 0.1))
    out = sys.stdout.buffer
    out.write(_EXACT_RESULT.pack(math.nan, math.nan, math.nan, 0.0, -1, -1))
    out.flush()
    size = 16 * hop
    inp = sys.stdin.buffer
    windows = 0
    while True:
        data = inp.read(size)
        if len(data) < size:
            return
        xy = np.frombuffer(data, dtype=float)
        res = online.update(xy[:hop], xy[hop:])
        if len(res):
            windows += len(res)
            out.write(
                _EXACT_RESULT.pack(
                    float(res.amplitude[-1]),
                    float(res.delay[-1]),
                    float(res.f_eq[-1]),
                    1.0 if res.valid[-1] else 0.0,
                    windows,
                    round(float(res.t_end[-1]) * fs),
                )
            )
            out.flush()


class ExactFEI:
    """Exact OnlineFEI at a coarse hop, fed in blocks of ``hop`` samples.

    ``background=False`` evaluates in the caller (lockstep: deterministic).
    ``background=True`` (paced) writes each block to a worker *process* through a pipe and
    reads its results (non-blocking) when it hands over the next block, so the window's FFT work
    (≈ 0.5 ms at N = 4 k) never runs on the step path. A worker thread is not good enough: it
    holds the GIL during its numpy calls and the loop thread then waits for the GIL after each
    reply (measured: 3.6 % → 8.5 % late steps at 1024 Hz). :attr:`latest` holds the newest
    completed window (it lags the stream by up to one hop in the background mode) and
    :attr:`end_step` the step at which that window ended: record and plot it there.
    """

    def __init__(self, fs: float, window_s: float, hop: int, background: bool) -> None:
        self.hop = hop
        self._bxy = np.zeros(2 * hop)
        self._i = 0
        self.latest = (math.nan, math.nan, math.nan, False)
        self.windows = 0
        self.end_step = -1  # step at which the window of :attr:`latest` ended
        self._fs = float(fs)
        self.online = None
        self._proc: subprocess.Popen[bytes] | None = None
        self._pending = b""
        if background:
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    "from rths_hil.hybrid.evaluators import exact_worker_main as m; m()",
                    repr(float(fs)),
                    repr(float(window_s)),
                    str(int(hop)),
                ],
                stdin=subprocess.PIPE,
                stdout=subprocess.PIPE,
                bufsize=0,
                start_new_session=True,  # a terminal's Ctrl-C goes to the loop only
            )
            assert proc.stdin is not None and proc.stdout is not None  # both PIPE
            self._proc = proc
            self._in = proc.stdin.fileno()
            self._out = proc.stdout.fileno()
            ready = proc.stdout.read(_EXACT_RESULT.size)  # blocks until warmed up
            if len(ready) != _EXACT_RESULT.size:
                raise RuntimeError("the exact-FEI worker process did not start")
            os.set_blocking(self._out, False)
        else:
            self.online = OnlineFEI(fs, window_s, hop=hop, method="exact")

    def _collect(self) -> None:
        try:
            data = os.read(self._out, 65536)
        except BlockingIOError:
            return
        self._take(self._pending + data)

    def _take(self, buf: bytes) -> None:
        """Keep the last whole result in ``buf`` (the worker's, oldest first); the rest waits."""
        n = len(buf) // _EXACT_RESULT.size
        if n:
            a, d, f, v, w, end = _EXACT_RESULT.unpack_from(buf, (n - 1) * _EXACT_RESULT.size)
            self.latest = (a, d, f, v > 0.5)
            self.windows = w
            self.end_step = end
        self._pending = buf[n * _EXACT_RESULT.size :]

    def push(self, target: float, measured: float) -> None:
        """Add one sample pair; evaluate (or hand over) each full block."""
        i = self._i
        b = self._bxy
        b[i] = target
        b[self.hop + i] = measured
        i += 1
        if i < self.hop:
            self._i = i
            return
        self._i = 0
        if self._proc is not None:
            self._collect()
            os.write(self._in, b.tobytes())
            return
        online = self.online
        assert online is not None  # no worker process: evaluated here
        res = online.update(b[: self.hop], b[self.hop :])
        if len(res):
            self.windows += len(res)
            self.end_step = round(float(res.t_end[-1]) * self._fs)
            self.latest = (
                float(res.amplitude[-1]),
                float(res.delay[-1]),
                float(res.f_eq[-1]),
                bool(res.valid[-1]),
            )

    def close(self) -> None:
        """Stop the worker process (after it has evaluated what it was given)."""
        proc, self._proc = self._proc, None
        if proc is None:
            return
        assert proc.stdin is not None and proc.stdout is not None  # both PIPE
        try:
            proc.stdin.close()
            proc.wait(timeout=5.0)
            os.set_blocking(self._out, True)
            self._take(self._pending + proc.stdout.read())
        except (OSError, subprocess.TimeoutExpired):
            proc.kill()
        finally:
            proc.stdout.close()
