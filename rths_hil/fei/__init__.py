"""Frequency-domain evaluation index (FEI) of actuator tracking, whole-record and moving-window.

The FEI (Guo et al., the FEI paper's ref. [6]; the FEI paper's Eq. 2.1–2.5) condenses a
target/measured pair into a generalised amplitude ``A`` and an equivalent delay ``d``. Moving
windows with overlap (MWO, the FEI paper's Section 3–4, Eq. 7: overlap ``OL = N − 1``) make it local
in time.

Conventions (fixed here, documented in ``docs/fei.md``)
-------------------------------------------------------
* ``y_I`` = target (calculated) displacement, ``y_o`` = measured displacement, ``fs`` in Hz.
* Each window of ``N`` samples: subtract each signal's mean, multiply by the symmetric Hann
  window ``numpy.hanning(N)`` (the FEI paper's Eq. 3.2 as printed is not a Hann window; we treat it
  as a typo), zero-pad to ``M`` = the smallest power of two ≥ ``N`` (``M = 2p``), FFT.
* Sums run over the one-sided bins ``k = 1 … p−1`` (DC and Nyquist excluded), for both the FEI
  and ``f_eq``. The ratio ``y_o/y_I · |y_I|²`` of Eq. 2.1 is computed as ``y_o · conj(y_I)``, so
  no bin is ever divided by::

      FEI  = Σ_k Y_o(k) conj(Y_I(k)) / Σ_k |Y_I(k)|²                  (Eq. 2.1)
      A    = |FEI|                                                     (Eq. 2.2)
      φ    = atan2(Im FEI, Re FEI)      (full ±π; Eq. 2.3 uses atan)   (Eq. 2.3)
      f_eq = Σ_k |Y_I(k)|² f_k / Σ_k |Y_I(k)|²,  f_k = k fs / M        (Eq. 2.4)
      d    = −φ / (2π f_eq)   [s]; measured lagging target → d > 0     (Eq. 2.5)

* Validity: a window's *level* is ``sqrt(2 E / (M Σ w²))`` with ``E = Σ_k |Y_I(k)|²`` — the
  Hann-weighted RMS of the mean-free target, in the signal's unit (m). A window is valid when
  its level exceeds ``abs_floor`` (default 1 µm) and ``rel_floor`` (default 5 %) of the running
  peak level of the windows evaluated so far (causal, so online and batch agree), and when
  ``f_eq`` is positive and finite. Invalid windows carry NaN estimates; rules must ignore them.

Algorithms
----------
* :func:`fei` — one window (the whole record), direct FFT.
* :func:`moving_fei` — all windows ending every ``hop`` samples. ``method="exact"`` chooses
  between a batched direct FFT (large hops) and an exact recursive evaluation for small hops: the
  three spectral sums are bilinear forms of the windowed signals with lag-only kernels, updated
  window to window through causal convolutions computed with FFTs over the whole record, so the
  cost per window is independent of ``N`` (see ``docs/fei.md``). Both agree with the brute-force
  DFT to round-off.
* :class:`OnlineFEI` — blocks of any length in, completed windows out. ``method="exact"`` keeps
  the last ``N`` samples and evaluates each completed window by FFT (equal to :func:`moving_fei`
  to round-off); ``method="streaming"`` costs O(1) per sample (see :mod:`rths_hil.fei.streaming`).

Modules
-------
* :mod:`rths_hil.fei.batch` — :func:`fei`, :func:`moving_fei`, the result types and floors.
* :mod:`rths_hil.fei.online` — :class:`OnlineFEI`.
* :mod:`rths_hil.fei.sliding` — sliding DFTs (exact online evaluation, streaming low band).
* :mod:`rths_hil.fei.streaming` — the O(1)-per-sample streaming evaluator.
"""

from .batch import (
    ABS_FLOOR,
    BATCH_BYTES,
    REL_FLOOR,
    SLIDING_MAX_HOP,
    ZERO_VARIANCE_RTOL,
    FEIResult,
    MovingFEIResult,
    fei,
    fft_length,
    moving_fei,
    window_samples,
)
from .online import OnlineFEI

__all__ = [
    "ABS_FLOOR",
    "BATCH_BYTES",
    "REL_FLOOR",
    "SLIDING_MAX_HOP",
    "ZERO_VARIANCE_RTOL",
    "FEIResult",
    "MovingFEIResult",
    "OnlineFEI",
    "fei",
    "fft_length",
    "moving_fei",
    "window_samples",
]
