"""Energy-error convergence of the exact discrete solution on the manufactured family.

docs/method.md §7; errors by a degree-7 quadrature per triangle.
"""

import numpy as np
import pytest

import fastmem as fm

SIZES = (8, 16, 32, 64, 128)

CASES = {
    "mu=(1,1) kappa=1": dict(mu=(1.0, 1.0), kappa=1.0),
    "mu=(1,10) kappa=1": dict(mu=(1.0, 10.0), kappa=1.0),
    "mu=(1,1) kappa=0": dict(mu=(1.0, 1.0), kappa=0.0),
    "mu=(1,10) kappa=0": dict(mu=(1.0, 10.0), kappa=0.0),
    "mu=(1,1) discontinuous": dict(mu=(1.0, 1.0), kappa=1.0, discontinuous=True),
    "mu=(1,10) discontinuous": dict(mu=(1.0, 10.0), kappa=1.0, discontinuous=True),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_energy_error_rate_is_one(case):
    ms = fm.Manufactured(**CASES[case])
    errors = []
    for n in SIZES:
        mesh = fm.Mesh.square(n)
        r = fm.solve(ms.scene(mesh), method="exact")
        assert r.converged
        errors.append(ms.energy_error(mesh, r.u1, r.u2, degree=7))
    errors = np.array(errors)
    rates = np.log2(errors[:-1] / errors[1:])
    assert np.all((rates > 0.9) & (rates < 1.1)), rates
    assert errors[-1] < 0.025  # absolute level on the finest mesh (n = 128)


def test_active_set_approximates_contact_set():
    """Away from the free boundary {b = g/beta} the discrete active set is exact."""
    ms = fm.Manufactured(mu=(1.0, 1.0), kappa=1.0)
    mesh = fm.Mesh.square(64)
    r = fm.solve(ms.scene(mesh), method="exact")
    x, y = mesh.vertices.T
    b = (1 - x**2) * (1 - y**2)
    ii = np.zeros(mesh.n_vertices, dtype=bool)
    ii[mesh.interior_vertices] = True
    h = mesh.h
    assert np.all(r.active[ii & (b > 0.4 + 2 * h)])
    assert not np.any(r.active[ii & (b < 0.4 - 2 * h)])
