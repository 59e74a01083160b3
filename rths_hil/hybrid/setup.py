"""The experimental setup: DOFs ↔ actuators, one transformation ``T`` for every layer.

OpenFresco (Schellenberg, Mahin and Fenves 2009) splits a hybrid test into the *experimental
element* (the numerical model's DOFs), the *experimental setup* (``ExperimentalSetup``: the
element's trial DOF displacements into actuator commands, ``transfTrialDisp``, and the
measured actuator displacements and forces back onto the DOFs, ``transfDaqDisp``,
``transfDaqForce``) and the *experimental control* (the controllers). This module is the setup
role of the bridge: a transformation ``T`` of one row per actuator (``n_actuators × n_dofs``)::

    d = T·u                            actuator displacements of the DOF displacements u
    p = Tᵀ·f                           DOF forces of the measured actuator forces f
    u = u_t + T⁺·(d_m − T·u_t)         DOF displacements consistent with the measured d_m,
                                       nearest the trial u_t (the minimum-norm correction)
    Tᵀ·K·T                             a per-actuator matrix (stiffness, damping, mass) on the DOFs

The same vocabulary serves two layers:

* a channel's row over the numerical structure's DOFs, from its ``dof`` (a unit row) or its
  ``transform`` (:func:`channel_row`, used by :mod:`rths_hil.hybrid.plan`); the loop's step
  applies the rows with plain floats (:func:`dot`, no array per step);
* the OpenSees site's ``T`` over the client element's DOFs (``openfresco.transform``, or by
  default the identity, one actuator per DOF, or :func:`chain_transform`, OpenFresco's basic
  system of two-node elements in series; :func:`site_transform`), used by
  :class:`rths_hil.openfresco.site.Mapping` through :class:`Setup`.

References
----------
A. Schellenberg, S. A. Mahin, G. L. Fenves, "Advanced implementation of hybrid simulation",
PEER Report 2009/104, Chapter 3 (the OpenFresco framework: experimental element, site,
setup and control).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ..errors import InputError

__all__ = [
    "Setup",
    "chain_transform",
    "channel_row",
    "check_rows",
    "dot",
    "site_transform",
    "split_rows",
    "unit_row",
]


def dot(row: list[float], x) -> float:
    """A row of ``T`` times a vector for short rows (plain floats): the loop's ``T·u``."""
    s = 0.0
    for r, v in zip(row, x, strict=False):
        if r:
            s += r * v
    return s


def unit_row(dof: int, n_dofs: int) -> np.ndarray:
    """The row of an actuator on DOF ``dof`` (0-based) alone: ``e_dof``."""
    row = np.zeros(n_dofs)
    row[dof] = 1.0
    return row


def channel_row(
    transform: Any, dof: int | None, n_dofs: int, where: str, default_dof: int = 1
) -> np.ndarray:
    """A channel's row of ``T``: its ``transform``, or the unit row of its ``dof`` (1-based).

    Parameters
    ----------
    transform : list of float or None
        The row given in the configuration (``n_dofs`` weights).
    dof : int or None
        The 1-based DOF the actuator acts on when no ``transform`` is given.
    n_dofs : int
        The structure's DOFs.
    where : str
        Where the channel is configured (for the messages).
    default_dof : int
        ``dof`` when neither is given.

    Raises
    ------
    InputError
        A row of another length, a DOF out of range, an all-zero row.
    """
    if transform is not None:
        row = np.asarray(transform, dtype=float)
        if row.size != n_dofs:
            raise InputError(
                f"{where}.transform: {row.size} entries, the structure has {n_dofs} DOF"
            )
    else:
        d = dof if dof is not None else default_dof
        if not 1 <= d <= n_dofs:
            raise InputError(f"{where}.dof: {d} is out of range: the structure has {n_dofs} DOF")
        row = unit_row(d - 1, n_dofs)
    if not np.any(row):
        raise InputError(f"{where}.transform: all zero: the actuator acts on no DOF")
    return row


def chain_transform(n: int) -> np.ndarray:
    """``T`` of ``n`` actuators between ``n + 1`` nodes in series: row i is ``u_{i+1} − u_i``.

    The basic system of a chain of two-node elements (one DOF per node): one actuator per
    element, its elongation ``u_{i+1} − u_i``, forces ``(−f_i, +f_i)`` at its nodes.
    """
    T = np.zeros((n, n + 1))
    for i in range(n):
        T[i, i], T[i, i + 1] = -1.0, 1.0
    return T


def split_rows(transform: Any, n_actuators: int, what: str) -> np.ndarray:
    """``T`` from nested rows or a flat row-major list of ``n_actuators`` rows.

    ``what`` names the key in the messages (``openfresco.transform``).
    """
    try:
        T = np.asarray(transform, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{what}: not numbers: {transform!r}") from None
    if T.ndim == 1:
        if T.size % n_actuators:
            raise InputError(
                f"{what}: {T.size} values are not {n_actuators} rows "
                "(one row of element-DOF weights per actuator, row-major)"
            )
        T = T.reshape(n_actuators, -1)
    return T


def check_rows(T: np.ndarray, n_actuators: int, n_dofs: int | None, what: str) -> np.ndarray:
    """``T`` checked: one finite row per actuator, ``n_dofs`` wide (when known), independent.

    Independent rows: no actuator's displacement is fixed by the others', so measured
    actuator displacements map back onto the DOFs (:meth:`Setup.dofs_from_measured`).
    """
    if T.ndim == 1:
        T = T[None, :]
    if T.ndim != 2 or T.shape[0] != n_actuators:
        raise InputError(
            f"{what}: {T.shape[0] if T.ndim == 2 else '?'} row(s), expected "
            f"one per actuator ({n_actuators})"
        )
    if n_dofs is not None and T.shape[1] != n_dofs:
        raise InputError(
            f"{what}: rows of {T.shape[1]} values, but the client's element has {n_dofs} DOFs"
        )
    if not np.all(np.isfinite(T)) or np.linalg.matrix_rank(T) < n_actuators:
        raise InputError(f"{what}: rows must be finite and independent")
    return T


def site_transform(n_actuators: int, n_dofs: int) -> np.ndarray | None:
    """The default ``T`` of a site without ``transform``: the identity (actuator ``i`` on DOF
    ``i``) when the counts agree, :func:`chain_transform` for one DOF more, else ``None``."""
    if n_dofs == n_actuators:
        return np.eye(n_dofs)
    if n_dofs == n_actuators + 1:
        return chain_transform(n_actuators)
    return None


class Setup:
    """The transformation ``T`` both ways (the module's equations).

    Parameters
    ----------
    T : array_like
        One row per actuator, one column per DOF.

    Attributes
    ----------
    T : numpy.ndarray
        The transformation.
    n_actuators, n_dofs : int
        Its shape.
    """

    def __init__(self, T: Any) -> None:
        self.T = T = np.atleast_2d(np.asarray(T, dtype=float))
        self.n_actuators, self.n_dofs = T.shape
        self._pinv = np.linalg.pinv(T)

    def to_actuators(self, u: np.ndarray) -> np.ndarray:
        """Actuator displacements ``T·u`` of DOF displacements ``u``."""
        return self.T @ u

    def to_dofs(self, f: np.ndarray) -> np.ndarray:
        """DOF forces ``Tᵀ·f`` of actuator forces ``f``."""
        return self.T.T @ f

    def dofs_from_measured(self, u_trial: np.ndarray, d_meas: np.ndarray) -> np.ndarray:
        """DOF displacements consistent with the measurement, nearest the trial.

        ``u = u_trial + T⁺·(d_meas − T·u_trial)`` (the minimum-norm correction).
        """
        return u_trial + self._pinv @ (d_meas - self.T @ u_trial)

    def on_dofs(self, m: np.ndarray) -> np.ndarray:
        """A per-actuator matrix on the DOFs: ``Tᵀ·m·T``."""
        T = self.T
        return T.T @ m @ T
