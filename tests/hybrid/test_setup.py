"""The experimental setup (DOFs ↔ actuators) against independent references.

References: the direct stiffness method (element stiffness matrices assembled by hand), the
principle of virtual work (``f·(T·u) = (Tᵀ·f)·u``), numpy's least squares for the correction
of a trial onto a measurement.
"""

from __future__ import annotations

import numpy as np
import pytest

from rths_hil.errors import InputError
from rths_hil.hybrid.setup import (
    Setup,
    chain_transform,
    channel_row,
    check_rows,
    dot,
    site_transform,
    split_rows,
)


def _assembled_springs(ks: list[float]) -> np.ndarray:
    """Springs in series between nodes 0..n, assembled element by element (direct stiffness)."""
    n = len(ks)
    K = np.zeros((n + 1, n + 1))
    for i, k in enumerate(ks):
        ke = k * np.array([[1.0, -1.0], [-1.0, 1.0]])
        K[i : i + 2, i : i + 2] += ke
    return K


def test_chain_is_the_basic_system_of_springs_in_series():
    ks = [1.0e6, 2.5e6, 4.0e5]
    s = Setup(chain_transform(3))
    np.testing.assert_allclose(s.on_dofs(np.diag(ks)), _assembled_springs(ks))
    # elongations of each spring: u_{i+1} − u_i
    u = np.array([0.0, 1.0e-3, 4.0e-3, 2.0e-3])
    np.testing.assert_allclose(s.to_actuators(u), [1.0e-3, 3.0e-3, -2.0e-3])
    # a spring's tension pulls its end nodes together: (−f, +f)
    np.testing.assert_allclose(s.to_dofs(np.array([5.0, 0.0, 0.0])), [-5.0, 5.0, 0.0, 0.0])


def test_both_ways_do_the_same_virtual_work():
    rng = np.random.default_rng(3)
    T = rng.normal(size=(2, 5))
    s = Setup(T)
    for _ in range(5):
        u, f = rng.normal(size=5), rng.normal(size=2)
        assert f @ s.to_actuators(u) == pytest.approx(s.to_dofs(f) @ u, rel=1e-12)


def test_measured_displacements_onto_the_dofs_nearest_the_trial():
    rng = np.random.default_rng(7)
    T = rng.normal(size=(2, 4))
    s = Setup(T)
    u_t, d_m = rng.normal(size=4), rng.normal(size=2)
    u = s.dofs_from_measured(u_t, d_m)
    np.testing.assert_allclose(T @ u, d_m, atol=1e-12)  # it reproduces the measurement
    # the smallest change that does: least squares on T·Δ = d_m − T·u_t
    delta, *_ = np.linalg.lstsq(T, d_m - T @ u_t, rcond=None)
    np.testing.assert_allclose(u - u_t, delta, atol=1e-12)


def test_site_default_transforms():
    np.testing.assert_array_equal(site_transform(2, 2), np.eye(2))
    np.testing.assert_array_equal(site_transform(1, 2), [[-1.0, 1.0]])
    assert site_transform(2, 5) is None


def test_rows_split_and_checked():
    T = split_rows([-1, 1, 0, 0, -1, 1], 2, "openfresco.transform")
    np.testing.assert_array_equal(T, [[-1, 1, 0], [0, -1, 1]])
    with pytest.raises(InputError, match="3 values are not 2 rows"):
        split_rows([1.0, -1.0, 0.5], 2, "openfresco.transform")
    with pytest.raises(InputError, match="finite and independent"):
        check_rows(np.array([[1.0, 2.0], [2.0, 4.0]]), 2, 2, "openfresco.transform")
    with pytest.raises(InputError, match="rows of 3 values, but the client's element has 4"):
        check_rows(T, 2, 4, "openfresco.transform")


def test_channel_row():
    np.testing.assert_array_equal(channel_row(None, 2, 3, "a.toml"), [0.0, 1.0, 0.0])
    np.testing.assert_array_equal(channel_row(None, None, 3, "a.toml", 3), [0.0, 0.0, 1.0])
    np.testing.assert_array_equal(channel_row([0.5, -0.5], None, 2, "a.toml"), [0.5, -0.5])
    with pytest.raises(InputError, match=r"^a\.toml\.dof: 4 is out of range"):
        channel_row(None, 4, 3, "a.toml")
    with pytest.raises(InputError, match=r"^a\.toml\.transform: 2 entries, the structure has 3"):
        channel_row([1.0, 0.0], None, 3, "a.toml")
    with pytest.raises(InputError, match="all zero"):
        channel_row([0.0, 0.0], None, 2, "a.toml")


def test_dot_is_the_row_product():
    rng = np.random.default_rng(1)
    for n in (1, 3, 6):
        row, x = rng.normal(size=n), rng.normal(size=n)
        row[0] = 0.0
        assert dot(row.tolist(), x.tolist()) == pytest.approx(float(row @ x), rel=1e-12)
