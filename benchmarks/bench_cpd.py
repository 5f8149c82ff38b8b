"""Non-rigid CPD: our low-rank, truncated CPD against pycpd's dense DeformableRegistration.

The pair: ``n`` Poisson-disk samples ``Y`` of an L-block in the canonical frame
(bounding-box diagonal 1), and ``X = warp(Y')`` with ``Y'`` an *independent* sample of
the same surface (seed 1) and ``warp`` a known smooth map
``p + a sin(2 pi p_(y,z,x) / wavelength)`` (a = 0.05, wavelength = 1).  There are no
exact point pairs (as between a polycube cloud and a part sample), but every moving
point's true target is known: the error is ``mean |T(y) - warp(y)|``, relative to the
warp's mean magnitude ``mean |warp(y) - y|``.  The part of the warp that slides along
the surface is only constrained by the smoothness prior, so neither method drives this
to zero.  (With ``X = warp(Y)`` exactly, sigma^2 collapses towards 0 and pycpd divides
by zero -- its update gives NaN.)

BLAS runs single-threaded for both (``--threads``): this machine's two cores are shared,
and oversubscribed OpenBLAS threads made timings swing by 5x between identical runs.

Fairness: both get the same data, the same ``beta``, ``lambda`` (pycpd's ``alpha``),
``w`` and the same sigma^2 initialisation (the dense all-pairs mean).  pycpd costs
seconds per iteration at 4096 points, so it runs a capped number of iterations
(``--pycpd-iters``, its tolerance set to ~0 so it does exactly that many).  Two
comparisons are reported:

* equal iterations -- ours also runs exactly ``--pycpd-iters`` iterations, single level
  (``coarse=None``, so no cheap coarse iterations on top): time ratio and both errors;
* to convergence -- ours with its defaults (coarse-to-fine, default stopping rule);
  pycpd's time is *extrapolated* to as many full-size iterations as our finest level
  ran (its measured set-up + its measured per-iteration time x that count; our coarse
  iterations are not counted for it), and its error is the one it had reached at the
  cap (it would improve with more iterations; that column says so).

* both to the same full budget at a smaller size (``--full-n``, default 1024, where
  pycpd is affordable): ``--full-iters`` (100) iterations each, no early stop -- the
  error comparison at convergence.

Then our time alone at 1k, 4k and 16k points (default stopping rule).  Prints a table, writes
``benchmarks/results/bench_cpd.json``.  Needs ``pip install pycpd`` (benchmark only).

    python benchmarks/bench_cpd.py [--n 4096] [--pycpd-iters 10] [--sizes 1024 4096 16384]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

if __name__ == "__main__":  # BLAS threads must be fixed before numpy loads
    _t = sys.argv[sys.argv.index("--threads") + 1] if "--threads" in sys.argv else "1"
    for _v in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(_v, _t)

import numpy as np
import trimesh

from polycubenet.frame import canonicalize
from polycubenet.registration import CPD_BETA, CPD_LAMBDA, CPD_W, cpd_nonrigid
from polycubenet.sampling import poisson_disk


def lblock() -> tuple[np.ndarray, np.ndarray]:
    a = trimesh.creation.box(bounds=[[0, 0, 0], [3, 1, 1]])
    b = trimesh.creation.box(bounds=[[0, 0, 1], [1, 1, 2]])
    m = trimesh.boolean.union([a, b], engine="manifold").subdivide().subdivide()
    V, _ = canonicalize(np.asarray(m.vertices, float), np.asarray(m.faces), rotate=False)
    return V, np.asarray(m.faces, np.int64)


def warp(p: np.ndarray, a: float = 0.05, wavelength: float = 1.0) -> np.ndarray:
    return p + a * np.sin(2.0 * np.pi / wavelength * p[:, [1, 2, 0]])


def make_pair(V, F, n):
    """Moving ``Y (n, 3)``, fixed ``X (n, 3)`` (warped independent sample), true targets ``warp(Y)``."""
    Y = poisson_disk(V, F, n, seed=0).points
    X = warp(poisson_disk(V, F, n, seed=1).points)
    return Y, X, warp(Y)


def rel_error(T: np.ndarray, Xt: np.ndarray, Y: np.ndarray) -> float:
    """``mean |T - Xt| / mean |Xt - Y|`` with ``Xt`` the true targets of ``Y``."""
    return float(np.linalg.norm(T - Xt, axis=1).mean() / np.linalg.norm(Xt - Y, axis=1).mean())


def run_ours(Y, X, Xt, **kw) -> dict:
    t0 = time.perf_counter()
    r = cpd_nonrigid(Y, X, beta=CPD_BETA, lam=CPD_LAMBDA, w=CPD_W, backend="numpy", **kw)
    t = time.perf_counter() - t0
    return {"time_s": t, "iterations": r.iterations, "converged": r.converged, "rel_error": rel_error(r.points, Xt, Y),
            "sigma2": r.sigma2, "landmarks": int(len(r.landmarks)), "k": r.meta["k"],
            "coarse_levels": r.meta["coarse_levels"], "coarse_iterations": r.meta["coarse_iterations"],
            "fine_iterations": r.meta["fine_iterations"]}


def run_pycpd(Y, X, Xt, iters: int) -> dict:
    from pycpd import DeformableRegistration

    stamps = []
    t0 = time.perf_counter()
    reg = DeformableRegistration(X=X, Y=Y, alpha=CPD_LAMBDA, beta=CPD_BETA, w=CPD_W,
                                 max_iterations=iters, tolerance=1e-300)
    t_setup = time.perf_counter() - t0
    t1 = time.perf_counter()
    TY, _ = reg.register(lambda **kw: stamps.append(time.perf_counter()))
    t_iter = time.perf_counter() - t1
    per_iter = t_iter / max(1, len(stamps))
    return {"setup_s": t_setup, "iter_s": t_iter, "per_iter_s": per_iter, "iterations": len(stamps),
            "time_s": t_setup + t_iter, "rel_error": rel_error(TY, Xt, Y), "sigma2": float(reg.sigma2)}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--n", type=int, default=4096)
    ap.add_argument("--pycpd-iters", type=int, default=10)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 4096, 16384])
    ap.add_argument("--full-n", type=int, default=1024)
    ap.add_argument("--full-iters", type=int, default=100)
    ap.add_argument("--threads", type=int, default=1, help="BLAS threads (set before numpy loads)")
    ap.add_argument("--out", type=Path, default=Path(__file__).parent / "results" / "bench_cpd.json")
    args = ap.parse_args()

    V, F = lblock()
    Y, X, Xt = make_pair(V, F, args.n)
    cpd_nonrigid(Y[:200], X[:200], max_iter=2, backend="numpy")  # warm-up (imports, BLAS)
    print(f"pair: {args.n} x {args.n} L-block samples, warp mean |v| = {np.linalg.norm(Xt - Y, axis=1).mean():.4f}"
          f" (diagonal 1); beta={CPD_BETA} lambda={CPD_LAMBDA} w={CPD_W}")

    ours_eq = run_ours(Y, X, Xt, max_iter=args.pycpd_iters, tol_rel=0.0, coarse=None)
    ours_conv = run_ours(Y, X, Xt)
    py = run_pycpd(Y, X, Xt, args.pycpd_iters)
    py_extrap = py["setup_s"] + py["per_iter_s"] * ours_conv["fine_iterations"]

    equal = {"iterations": args.pycpd_iters, "ours_s": ours_eq["time_s"], "pycpd_s": py["time_s"],
             "speedup": py["time_s"] / ours_eq["time_s"],
             "ours_rel_error": ours_eq["rel_error"], "pycpd_rel_error": py["rel_error"]}
    conv = {"ours_iterations": ours_conv["iterations"], "ours_fine_iterations": ours_conv["fine_iterations"],
            "pycpd_extrapolated_iterations": ours_conv["fine_iterations"], "ours_converged": ours_conv["converged"],
            "ours_s": ours_conv["time_s"], "pycpd_extrapolated_s": py_extrap,
            "speedup_extrapolated": py_extrap / ours_conv["time_s"],
            "ours_rel_error": ours_conv["rel_error"],
            "pycpd_rel_error_at_cap": py["rel_error"]}

    print(f"\n{'comparison':<34} {'ours s':>9} {'pycpd s':>10} {'speedup':>8} {'ours err':>9} {'pycpd err':>10}")
    print(f"{'equal iterations (' + str(args.pycpd_iters) + ')':<34} {equal['ours_s']:>9.2f} {equal['pycpd_s']:>10.1f}"
          f" {equal['speedup']:>7.0f}x {equal['ours_rel_error']:>9.4f} {equal['pycpd_rel_error']:>10.4f}")
    label = f"to convergence ({ours_conv['coarse_iterations']}+{ours_conv['fine_iterations']} it)"
    print(f"{label:<34} {conv['ours_s']:>9.2f}"
          f" {py_extrap:>9.1f}* {conv['speedup_extrapolated']:>7.0f}x {conv['ours_rel_error']:>9.4f}"
          f" {py['rel_error']:>9.4f}**")
    print(f"  pycpd: set-up {py['setup_s']:.1f} s, {py['per_iter_s']:.2f} s per iteration (measured over {py['iterations']})")
    print(f"  * pycpd set-up + per-iteration time x {ours_conv['fine_iterations']} (our full-size iterations; extrapolated, not run);"
          f" ours: coarse levels {ours_conv['coarse_levels']} took {ours_conv['coarse_iterations']} iterations")
    print(f"  ** pycpd's error after its {args.pycpd_iters} iterations (errors are mean |T(y) - warp(y)| / mean |warp(y) - y|)")

    Yf, Xf, Xtf = make_pair(V, F, args.full_n)
    of = run_ours(Yf, Xf, Xtf, max_iter=args.full_iters, tol_rel=0.0)
    pf = run_pycpd(Yf, Xf, Xtf, args.full_iters)
    full = {"n": args.full_n, "iterations": args.full_iters, "ours_s": of["time_s"], "pycpd_s": pf["time_s"],
            "speedup": pf["time_s"] / of["time_s"], "ours_rel_error": of["rel_error"], "pycpd_rel_error": pf["rel_error"],
            "ours_sigma2": of["sigma2"], "pycpd_sigma2": pf["sigma2"]}
    print(f"{'both, ' + str(args.full_iters) + ' it at n=' + str(args.full_n):<34} {full['ours_s']:>9.2f} {full['pycpd_s']:>10.1f}"
          f" {full['speedup']:>7.0f}x {full['ours_rel_error']:>9.4f} {full['pycpd_rel_error']:>10.4f}")

    rows = []
    print(f"\n{'n':>7} {'ours s':>8} {'coarse it':>10} {'fine it':>8} {'landmarks':>10} {'rel err':>9}")
    for n in args.sizes:
        Yn, Xn, Xtn = make_pair(V, F, n)
        r = run_ours(Yn, Xn, Xtn)
        r["n"] = n
        rows.append(r)
        print(f"{n:>7} {r['time_s']:>8.2f} {str(r['coarse_iterations']):>10} {r['fine_iterations']:>8}"
              f" {r['landmarks']:>10} {r['rel_error']:>9.4f}")

    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({
        "machine": platform.node(), "n": args.n, "blas_threads": os.environ.get("OPENBLAS_NUM_THREADS"),
        "command": " ".join(["python"] + sys.argv),
        "params": {"beta": CPD_BETA, "lambda": CPD_LAMBDA, "w": CPD_W, "warp": "p + 0.05 sin(2 pi p[y,z,x])",
                   "pair": "Y = sample(seed 0), X = warp(sample(seed 1)), truth = warp(Y)"},
        "pycpd": py, "ours_equal_iterations": ours_eq, "ours_converged": ours_conv,
        "equal_iterations": equal, "to_convergence": conv, "full_budget_small": full, "sizes": rows,
    }, indent=2))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
