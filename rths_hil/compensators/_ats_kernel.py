"""The ATS fit's compiled kernels (:mod:`numba`): the Butterworth sections on the command and
the measured displacement, the window rows and the bounded least-squares update, on the state
vector laid out in :mod:`.ats` (imported when the first
:class:`~rths_hil.compensators.ats.ATSCompensator` is built, so that reading the configuration
does not load numba)."""

from __future__ import annotations

import math

import numba

from .ats import (
    _A,
    _C0,
    _C1,
    _COUNT,
    _DMAX,
    _DT,
    _HEAD,
    _HI,
    _LO,
    _M0,
    _M1,
    _M2,
    _PRIMED,
    _ROWS,
    _SKIP,
    _THR2,
    _Z,
)

__all__ = ["observe", "sos_step"]


@numba.njit(cache=True)
def sos_step(sos, s, base, x):  # pragma: no cover - compiled
    """One sample through second-order sections (transposed direct form II), state in s."""
    for i in range(sos.shape[0]):
        b0, b1, b2, a1, a2 = sos[i, 0], sos[i, 1], sos[i, 2], sos[i, 4], sos[i, 5]
        j = base + 2 * i
        y = b0 * x + s[j]
        s[j] = b1 * x - a1 * y + s[j + 1]
        s[j + 1] = b2 * x - a2 * y
        x = y
    return x


@numba.njit(cache=True)
def observe(st, sos, ring, command, measured):  # pragma: no cover - compiled
    """Filter the pair, form a window row every ``skip`` samples, refit; True if ``a`` moved."""
    cf = sos_step(sos, st, _Z, command)
    mf = sos_step(sos, st, _Z + 2 * sos.shape[0], measured)
    st[_M2] = st[_M1]
    st[_M1] = st[_M0]
    st[_M0] = mf
    st[_C1] = st[_C0]
    st[_C0] = cf
    st[_PRIMED] += 1.0
    st[_COUNT] += 1.0
    if st[_COUNT] < st[_SKIP] or st[_PRIMED] < 3.0:
        return False
    st[_COUNT] = 0.0
    q = ring.shape[0]
    h = int(st[_HEAD])
    dt = st[_DT]
    m0, m1, m2 = st[_M0], st[_M1], st[_M2]
    ring[h, 0] = m1
    ring[h, 1] = (m0 - m2) / (2.0 * dt)
    ring[h, 2] = (m0 - 2.0 * m1 + m2) / (dt * dt)
    ring[h, 3] = st[_C1]
    st[_HEAD] = (h + 1) % q
    if st[_ROWS] < q:
        st[_ROWS] += 1.0
        if st[_ROWS] < q:
            return False
    # normal equations over the window
    s00 = s01 = s02 = s11 = s12 = s22 = b0 = b1 = b2 = 0.0
    for r in range(q):
        x0, x1, x2, y = ring[r, 0], ring[r, 1], ring[r, 2], ring[r, 3]
        s00 += x0 * x0
        s01 += x0 * x1
        s02 += x0 * x2
        s11 += x1 * x1
        s12 += x1 * x2
        s22 += x2 * x2
        b0 += x0 * y
        b1 += x1 * y
        b2 += x2 * y
    if s00 / q <= st[_THR2] or s11 <= 0.0 or s22 <= 0.0:
        return False
    # column scaling: unit diagonal, then the closed-form inverse of the 3×3 matrix
    d0, d1, d2 = 1.0 / math.sqrt(s00), 1.0 / math.sqrt(s11), 1.0 / math.sqrt(s22)
    n01, n02, n12 = s01 * d0 * d1, s02 * d0 * d2, s12 * d1 * d2
    c0, c1, c2 = b0 * d0, b1 * d1, b2 * d2
    det = 1.0 + 2.0 * n01 * n12 * n02 - n01 * n01 - n02 * n02 - n12 * n12
    if det < 1e-9:
        return False
    i00 = 1.0 - n12 * n12
    i01 = n02 * n12 - n01
    i02 = n01 * n12 - n02
    i11 = 1.0 - n02 * n02
    i12 = n01 * n02 - n12
    i22 = 1.0 - n01 * n01
    sol0 = (i00 * c0 + i01 * c1 + i02 * c2) / det * d0
    sol1 = (i01 * c0 + i11 * c1 + i12 * c2) / det * d1
    sol2 = (i02 * c0 + i12 * c1 + i22 * c2) / det * d2
    if sol0 != sol0 or sol1 != sol1 or sol2 != sol2:
        return False
    sol = (sol0, sol1, sol2)
    for i in range(3):
        v = sol[i]
        a, dm = st[_A + i], st[_DMAX + i]
        if v > a + dm:
            v = a + dm
        elif v < a - dm:
            v = a - dm
        if v > st[_HI + i]:
            v = st[_HI + i]
        elif v < st[_LO + i]:
            v = st[_LO + i]
        st[_A + i] = v
    return True
