#!/usr/bin/env python3
"""Independent check of tactbench's `fourier` solver (issue 12).

Implements the half-space point response (paper Eq. 1-2: Boussinesq for the normal
load, Cerruti for the tangential load, displacements u_x, u_y at depth z), builds the
dense transfer matrix H from it, and solves dense Tikhonov
f = V diag(s/(s^2+lambda^2)) U^T u with NumPy's SVD. Nothing here comes from the Rust
code except the problem description and the Fourier output to be checked.

Input: a JSON file written by the ignored Rust test
`fourier::numpy_reference_agrees_with_fourier_output` (tests/fourier.rs):

    {"cases": [{"name": str, "young_mpa": E, "poisson": nu, "lambda": mm/N,
                "force_grid": {"nx", "ny", "pitch_mm", "origin_mm": [x, y]},
                "layers": [{"depth_mm", "nx", "ny", "pitch_mm", "origin_mm": [x, y]}],
                "f_true": [fx, fy, fz per force node, row-major],
                "noise_mm": [per displacement, added to the exact H f_true],
                "fourier": [the solver's forces for H f_true + noise],
                "sigma_mm": displacement noise SD (optional, with the two below),
                "force_sd": [the solver's SD of every force component at sigma_mm],
                "sum_sd": [the solver's SD of the force sums at sigma_mm]}]}

Checks per case against the dense Tikhonov solution of the same (NumPy-computed)
displacements: force sum within 2 % of the applied total on every axis, field within
10 % overall and 5 % on the interior (>= 4 mm from the grid edges). With "sigma_mm":
the reported uncertainties against sigma * sqrt(diag(P P^T)) of NumPy's dense Tikhonov
operator P (what the refined solver converges to) and against a seeded NumPy Monte
Carlo of 2000 noise frames through P: every node's SD and the force sums' SDs within
10 %. Prints one line per case and exits 1 if any check fails.

Run (NumPy needed: `pip install numpy`):

    TACTBENCH_PYTHON=python3 cargo test --test integration \
        fourier::numpy_reference_agrees_with_fourier_output -- --ignored --nocapture

or by hand on a JSON file: `python3 tests/numpy_ref/fourier_check.py cases.json`.
"""
import json
import sys

import numpy as np


def point_response(dx, dy, z, young, nu):
    """2x3 response (mm/N) at horizontal offset (dx, dy) (marker - force point), depth z."""
    c = (1.0 + nu) / (2.0 * np.pi * young)
    r2 = dx * dx + dy * dy + z * z
    r = np.sqrt(r2)
    r3 = r2 * r
    rz = r + z
    a = z / r3 - (1.0 - 2.0 * nu) / (r * rz)  # Boussinesq, radial part
    b = (2.0 * (1.0 - nu) * r + z) / (r * rz)  # Cerruti, isotropic part
    g = (2.0 * r * (nu * r + z) + z * z) / (r3 * rz * rz)  # Cerruti, (x fx + y fy) part
    return np.array(
        [
            [c * (b + g * dx * dx), c * g * dx * dy, c * a * dx],
            [c * g * dx * dy, c * (b + g * dy * dy), c * a * dy],
        ]
    )


def nodes(grid):
    ix, iy = np.meshgrid(np.arange(grid["nx"]), np.arange(grid["ny"]))
    x = grid["origin_mm"][0] + grid["pitch_mm"] * ix.ravel()
    y = grid["origin_mm"][1] + grid["pitch_mm"] * iy.ravel()
    return np.stack([x, y], 1)


def transfer_matrix(case):
    forces = nodes(case["force_grid"])
    blocks = []
    for layer in case["layers"]:
        m = nodes(layer)
        dx = m[:, 0][:, None] - forces[:, 0][None, :]
        dy = m[:, 1][:, None] - forces[:, 1][None, :]
        resp = point_response(dx, dy, layer["depth_mm"], case["young_mpa"], case["poisson"])
        h = np.zeros((2 * len(m), 3 * len(forces)))
        for i in range(2):
            for j in range(3):
                h[i::2, j::3] = resp[i, j]
        blocks.append(h)
    return np.vstack(blocks)


def interior(case, f, margin_mm=4.0):
    g = case["force_grid"]
    m = int(np.ceil(margin_mm / g["pitch_mm"]))
    f = f.reshape(g["ny"], g["nx"], 3)
    return f[m : g["ny"] - m, m : g["nx"] - m, :].ravel()


def rel(a, b):
    return np.linalg.norm(a - b) / np.linalg.norm(b)


def check(case):
    h = transfer_matrix(case)
    f_true = np.asarray(case["f_true"])
    u = h @ f_true + np.asarray(case["noise_mm"])
    uu, s, vt = np.linalg.svd(h, full_matrices=False)
    lam = case["lambda"]
    dense = vt.T @ ((s / (s * s + lam * lam)) * (uu.T @ u))
    got = np.asarray(case["fourier"])
    applied = f_true.reshape(-1, 3).sum(0)
    total = np.abs(applied).max()
    sd, sg = dense.reshape(-1, 3).sum(0), got.reshape(-1, 3).sum(0)
    e_sum = np.abs(sg - sd).max() / total
    e_all = rel(got, dense)
    e_int = rel(interior(case, got), interior(case, dense))
    ok = e_sum <= 0.02 and e_all <= 0.10 and e_int <= 0.05
    print(
        f"{case['name']}: applied {np.round(applied, 4)}, numpy dense {np.round(sd, 4)}, "
        f"fourier {np.round(sg, 4)}; sum {e_sum:.4f} (<= 0.02), field {e_all:.4f} (<= 0.10), "
        f"interior {e_int:.4f} (<= 0.05): {'ok' if ok else 'FAIL'}"
    )
    if "sigma_mm" in case:
        sigma = case["sigma_mm"]
        p = vt.T @ ((s / (s * s + lam * lam))[:, None] * uu.T)
        node = sigma * np.linalg.norm(p, axis=1)
        sums = sigma * np.linalg.norm(p.reshape(-1, 3, p.shape[1]).sum(0), axis=1)
        rng = np.random.default_rng(12)
        draws = p @ (sigma * rng.standard_normal((p.shape[1], 2000)))
        mc_node = draws.std(axis=1)
        mc_sum = draws.reshape(-1, 3, draws.shape[1]).sum(0).std(axis=1)
        got_node = np.asarray(case["force_sd"])
        got_sum = np.asarray(case["sum_sd"])
        e_node = np.abs(got_node / node - 1.0).max()
        e_sum_sd = np.abs(got_sum / sums - 1.0).max()
        e_mc_node = rel(got_node, mc_node)
        e_mc_sum = np.abs(got_sum / mc_sum - 1.0).max()
        ok_sd = e_node <= 0.10 and e_sum_sd <= 0.10 and e_mc_node <= 0.10 and e_mc_sum <= 0.10
        print(
            f"  uncertainty at {sigma} mm: sum SD fourier {np.round(got_sum, 5)}, numpy exact "
            f"{np.round(sums, 5)}, MC {np.round(mc_sum, 5)}; worst node vs exact {e_node:.4f}, "
            f"sums vs exact {e_sum_sd:.4f}, nodes vs MC {e_mc_node:.4f}, sums vs MC "
            f"{e_mc_sum:.4f} (all <= 0.10): {'ok' if ok_sd else 'FAIL'}"
        )
        ok = ok and ok_sd
    return ok


def main():
    with open(sys.argv[1]) as fh:
        cases = json.load(fh)["cases"]
    results = [check(c) for c in cases]
    sys.exit(0 if all(results) else 1)


if __name__ == "__main__":
    main()
