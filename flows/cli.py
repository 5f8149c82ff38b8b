"""``polycubenet``: the command line of the meshing service.

    polycubenet mesh INPUT... -o OUT [--formats vtu,inp] [--size S | --hexes N] [--workers N]
                                     [--dask-address HOST:PORT] [--polycube auto|learned|classical|voxel|oracle]
                                     [--min-sj SJ]
    polycubenet retry OUT            re-run the failed parts of OUT (earlier stages from the cache)
    polycubenet scan DROP -o OUT     mesh what is new or changed in DROP
    polycubenet train --data DIR --run DIR --publish DIR [--steps N] [--count K]
    polycubenet report OUT           rebuild OUT/report.html from the manifest and print the summary

The flows run on the embedded Prefect server unless ``PREFECT_API_URL`` names one.  A
progress bar shows parts done / failed and the ETA; a summary table follows.  The exit
code is non-zero only when the tool itself failed (bad arguments, a crash): a part that
cannot be meshed is a row of the manifest with its error, not a failure of the command.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

EXIT_OK, EXIT_CRASH, EXIT_USAGE = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    from polycubenet import library

    ap = argparse.ArgumentParser(prog="polycubenet", description="All-hex meshing of CAD libraries through polycubes.")
    ap.add_argument("-v", "--verbose", action="store_true", help="show Prefect's logs")
    sub = ap.add_subparsers(dest="command", required=True)

    def runner_args(p):
        p.add_argument("--workers", type=int, default=1, help="local Dask worker processes (default 1)")
        p.add_argument("--dask-address", default=None, help="scheduler of a running Dask cluster")
        p.add_argument("--runner", choices=("dask", "threads"), default="dask",
                       help="task runner: a Dask cluster (default) or a thread pool of --workers threads")

    def mesh_args(p):
        p.add_argument("--formats", default="vtu", help="comma-separated: vtu,vtk,mesh,inp,msh,bdf (default vtu)")
        size = p.add_mutually_exclusive_group()
        size.add_argument("--size", type=float, default=None, help="element size, relative to the part's diagonal")
        size.add_argument("--hexes", type=int, default=None,
                          help="approximate hexes of each part's polycube partition (default 5000); the pillow "
                               "layer adds one hex per boundary quad on top of it")
        p.add_argument("--polycube", choices=("auto", "learned", "classical", "voxel", "oracle"), default="auto",
                       help="auto (default): the model's polycube, the classical chain where it fails validation or "
                            "gives an invalid mesh; learned: the model's only; classical: built from the surface, "
                            "then the voxel polycube as a last resort; voxel: the voxel polycube only; oracle: "
                            "synthetic parts' ground-truth sidecars")
        p.add_argument("--no-fallback", action="store_true", help="no classical fallback (auto becomes learned)")
        p.add_argument("--checkpoint", default=None, help="model checkpoint (default: the shipped one)")
        p.add_argument("--steps", type=int, default=None, help="DDIM steps")
        p.add_argument("--points", type=int, default=None, help="points sampled on each part (default 4096)")
        p.add_argument("--polycube-points", type=int, default=None, help="points of each classical/voxel polycube cloud")
        p.add_argument("--learned-points", type=int, default=None, help="points the model generates (default 4096)")
        p.add_argument("--seed", type=int, default=0)
        p.add_argument("--min-sj", type=float, default=None, metavar="SJ",
                       help="quality bar (default 0.2): a valid mesh whose minimum scaled Jacobian is under it does "
                            "not end the part's chain of polycube sources (the next is tried, the better mesh kept); "
                            "the report marks parts meshed under it")
        p.add_argument("--part-timeout", type=float, default=library.DEFAULT_PART_TIMEOUT,
                       help="seconds one part may run before it becomes a failed row and its worker is restarted "
                            f"(default {library.DEFAULT_PART_TIMEOUT:g}; 0: no limit)")
        p.add_argument("--worker-memory", default=None,
                       help="memory cap of each local Dask worker, e.g. 4GiB (default: the machine's memory shared "
                            "between the workers); a part past it fails and the batch goes on")
        p.add_argument("--keep-largest", action="store_true",
                       help="a file with several solids/shells that do not touch: mesh the largest (default: refuse)")
        p.add_argument("--work", default=None, help="stage files and cache (default OUT/.work)")
        runner_args(p)

    p = sub.add_parser("mesh", help="mesh parts (files, folders, globs) into OUT")
    p.add_argument("inputs", nargs="+")
    p.add_argument("-o", "--out", required=True)
    mesh_args(p)

    p = sub.add_parser("retry", help="re-run the failed parts of OUT")
    p.add_argument("out")
    runner_args(p)

    p = sub.add_parser("scan", help="mesh what is new or changed in DROP")
    p.add_argument("drop")
    p.add_argument("-o", "--out", required=True)
    mesh_args(p)

    p = sub.add_parser("train", help="make data, train, evaluate, publish a checkpoint")
    p.add_argument("--data", required=True)
    p.add_argument("--run", required=True)
    p.add_argument("--publish", required=True)
    p.add_argument("--count", type=int, default=1000, help="synthetic training pairs")
    p.add_argument("--eval-count", type=int, default=50)
    p.add_argument("--steps", type=int, default=2000)
    p.add_argument("--preset", default="cpu")
    p.add_argument("--batch", type=int, default=None)
    p.add_argument("--train-points", type=int, default=None)
    p.add_argument("--gpus", type=int, default=None, help="processes for torchrun (default: the GPUs present)")
    p.add_argument("--resume", action="store_true")

    p = sub.add_parser("report", help="rebuild OUT/report.html and print the summary")
    p.add_argument("out")
    return ap


def _mesh_kwargs(a) -> dict:
    polycube = "learned" if a.polycube == "auto" else a.polycube
    fallback = a.polycube == "auto" and not a.no_fallback
    kw = {"formats": [f.strip() for f in a.formats.split(",") if f.strip()], "polycube": polycube,
          "fallback": fallback, "seed": a.seed}
    kw["part_timeout"] = a.part_timeout if a.part_timeout and a.part_timeout > 0 else None
    if getattr(a, "keep_largest", False):
        kw["load_kw"] = {"keep_largest": True}
    if a.size is not None:
        kw.update(target_size=a.size, target_hexes=None)
    elif a.hexes is not None:
        kw["target_hexes"] = a.hexes
    for src, dst in (("checkpoint", "checkpoint"), ("steps", "steps"), ("points", "n_sample"), ("min_sj", "min_sj"),
                     ("polycube_points", "n_polycube"), ("learned_points", "n_learned"), ("work", "work")):
        if getattr(a, src) is not None:
            kw[dst] = getattr(a, src)
    return kw


class _Bar:
    """tqdm progress bar fed by the flow's progress hook."""

    def __init__(self, total: int, desc: str):
        from tqdm import tqdm

        self.bar = tqdm(total=total, unit="part", desc=desc, file=sys.stderr, dynamic_ncols=True)

    def __call__(self, ev: dict) -> None:
        if ev.get("total") and self.bar.total != ev["total"]:
            self.bar.total = ev["total"]
        self.bar.update(1)
        self.bar.set_postfix_str(f"done {ev['done']} failed {ev['failed']} last {ev['part']}")

    def close(self):
        self.bar.close()

    def __reduce__(self):
        # the hook lives in the flow's process; if a task graph ever drags the hook list along
        # (Dask pickles by value what it cannot import), a worker gets a no-op, not a terminal
        return (_NoHook, ())


class _NoHook:
    def __call__(self, ev: dict) -> None:
        return None


def _run_with_progress(fn, total: int, desc: str):
    from flows import mesh_library as ml

    bar = _Bar(total, desc)
    ml.PROGRESS_HOOKS.append(bar)
    try:
        return fn()
    finally:
        ml.PROGRESS_HOOKS.remove(bar)
        bar.close()


def _print_summary(out: str) -> None:
    from polycubenet import library

    m = library.read_manifest(out)
    rows = m["parts"]
    summary = library.summary_rows(rows)
    print(library.format_table(summary))
    n_ok = sum(r["status"] == "meshed" for r in rows)
    n_bad = sum(r["status"] == "meshed" and not (r.get("quality") or {}).get("valid") for r in rows)
    bar = library.quality_bar(m)
    flagged = library.flagged_counts(summary, bar)
    under = f", {flagged}" if flagged else ""
    print(f"\n{len(rows)} parts: {n_ok} meshed ({n_bad} of them flagged invalid: see quality.json{under}), {len(rows) - n_ok} failed.  manifest: {Path(out) / library.MANIFEST}"
          f"  report: {Path(out) / library.REPORT}")
    last = m.get("last_run") or {}
    if last.get("rejected_polycube_seconds"):
        print(f"this run: {last.get('seconds', 0):.0f} s, of which {last['rejected_polycube_seconds']:.0f} s of stage time "
              "went to polycubes that were rejected (see each row's rejected_* timings)")


def main(argv: list[str] | None = None) -> int:
    a = _parser().parse_args(argv)
    if not a.verbose:
        os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
        os.environ.setdefault("PREFECT_LOGGING_TO_API_WHEN_MISSING_FLOW", "ignore")
        os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    # the embedded server's first start on a fresh machine builds its database; Prefect waits 20 s by default,
    # which a machine busy with other work misses (seen: `polycubenet mesh` beside two data generators and a
    # training run on 2 cores failed "Timed out while attempting to connect to ephemeral Prefect API server")
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")

    from polycubenet import library

    if a.command == "report":
        if not (Path(a.out) / library.MANIFEST).is_file():
            print(f"polycubenet: {a.out} has no {library.MANIFEST}", file=sys.stderr)
            return EXIT_USAGE
        manifest = library.read_manifest(a.out)
        library.write_report_html(a.out, manifest["parts"], min_sj=library.quality_bar(manifest))
        _print_summary(a.out)
        return EXIT_OK

    try:
        if a.command == "mesh":
            parts = library.discover(a.inputs, exclude=[a.out])
            if not parts:
                print(f"polycubenet: no parts found under {a.inputs}", file=sys.stderr)
                return EXIT_USAGE
            kw = _mesh_kwargs(a)
        elif a.command == "scan":
            kw = _mesh_kwargs(a)
        elif a.command == "retry" and not (Path(a.out) / library.MANIFEST).is_file():
            print(f"polycubenet: {a.out} has no {library.MANIFEST}", file=sys.stderr)
            return EXIT_USAGE
    except (FileNotFoundError, ValueError) as exc:
        print(f"polycubenet: {exc}", file=sys.stderr)
        return EXIT_USAGE

    from flows.runners import make_runner

    try:
        if a.command == "mesh":
            from flows.mesh_library import mesh_library

            flow = mesh_library.with_options(task_runner=make_runner(a.workers, a.dask_address, a.runner, a.worker_memory))
            _run_with_progress(lambda: flow(inputs=[str(p) for p in parts], out=a.out, **kw), len(parts), "mesh")
            _print_summary(a.out)
        elif a.command == "retry":
            from flows.retry_failed import retry_failed

            n = sum(r["status"] == "failed" for r in library.read_manifest(a.out)["parts"])
            _run_with_progress(lambda: retry_failed(out=a.out, workers=a.workers, dask_address=a.dask_address,
                                                    runner=a.runner), n, "retry")
            _print_summary(a.out)
        elif a.command == "scan":
            from flows.scan_drops import changed_parts, scan_drops

            new, changed = changed_parts(a.drop, a.out)
            print(f"{a.drop}: {len(new)} new, {len(changed)} changed parts")
            if new or changed:
                opts = {k: v for k, v in kw.items() if k not in ("polycube", "formats", "target_hexes", "target_size")}
                _run_with_progress(lambda: scan_drops(
                    drop=a.drop, out=a.out, polycube=kw["polycube"], formats=kw["formats"],
                    target_hexes=kw.get("target_hexes", 5000), target_size=kw.get("target_size"), workers=a.workers,
                    dask_address=a.dask_address, runner=a.runner, mesh_options=opts), len(new) + len(changed), "scan")
                _print_summary(a.out)
        elif a.command == "train":
            from flows.train import train

            res = train(data=a.data, run=a.run, publish_to=a.publish, count=a.count, eval_count=a.eval_count,
                        steps=a.steps, preset=a.preset, batch=a.batch, points=a.train_points, gpus=a.gpus,
                        resume=a.resume)
            print(f"published {res['checkpoint']} with metrics {res['metrics']}")
    except KeyboardInterrupt:
        print("polycubenet: interrupted; run the same command again to resume from the cache", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - the tool itself failed: say so, exit non-zero
        print(f"polycubenet: {a.command} failed: {type(exc).__name__}: {exc}", file=sys.stderr)
        return EXIT_CRASH
    return EXIT_OK


def leave(code: int) -> None:
    """End the process with ``code`` once Python's own exit work is done, without running the C
    libraries' destructors.

    Python's exit work (joining non-daemon threads, the ``atexit`` handlers: logging, the embedded
    Prefect server, the Dask cluster) runs first and the streams are flushed; only ``_dl_fini`` is
    skipped.  There, when open3d ran in one worker thread and a native library (gmsh, prefect's
    dependencies, ...) was first loaded in another, libEGL's destructor aborts the process
    (``malloc_consolidate(): unaligned fastbin chunk detected``, rc 134) after every output was
    written: a batch script would read a complete run as a crash (``--runner threads``).
    """
    import atexit
    import threading

    threading._shutdown()  # what the interpreter does first at exit: wait for non-daemon threads
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass
    os._exit(code)


def entry() -> None:
    """The ``polycubenet`` console script: :func:`main`, then :func:`leave`."""
    leave(main())


if __name__ == "__main__":
    entry()
