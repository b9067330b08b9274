#!/usr/bin/env python3
"""Independent NumPy check of tactbench's automatic Tikhonov lambda (GCV), automatic
TSVD rank, condition number and per-node uncertainty (issue 12).

Used by the ignored Rust test `solvers::numpy_reference_checks_lambda_rank_and_uncertainty`:

    python3 -m venv /tmp/venv && /tmp/venv/bin/pip install numpy
    TACTBENCH_PYTHON=/tmp/venv/bin/python \
        cargo test --test integration solvers::numpy_reference -- --ignored

The Rust test writes a JSON case (geometry, one displacement frame, what tactbench
chose at several scalings of that frame, its reported standard deviations) and runs
`python lambda_check.py CASE.json`. Everything here is built from the paper's Eq. 1-2
(Boussinesq-Cerruti point-load displacements) and textbook formulas, not from
tactbench's code:

  * H: column (3j + c) = in-plane displacement of every marker under a unit force
    along c at force point j (Eq. 1-2), rows interleaved ux, uy per marker.
  * GCV (Golub, Heath & Wahba 1979) for Tikhonov, G(l) = ||H f_l - u||^2 /
    (m - trace(H P_l))^2, minimised over log l in [sigma_r/10, sigma_1] by a dense grid
    and golden-section refinement on the *unscaled* frame; tactbench's lambda at every
    scaling of the frame (1, 1e-160, 1e300) must match it.
  * TSVD rank by GCV over k = 1 .. min(r, m-1).
  * Per-node SD for noise sigma: sigma * row norms of P = (H^T H + l^2 I)^-1 H^T
    (normal equations, not an SVD); SD of the force sums from the summed rows; and
    a seeded Monte Carlo of the same (within 10 %).

Exit status 0 when every check passes, 1 otherwise (each failure printed).
"""

import json
import math
import sys

import numpy as np


def eq12(dx, dy, z, f, e, s):
    """Paper Eq. 1-2: in-plane displacement (mm) at offset (dx, dy), depth z (mm)
    below a surface point force f = (fx, fy, fz) N, Young's modulus e (N/mm^2),
    Poisson ratio s."""
    r = math.sqrt(dx * dx + dy * dy + z * z)
    k = (1.0 + s) / (2.0 * math.pi * e)
    out = []
    for c, fc in ((dx, f[0]), (dy, f[1])):
        t1 = (c * z / r**3 - (1.0 - 2.0 * s) * c / (r * (r + z))) * f[2]
        t2 = (2.0 * (1.0 - s) * r + z) / (r * (r + z)) * fc
        t3 = (2.0 * r * (s * r + z) + z * z) * c / (r**3 * (r + z) ** 2) * (dx * f[0] + dy * f[1])
        out.append(k * (t1 + t2 + t3))
    return out


def transfer_matrix(case):
    markers, points = case["markers"], case["points"]
    e, s = case["e_n_per_mm2"], case["nu"]
    h = np.zeros((2 * len(markers), 3 * len(points)))
    for i, (x, y, z) in enumerate(markers):
        for j, (px, py) in enumerate(points):
            for c in range(3):
                f = [0.0, 0.0, 0.0]
                f[c] = 1.0
                ux, uy = eq12(x - px, y - py, z, f, e, s)
                h[2 * i, 3 * j + c] = ux
                h[2 * i + 1, 3 * j + c] = uy
    return h


def golden_min(fun, a, b, iters=100):
    g = (math.sqrt(5.0) - 1.0) / 2.0
    x1, x2 = b - g * (b - a), a + g * (b - a)
    f1, f2 = fun(x1), fun(x2)
    for _ in range(iters):
        if f1 <= f2:
            b, x2, f2 = x2, x1, f1
            x1 = b - g * (b - a)
            f1 = fun(x1)
        else:
            a, x1, f1 = x1, x2, f2
            x2 = a + g * (b - a)
            f2 = fun(x2)
    return x1 if f1 <= f2 else x2


def main():
    case = json.load(open(sys.argv[1]))
    failures = []

    def check(ok, what):
        print(("ok   " if ok else "FAIL ") + what)
        if not ok:
            failures.append(what)

    h = transfer_matrix(case)
    m, n = h.shape
    u = np.array(case["u"])
    uu, sv, vt = np.linalg.svd(h, full_matrices=False)
    kappa = sv[0] / sv[-1]
    check(abs(case["condition_number"] - kappa) <= 1e-6 * kappa,
          f"condition number {case['condition_number']:.6e} vs numpy {kappa:.6e}")
    tol = max(m, n) * np.finfo(float).eps * sv[0]
    r = int(np.sum(sv > tol))

    beta = uu.T @ u
    d0 = max(float(u @ u - beta @ beta), 0.0)

    def gcv(t):
        lam = math.exp(t)
        phi = sv[:r] ** 2 / (sv[:r] ** 2 + lam * lam)
        res = d0 + np.sum(((1.0 - phi) * beta[:r]) ** 2) + np.sum(beta[r:] ** 2)
        return res / (m - phi.sum()) ** 2

    lo, hi = math.log(0.1 * sv[r - 1]), math.log(sv[0])
    grid = np.linspace(lo, hi, 4000)
    vals = [gcv(t) for t in grid]
    k = int(np.argmin(vals))
    check(0 < k < len(grid) - 1, f"numpy GCV optimum is interior (grid index {k} of {len(grid)})")
    t = golden_min(gcv, grid[max(k - 1, 0)], grid[min(k + 1, len(grid) - 1)])
    lam_ref = math.exp(t)
    for c in case["tikhonov_gcv"]:
        check(abs(c["lambda"] - lam_ref) <= 1e-3 * lam_ref,
              f"GCV lambda at scale {c['scale']:.0e}: tactbench {c['lambda']:.8e}, numpy {lam_ref:.8e}")

    best_k, best = None, math.inf
    for kk in range(1, min(r, m - 1) + 1):
        res = d0 + float(np.sum(beta[kk:] ** 2))
        g = res / (m - kk) ** 2
        if g < best:
            best_k, best = kk, g
    for c in case["tsvd"]:
        check(c["rank"] == best_k, f"TSVD rank at scale {c['scale']:.0e}: tactbench {c['rank']}, numpy {best_k}")

    unc = case["uncertainty"]
    lam, sigma = unc["lambda"], unc["sigma_mm"]
    p = np.linalg.solve(h.T @ h + lam * lam * np.eye(n), h.T)
    sd_ref = sigma * np.linalg.norm(p, axis=1)
    sd = np.array(unc["force_sd"])
    rel = np.max(np.abs(sd - sd_ref) / sd_ref)
    check(rel <= 1e-6, f"per-node SD against sigma*row norms of (H^T H + l^2 I)^-1 H^T: max rel diff {rel:.2e}")
    sum_ref = [sigma * np.linalg.norm(p[a::3].sum(axis=0)) for a in range(3)]
    for a in range(3):
        d = abs(unc["sum_sd"][a] - sum_ref[a]) / sum_ref[a]
        check(d <= 1e-6, f"SD of F_sum axis {a}: tactbench {unc['sum_sd'][a]:.6e}, numpy {sum_ref[a]:.6e}")

    rng = np.random.default_rng(12)
    noise = rng.normal(0.0, sigma, size=(4000, m))
    f = noise @ p.T
    mc = f.std(axis=0)
    mc_sum = [f[:, a::3].sum(axis=1).std() for a in range(3)]
    rel = np.max(np.abs(sd - mc) / mc)
    check(rel <= 0.10, f"per-node SD against a 4000-draw Monte Carlo: max rel diff {rel:.3f}")
    for a in range(3):
        d = abs(unc["sum_sd"][a] - mc_sum[a]) / mc_sum[a]
        check(d <= 0.10, f"SD of F_sum axis {a} against Monte Carlo: rel diff {d:.3f}")

    if failures:
        print(f"{len(failures)} check(s) failed")
        sys.exit(1)
    print("all checks passed")


if __name__ == "__main__":
    main()
