#!/usr/bin/env python3
"""Independent check of the bonded-layer kernels of src/model/layer.rs.

Method (different from the Rust code's closed-form Papkovich–Neuber solution): for each
wave number k the Navier equations of the mode e^{ikx} are written as a first-order
ODE system in z for the displacement–stress vector (u_x = i a, u_z = b, σ_xz = i c,
σ_zz = d; u_y = a_t, σ_yz = c_t) and integrated numerically with SciPy (solve_ivp,
DOP853, rtol 1e-12) from the bonded face z = h (a = b = 0) upwards for two unit stress
starts; their combination matching the surface traction σ_iz(0) = −p_i is the
solution. Output: one line per case, whitespace separated:

    h z nu k ll tt lz zl zz

(the scalar kernels of layer.rs, E = 1 N/mm², unit mm/N·mm²).

Run:  pip install numpy scipy; python3 tests/numpy_ref/layer_check.py
Used by the ignored test `layer::numpy_reference_kernels_agree` (tests/layer.rs):
    TACTBENCH_PYTHON=python3 cargo test --test integration layer:: -- --ignored
"""
import numpy as np
from scipy.integrate import solve_ivp

E = 1.0


def psv_rhs(k, lam, mu):
    def f(z, y):
        a, b, c, d = y
        bp = (d + lam * k * a) / (lam + 2 * mu)
        return [c / mu - k * b, bp, (lam + 2 * mu) * k * k * a - lam * k * bp, k * c]
    return f


def integrate(f, h, z, y0):
    # From z = h up to z = 0, recording the state at depth z.
    s = solve_ivp(f, (h, 0.0), y0, method="DOP853", rtol=1e-12, atol=1e-14,
                  dense_output=True)
    return s.sol(z), s.sol(0.0)


def kernels(h, z, nu, k):
    mu = E / (2 * (1 + nu))
    lam = 2 * mu * nu / (1 - 2 * nu)
    f = psv_rhs(k, lam, mu)
    yz1, y01 = integrate(f, h, z, [0.0, 0.0, 1.0, 0.0])
    yz2, y02 = integrate(f, h, z, [0.0, 0.0, 0.0, 1.0])
    m = np.array([[y01[2], y02[2]], [y01[3], y02[3]]])
    # Surface stresses (c, d) for p_l = -i (c(0) = 1, d(0) = 0) and p_z = 1 (c = 0, d = -1).
    cl = np.linalg.solve(m, [1.0, 0.0])
    cz = np.linalg.solve(m, [0.0, -1.0])
    yl = cl[0] * yz1 + cl[1] * yz2
    yzz = cz[0] * yz1 + cz[1] * yz2
    ll, zl = -yl[0], yl[1]          # u_x = i a = ll p_l with p_l = -i; u_z = b = i zl p_l
    lz, zz = yzz[0], yzz[1]         # u_x = i a = i lz; u_z = b = zz
    # Antiplane: a_t' = c_t/mu, c_t' = mu k^2 a_t, a_t(h) = 0, c_t(0) = -1.
    g = lambda _z, y: [y[1] / mu, mu * k * k * y[0]]
    tz, t0 = integrate(g, h, z, [0.0, 1.0])
    tt = -tz[0] / t0[1]
    return ll, tt, lz, zl, zz


CASES = [(h, z, nu, k)
         for (h, z) in [(3.0, 0.5), (3.0, 1.0), (3.0, 2.0), (40.0, 3.0), (40.0, 6.0)]
         for nu in [0.3, 0.49]
         for k in [0.05, 0.5, 1.5, 3.0]
         if k * h <= 15.0]

if __name__ == "__main__":
    for (h, z, nu, k) in CASES:
        v = kernels(h, z, nu, k)
        print(h, z, nu, k, *("%.15e" % x for x in v))
