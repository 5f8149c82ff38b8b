"""Parts the project has never seen: how often is the learned polycube accepted on them?

    python benchmarks/unseen_parts.py [--count 16] [--seed 7] [--family blocks|mixed|machined|finished|profiles|turned] [--mesh] [--anchors even] \\
        [--draws default] [--json benchmarks/results/unseen_parts.json]
    python benchmarks/unseen_parts.py --count 16 --seed 61 --family mixed --make-only DIR   # the STEP files only

Builds ``--count`` new CAD-like parts with gmsh's OpenCASCADE kernel, each from its own seed
(none of them is in ``examples/parts``, and the seed decides everything: run with another
``--seed`` for a fresh set): a base block, then 0-2 blocks fused on it (steps and bosses),
0-2 through-holes (round or square), 0-1 pockets and sometimes a slot, with random sizes;
``--family mixed`` or ``machined`` also round bosses, a slanted end and a random rotation (:data:`FAMILIES`:
the mixed family's slanted end carries a knife-edge notch, the machined family's is a plain plane cut;
``finished`` is the machined part with some edges filleted and chamfered, as CAD parts and the examples are).
For each part it runs the learned source exactly as ``mesh_part`` does (the shipped
checkpoint, its default steps, 4096 learned points): generate, outlier filter, structure
extraction with the part's genus; ``--mesh`` also meshes every part (and the examples) through
the learned source alone as ``mesh_part`` runs it (first draw, then the model's further draws:
``polycubenet.policy.LEARNED_DRAWS``) and counts the valid meshes within the Hausdorff bar, and
how many of them the first draw gave.  Prints one row per part and the accepted fraction,
beside the same measure on the 10 example parts; writes the JSON.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


#: the part families: ``mixed`` adds round bosses, a slanted end and a rotation to ``blocks``; its wedge is a
#: box of the part's height turned about a point inside the end, so the wedge's lifted bottom also cuts a
#: thin notch under the slanted face: a convex knife edge whose faces' normals are 180 degrees less the
#: slant apart (135 or more; :func:`knife_edge_deg`), on every slanted end of the five mixed sets (52 of 80
#: parts).  ``machined`` draws exactly the parts of ``mixed`` (same random numbers) with the slanted end a
#: plane cut through the whole end, as a saw or mill leaves it: no notch (the plane still leaves knife
#: edges where it crosses a hole, pocket or slot near the end).  ``finished`` is exactly the ``machined`` part,
#: then finished as CAD parts usually are: 1-4 of its straight edges rounded by a fillet and 0-2 chamfered
#: (:func:`finish_edges`, from random numbers drawn after all of ``machined``'s), the treatment every example
#: part has and no other family does.  ``profiles`` and ``turned`` leave the block generator altogether and draw
#: the kinds of part the examples are (:func:`build_profile`, :func:`build_turned`): extruded L, T, U, Z and stair
#: sections with holes through their legs and sometimes a mitred end; shafts, bushings and flanges with bores,
#: bolt circles, cross holes, flats and keyways.
FAMILIES = ("blocks", "mixed", "machined", "finished", "profiles", "turned")


def build_part(occ, rng: np.random.Generator, family: str = "blocks") -> str:
    """One random machined-style solid in the current gmsh model; returns a short description.
    ``mixed`` and ``machined`` add round bosses, slanted cuts and a rotation about a random axis
    (:data:`FAMILIES`)."""
    if family not in FAMILIES:
        raise ValueError(f"family must be one of {FAMILIES}; got {family!r}")
    if family in ("profiles", "turned"):
        what = (build_profile if family == "profiles" else build_turned)(occ, rng)
        _rotate(occ, rng, what)
        return _one_solid(occ, what)
    curved = family in ("mixed", "machined", "finished")
    L, W, H = rng.uniform(40, 90), rng.uniform(25, 60), rng.uniform(12, 30)
    base = occ.addBox(0, 0, 0, L, W, H)
    what = [f"block {L:.0f}x{W:.0f}x{H:.0f}"]
    solid = [(3, base)]
    for _ in range(rng.integers(0, 3)):  # steps and bosses on top
        l, w = rng.uniform(0.25, 0.6) * L, rng.uniform(0.3, 1.0) * W
        x, y = rng.uniform(0, L - l), rng.uniform(0, W - w)
        h = rng.uniform(0.4, 1.2) * H
        if curved and rng.random() < 0.5:
            r = 0.5 * min(l, w)
            tool = occ.addCylinder(x + r, y + r, H - 1e-3, 0, 0, h, r)
            what.append("round boss")
        else:
            tool = occ.addBox(x, y, H - 1e-3, l, w, h)
            what.append("boss")
        solid, _ = occ.fuse(solid, [(3, tool)])
    occ.synchronize()
    tools = []
    for _ in range(rng.integers(0, 3)):  # through-holes along z
        r = rng.uniform(0.06, 0.14) * min(L, W)
        x, y = rng.uniform(r + 4, L - r - 4), rng.uniform(r + 4, W - r - 4)
        if rng.random() < 0.6:
            tools.append((3, occ.addCylinder(x, y, -5, 0, 0, 3 * H + 10, r)))
            what.append("round hole")
        else:
            tools.append((3, occ.addBox(x - r, y - r, -5, 2 * r, 2 * r, 3 * H + 10)))
            what.append("square hole")
    if rng.random() < 0.5:  # a pocket from the top of the base
        l, w = rng.uniform(0.2, 0.4) * L, rng.uniform(0.2, 0.5) * W
        tools.append((3, occ.addBox(rng.uniform(3, L - l - 3), rng.uniform(3, W - w - 3), 0.5 * H, l, w, 3 * H)))
        what.append("pocket")
    if rng.random() < 0.3:  # a slot across the part
        w = rng.uniform(0.1, 0.2) * W
        tools.append((3, occ.addBox(-5, rng.uniform(3, W - w - 3), rng.uniform(0.5, 0.8) * H, L + 10, w, 3 * H)))
        what.append("slot")
    if curved and rng.random() < 0.6:  # a slanted cut across one end
        a = rng.uniform(20, 45)
        if family == "mixed":  # the box's bottom, lifted by the turn, notches the part (FAMILIES)
            wedge = occ.addBox(-L, -5, 0, L, W + 10, 3 * H)
        else:  # a half-space: its only face near the part is the cutting plane
            wedge = occ.addBox(-4 * L, -5, -10 * H, 4 * L, W + 10, 20 * H)
        occ.rotate([(3, wedge)], 0, 0, H * rng.uniform(0.3, 0.7), 0, 1, 0, -np.radians(a))
        occ.translate([(3, wedge)], rng.uniform(0.1, 0.25) * L, 0, 0)
        tools.append((3, wedge))
        what.append(f"slanted end {a:.0f} deg")
    if tools:
        solid, _ = occ.cut(solid, tools)
    occ.synchronize()
    if curved:
        _rotate(occ, rng, what)
    if family == "finished":
        what.extend(finish_edges(occ, np.random.default_rng(rng.integers(1 << 62)), min(H, W)))
    return _one_solid(occ, what)


def _rotate(occ, rng: np.random.Generator, what: list[str]) -> None:
    """Turn the model about a random axis through the origin by up to half a turn."""
    axis = rng.normal(size=3)
    occ.rotate(occ.getEntities(3), 0, 0, 0, *axis, rng.uniform(0, np.pi))
    occ.synchronize()
    what.append("rotated")


def _one_solid(occ, what: list[str]) -> str:
    """The description of a build that left exactly one solid (else RuntimeError)."""
    vols = occ.getEntities(3)
    if len(vols) != 1:
        raise RuntimeError(f"{len(vols)} volumes")
    return ", ".join(what)


def _free_span(leg: tuple, others: list[tuple], axis: int) -> tuple[float, float]:
    """The longest stretch of the section box ``leg`` = (x, y, w, h) along ``axis`` (0: x, 1: y) that no box of
    ``others`` covers: where a hole through the leg meets no other leg."""
    lo, hi = leg[axis], leg[axis] + leg[2 + axis]
    cuts = sorted((o[axis], o[axis] + o[2 + axis]) for o in others
                  if o[1 - axis] < leg[1 - axis] + leg[3 - axis] and leg[1 - axis] < o[1 - axis] + o[3 - axis])
    best, start = (lo, lo), lo
    for a, b in cuts + [(hi, hi)]:
        if min(a, hi) - start > best[1] - best[0]:
            best = (start, min(a, hi))
        start = max(start, b)
    return best


def build_profile(occ, rng: np.random.Generator) -> list[str]:
    """An extruded profile (:data:`FAMILIES`): an L, T, U, Z or stair section of legs 15-35 % of the section
    thick, 40-120 long, with 0-3 round or square holes through its legs (each where no other leg meets it) and
    sometimes one end mitred at 20-40 degrees."""
    kind = str(rng.choice(["L", "T", "U", "Z", "stair"]))
    a, b, length = rng.uniform(25, 60), rng.uniform(20, 50), rng.uniform(40, 120)
    t1, t2 = rng.uniform(0.15, 0.35) * b, rng.uniform(0.15, 0.35) * a  # flange (along y), web (along x)
    if kind == "L":
        legs = [(0, 0, a, t1), (0, 0, t2, b)]
    elif kind == "T":
        legs = [(0, b - t1, a, t1), ((a - t2) / 2, 0, t2, b)]
    elif kind == "U":
        legs = [(0, 0, a, t1), (0, 0, t2, b), (a - t2, 0, t2, b)]
    elif kind == "Z":
        legs = [(0, 0, (a + t2) / 2, t1), ((a - t2) / 2, 0, t2, b), ((a - t2) / 2, b - t1, (a + t2) / 2, t1)]
    else:
        n = int(rng.integers(2, 4))
        legs = [(0, 0, a * (n - i) / n, b * (i + 1) / n) for i in range(n)]
    what = [f"{kind} profile {a:.0f}x{b:.0f}x{length:.0f}"]
    solid = [(3, occ.addBox(x, y, 0, w, h, length)) for x, y, w, h in legs]
    if len(solid) > 1:
        solid, _ = occ.fuse(solid[:1], solid[1:])
    tools, holes = [], []
    for _ in range(rng.integers(0, 4)):
        k = int(rng.integers(len(legs)))
        x, y, w, h = legs[k]
        along = 0 if w >= h else 1  # the leg's long side in the section; the hole goes through its thickness
        lo, hi = _free_span(legs[k], legs[:k] + legs[k + 1:], along)
        r = rng.uniform(0.15, 0.35) * min(hi - lo, length)
        if hi - lo < 2 * r + 4 or r < 1.5:
            continue
        c, z = rng.uniform(lo + r + 2, hi - r - 2), rng.uniform(r + 3, length - r - 3)
        if any(k == k2 and np.hypot(c - c2, z - z2) < 1.5 * (r + r2) + 2 for k2, c2, z2, r2 in holes):
            continue  # it would run into a hole already drilled in this leg: one hole each, as described
        holes.append((k, c, z, r))
        depth = (h, w)[along] + 10
        start = [0.0, 0.0]
        start[along], start[1 - along] = c, (y, x)[along] - 5
        d = [0.0, 0.0, 0.0]
        d[1 - along] = depth
        if rng.random() < 0.6:
            tools.append((3, occ.addCylinder(start[0], start[1], z, *d, r)))
            what.append("round hole")
        else:
            corner = [start[0] - r * (along == 0), start[1] - r * (along == 1), z - r]
            size = [2 * r if along == 0 else depth, 2 * r if along == 1 else depth, 2 * r]
            tools.append((3, occ.addBox(*corner, *size)))
            what.append("square hole")
    if rng.random() < 0.3:  # one end mitred: the half-space beyond a plane through the end, tilted about y
        ang = rng.uniform(20, 40)
        cut = occ.addBox(-4 * a, -4 * b, length, 8 * a, 8 * b, 4 * length)
        occ.rotate([(3, cut)], a / 2, 0, length, 0, 1, 0, np.radians(ang))
        occ.translate([(3, cut)], 0, 0, -0.5 * a * np.tan(np.radians(ang)) - 2)
        tools.append((3, cut))
        what.append(f"mitred end {ang:.0f} deg")
    if tools:
        solid, _ = occ.cut(solid, tools)
    occ.synchronize()
    return what


def build_turned(occ, rng: np.random.Generator) -> list[str]:
    """A turned part (:data:`FAMILIES`): 2-4 coaxial steps (radius 8-30, length 6-35), sometimes a flange disc
    at one end with 3-6 bolt holes, a through bore, a cross hole through one step, a flat milled on one step
    or a keyway cut along one."""
    n = int(rng.integers(2, 5))
    radii, lengths = rng.uniform(8, 30, n), rng.uniform(6, 35, n)
    z0 = np.concatenate([[0.0], np.cumsum(lengths)])
    solid = [(3, occ.addCylinder(0, 0, z0[i], 0, 0, lengths[i], radii[i])) for i in range(n)]
    solid, _ = occ.fuse(solid[:1], solid[1:])
    what = [f"shaft of {n} steps, radius {radii.min():.0f}-{radii.max():.0f}, length {z0[-1]:.0f}"]
    tools = []
    bore = rng.uniform(0.3, 0.6) * radii.min() if rng.random() < 0.5 else 0.0
    if rng.random() < 0.35:  # a flange at the start, with a bolt circle
        big = radii.max() * rng.uniform(1.5, 2.1)
        thick = rng.uniform(4, 10)
        solid, _ = occ.fuse(solid, [(3, occ.addCylinder(0, 0, -thick + 1e-3, 0, 0, thick, big))])
        k = int(rng.integers(3, 7))
        rc = 0.5 * (big + radii[0])
        rb = min(0.3 * (big - radii[0]), 0.6 * np.pi * rc / k)
        if rb >= 1.5:
            for j in range(k):
                phi = 2 * np.pi * j / k
                tools.append((3, occ.addCylinder(rc * np.cos(phi), rc * np.sin(phi), -thick - 5, 0, 0, thick + 10, rb)))
            what.append(f"flange radius {big:.0f} with {k} bolt holes")
        else:
            what.append(f"flange radius {big:.0f}")
    if bore:
        tools.append((3, occ.addCylinder(0, 0, -20, 0, 0, z0[-1] + 40, bore)))
        what.append(f"bore radius {bore:.0f}")
    i = int(rng.integers(n))
    if rng.random() < 0.3 and lengths[i] > 10:  # a cross hole through step i
        rx = rng.uniform(0.15, 0.3) * min(radii[i], lengths[i])
        tools.append((3, occ.addCylinder(-2 * radii.max() - 5, 0, z0[i] + lengths[i] / 2, 4 * radii.max() + 10, 0, 0, rx)))
        what.append("cross hole")
    elif rng.random() < 0.3:  # a flat milled on step i, over its whole length
        d = rng.uniform(0.6, 0.85) * radii[i]
        tools.append((3, occ.addBox(d, -radii[i] - 1, z0[i], radii[i], 2 * radii[i] + 2, lengths[i])))
        what.append("flat")
    elif rng.random() < 0.3 and lengths[i] > 12:  # a keyway along step i
        w = 0.3 * radii[i]
        tools.append((3, occ.addBox(-w / 2, radii[i] - 0.25 * radii[i], z0[i] + 0.2 * lengths[i], w, radii[i], 0.6 * lengths[i])))
        what.append("keyway")
    if tools:
        solid, _ = occ.cut(solid, tools)
    occ.synchronize()
    return what


def finish_edges(occ, rng: np.random.Generator, size: float) -> list[str]:
    """Round 1-4 random straight edges of the one solid in the model with a fillet and chamfer 0-2 more
    (radius / distance 1 mm to a fifth of ``size``, at most a third of the edge's length); an edge that OCC
    cannot finish is left sharp and the next one tried.  Returns what was done, for the description."""
    import gmsh

    done = []
    for kind, count in (("fillet", int(rng.integers(1, 5))), ("chamfer", int(rng.integers(0, 3)))):
        made = tries = 0
        while made < count and tries < 12:
            tries += 1
            (vol,) = occ.getEntities(3)
            curves = occ.getEntities(1)
            straight = [c for d, c in curves if gmsh.model.getType(d, c) == "Line"]
            if not straight:
                break
            c = straight[int(rng.integers(len(straight)))]
            length = occ.getMass(1, c)
            r = min(rng.uniform(1.0, max(1.0, 0.2 * size)), length / 3)
            try:
                if kind == "fillet":
                    out = occ.fillet([vol[1]], [c], [r], removeVolume=False)
                else:
                    up, _ = gmsh.model.getAdjacencies(1, c)  # the faces the edge bounds: measured from the first
                    out = occ.chamfer([vol[1]], [c], [int(up[0])], [r], removeVolume=False)
                occ.synchronize()
            except Exception:  # noqa: BLE001 - OCC refuses this edge (too short, meets a curved face): another
                continue
            new = [e for e in out if e[0] == 3]
            if len(new) != 1:  # OCC gave no solid (or split it): keep the part as it was
                if out:
                    occ.remove(out, recursive=True)
                    occ.synchronize()
                continue
            occ.remove([vol], recursive=True)
            occ.synchronize()
            made += 1
            done.append(f"{kind} {r:.1f}")
    return done


def knife_edge_deg(path: Path) -> float:
    """The sharpest convex edge of a part: the largest angle (degrees) between the normals of two
    triangles that meet on a convex edge, 90 on a box; above 135 a knife edge whose faces meet at
    less than 45 degrees (:data:`FAMILIES`; :func:`polycubenet.io.sharpest_convex_edge_deg`)."""
    from polycubenet.io import load_part

    return float(load_part(path).meta["sharpest_edge_deg"])


def _build_step(path: Path, seed: int, k: int, family: str) -> None:
    """Build part ``k`` of ``seed`` and write it to ``path``, its description beside it (``.txt``); run in a
    child process by :func:`make_parts`.  A build that OpenCASCADE refuses (a fillet that splits the solid, ...)
    exits with status 1 and one line on stderr, not a traceback: :func:`make_parts` skips that draw."""
    from polycubenet.io import gmsh_session, quiet_stdout

    with gmsh_session() as gmsh:
        gmsh.model.add(path.stem)
        try:
            desc = build_part(gmsh.model.occ, np.random.default_rng([seed, k]), family)
            with quiet_stdout():
                gmsh.write(str(path))
        except Exception as exc:  # noqa: BLE001 - any refused build: this draw is skipped
            print(f"{path.stem}: build refused, skipped ({type(exc).__name__}: {exc})", file=sys.stderr)
            raise SystemExit(1) from None
        finally:
            gmsh.model.remove()
    path.with_suffix(".txt").write_text(desc)


def make_parts(folder: Path, count: int, seed: int, family: str = "blocks") -> list[tuple[Path, str]]:
    """``count`` parts of ``family`` from ``seed`` as STEP files in ``folder``, with their descriptions.  Each
    is built in a child process: OpenCASCADE can crash (a fillet of ``finished``, seed 211 part 8) or hang on
    a random build, and then that draw is skipped, as one that OCC refuses or that does not load as one closed
    solid is."""
    import multiprocessing

    from polycubenet.io import load_part

    ctx = multiprocessing.get_context("spawn")
    out = []
    k = 0
    while len(out) < count and k < 4 * count:
        path = folder / f"{family}_{seed}_{k:03d}.step"
        child = ctx.Process(target=_build_step, args=(path, seed, k, family))
        child.start()
        child.join(120)
        if child.is_alive():
            child.kill()
            child.join()
        k += 1
        if child.exitcode != 0 or not path.with_suffix(".txt").exists():
            path.unlink(missing_ok=True)
            continue
        desc = path.with_suffix(".txt").read_text()
        path.with_suffix(".txt").unlink()
        try:
            load_part(path)
        except Exception:  # noqa: BLE001 - a shape that does not load as one closed solid: next one
            path.unlink()
            continue
        out.append((path, desc))
    return out


def set_paths(spec: str, tmp: Path, count: int = 16) -> list[Path]:
    """The STEP files of a ``--sets`` entry: ``examples`` (``examples/parts/*.step``), a folder of STEP files, or a
    never-seen ``family:seed`` set of ``count`` parts built into ``tmp`` (:func:`make_parts`)."""
    if spec == "examples":
        return sorted((ROOT / "examples/parts").glob("*.step"))
    if Path(spec).is_dir():
        return sorted(Path(spec).glob("*.step"))
    family, seed = spec.split(":")
    folder = tmp / spec.replace(":", "_")
    folder.mkdir(parents=True)
    return [p for p, _ in make_parts(folder, count, int(seed), family)]


def meets_bars(r, cfg) -> bool:
    """Whether a ``mesh_part`` result counts: its mesh valid, within the Hausdorff bar of the part
    (:func:`polycubenet.policy.faithful`) and at least the quality bar ``cfg.min_sj``."""
    from polycubenet.policy import faithful

    q = r.report
    return bool(q is not None and q.valid and faithful(r.mesh.meta)
                and (cfg.min_sj is None or (q.sj_min is not None and q.sj_min >= cfg.min_sj)))


def parse_draws(text: str) -> tuple | None:
    """A ``--draws`` table of the model's further draws: None for ``default`` (the policy's
    ``LEARNED_DRAWS``), else ``LEARNED_DRAWS``-shaped tuples from entries
    ``STEPS/SEED/FALLBACKS/TURN[/ANCHORS[/STRETCH]]`` joined by commas (FALLBACKS ``y``/``n``; TURN ``x``, ``y``,
    ``z`` or ``-`` for none; ANCHORS ``uniform`` (the default) or ``even``,
    :data:`polycubenet.inference.ANCHOR_SPREADS`; STRETCH the exponent of
    :func:`polycubenet.inference.stretch_factors`)."""
    from polycubenet.inference import ANCHOR_SPREADS

    if text == "default":
        return None
    table = []
    for entry in text.split(","):
        fields = entry.split("/")
        if (len(fields) not in (4, 5, 6) or fields[2] not in ("y", "n") or fields[3] not in ("x", "y", "z", "-")
                or (len(fields) >= 5 and fields[4] not in ANCHOR_SPREADS)):
            raise ValueError(f"bad --draws entry {entry!r}: expected STEPS/SEED/y|n/x|y|z|-[/uniform|even[/STRETCH]]")
        row = (int(fields[0]), int(fields[1]), fields[2] == "y", None if fields[3] == "-" else fields[3])
        table.append(row + tuple(fields[4:5]) + tuple(float(f) for f in fields[5:6]))
    return tuple(table)


def use_even_anchors() -> None:
    """For this process: the model's anchors drawn as a Poisson-disk sample of the part (blue noise, as
    the model's training anchors and the held-out pairs' are spread) instead of the pipeline's
    independent area-uniform samples (:func:`polycubenet.inference.part_anchors`), for both the first-draw
    rows and ``--mesh``.  A measurement, not a pipeline setting: the flow's cache key does not know it."""
    from polycubenet import inference

    base = inference.part_anchors

    def even(V, F, n, seed=0, normals=False, spread="uniform"):  # every draw's, whatever it asks for
        return base(V, F, n, seed, normals, spread="even")

    inference.part_anchors = even


def map_name(meta: dict) -> str:
    """The map that made a kept mesh, as the row's last column: ``registration``, ``exact`` (realised),
    ``exact, N inserted`` where the realisation put back N thin slabs of the part
    (:func:`polycubenet.realise.match_structure`), or ``exact, part's structure`` where it kept the part's own
    solid on the learned labels (``RealiseConfig.own_structure``)."""
    name = str(meta.get("map")).split(" (")[0]
    realised = meta.get("realised") or {}
    if name == "exact" and realised.get("structure", "learned") != "learned":
        return "exact, part's structure"
    inserted = realised.get("inserted_slabs") or 0
    return f"{name}, {inserted} inserted" if name == "exact" and inserted else name


def mesh_learned(paths: list[Path], checkpoint: str, steps: int, draw_seed: int = 0,
                 learned_maps: tuple[str, ...] | None = None, snap_planes: float | str | None = "default",
                 draws: tuple | None = None, first_anchors: str = "uniform", spot_mend: bool = True,
                 mend_moves: int | None = None, own_structure: bool | None = None,
                 sheets: bool | None = None, strips: bool | str | None = None, hexes: int = 3000) -> dict:
    """Mesh through the learned source only (``--polycube learned``: the first draw at ``steps``,
    then the model's further draws, ``polycubenet.policy.LEARNED_DRAWS``; no classical fallback), as
    ``mesh_part`` does: name -> (valid, faithful and at least the quality bar ``min_sj``, SJ min,
    which draw was kept: 1, 2, ... or None, seconds, the mesh's distance to the part (Hausdorff /
    diagonal), why the first draw was left, the map that made the kept mesh: ``registration`` or
    ``exact (realised)``, :func:`polycubenet.pipeline.pull_back_learned`).  ``draw_seed``: the model's noise
    seed (``ModelSource(seed=...)``; 0 as the pipeline runs it), to see what other draws would give.
    ``learned_maps``: ``PipelineConfig.learned_maps`` (None: the default, the registration alone).
    ``snap_planes``: ``PipelineConfig.snap_planes`` (``"default"``: the pipeline's; None: off).
    ``draws``: the model's further draws (:func:`parse_draws`; None: ``policy.LEARNED_DRAWS``).
    ``first_anchors``: the first draw's anchor spread (``ModelSource(anchors=...)``; the further draws take
    theirs from the table).  ``spot_mend``: ``PullbackConfig.capture_spots`` (False: meshes off the part are not
    mended, the code before session 45).  ``own_structure``: ``RealiseConfig.own_structure`` (None: the config's; False:
    a realisation keeps the learned structure or nothing, the code before session 65).  ``sheets``: False merges close
    planes that face opposite ways (``ExtractConfig.sheet_bandwidths=None``, the code before session 70; None: the
    config's).  ``strips``: the realisation's thin-strip rule (``ClassicalConfig.keep_strips`` and
    ``RealiseConfig.keep_sheets`` together; ``"repair"``: ``keep_strips`` alone; None: the configs').  Each row ends with whether
    the kept mesh's spots were mended.  ``hexes``: ``PipelineConfig.target_hexes`` (3000 in every figure of
    sessions 66-88; the product's default is 5000)."""
    from polycubenet import policy
    from polycubenet.inference import ModelSource
    from polycubenet.pipeline import PipelineConfig, mesh_part
    from polycubenet.policy import refinement

    if draws is not None:  # the policy's table for these parts only
        saved = policy.LEARNED_DRAWS
        policy.LEARNED_DRAWS = draws
        try:
            return mesh_learned(paths, checkpoint, steps, draw_seed, learned_maps, snap_planes,
                                first_anchors=first_anchors, spot_mend=spot_mend, mend_moves=mend_moves,
                                own_structure=own_structure, sheets=sheets, strips=strips, hexes=hexes)
        finally:
            policy.LEARNED_DRAWS = saved

    res = {}
    cfg = PipelineConfig(polycube="learned", target_hexes=int(hexes))
    if learned_maps:
        cfg = dataclasses.replace(cfg, learned_maps=tuple(learned_maps))
    if snap_planes != "default":
        cfg = dataclasses.replace(cfg, snap_planes=snap_planes)
    if mend_moves is not None:
        cfg = dataclasses.replace(cfg, extract=dataclasses.replace(cfg.extract, mend_moves=int(mend_moves)))
    if sheets is False:
        cfg = dataclasses.replace(cfg, extract=dataclasses.replace(cfg.extract, sheet_bandwidths=None))
    if own_structure is not None and cfg.realise is not None:
        cfg = dataclasses.replace(cfg, realise=dataclasses.replace(cfg.realise, own_structure=bool(own_structure)))
    if strips is not None and cfg.realise is not None:
        cfg = dataclasses.replace(cfg, realise=dataclasses.replace(
            cfg.realise, keep_sheets=strips is True,
            classical=dataclasses.replace(cfg.realise.classical, keep_strips=strips in (True, "repair"))))
    if not spot_mend:
        cfg = dataclasses.replace(cfg, pullback=dataclasses.replace(cfg.pullback, capture_spots=False))
    for p in paths:
        t0 = time.perf_counter()
        try:
            r = mesh_part(p, ModelSource(checkpoint, steps=steps, seed=draw_seed, device="cpu", anchors=first_anchors), cfg)
            q = r.report
            ok = r.provenance == "learned" and meets_bars(r, cfg)
            draw = 1 + refinement(r.source)[1] if r.source else None
            dist = r.row()["hausdorff"]
            res[p.stem] = (ok, None if q is None else q.sj_min, draw if ok else None,
                           round(time.perf_counter() - t0, 1), None if dist is None else round(float(dist), 4),
                           r.fallback_reason, map_name(r.mesh.meta),
                           bool((r.mesh.meta.get("spots") or {}).get("kept")))
        except Exception as exc:  # noqa: BLE001 - report the failure in the row
            res[p.stem] = (False, f"{type(exc).__name__}", None, round(time.perf_counter() - t0, 1), None, str(exc), None)
    return res


def main(argv=None) -> int:
    from model_failures import part_rows

    from polycubenet.atomic import write_json
    from polycubenet.inference import ANCHOR_SPREADS, DEFAULT_CHECKPOINT

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--count", type=int, default=16)
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--family", choices=FAMILIES, default="blocks",
                    help="blocks: axis-aligned steps, bosses, holes, pockets, slots; mixed: also round bosses, "
                         "slanted cuts (with a knife-edge notch) and a random rotation; machined: the mixed parts "
                         "with each slanted end a plain plane cut; finished: the machined parts with 1-4 edges "
                         "filleted and 0-2 chamfered; profiles: extruded L/T/U/Z/stair sections with holes; turned: "
                         "shafts, bushings and flanges")
    ap.add_argument("--checkpoint", default=str(DEFAULT_CHECKPOINT))
    ap.add_argument("--steps", type=int, default=None,
                    help="DDIM steps (default: the checkpoint's own default_steps, as mesh_part uses)")
    ap.add_argument("--mesh", action="store_true", help="also mesh every part and example through the learned source alone (every draw)")
    ap.add_argument("--draw-seed", type=int, default=0,
                    help="the model's noise seed for --mesh (0: as the pipeline draws; others: what further draws give)")
    ap.add_argument("--learned-maps", default=None,
                    help="with --mesh: the maps a learned polycube is pulled back through, in order, comma-separated "
                         "(PipelineConfig.learned_maps: registration, refined, anchors; default: the registration alone)")
    ap.add_argument("--snap-planes", default="default", metavar="DEG|off",
                    help="PipelineConfig.snap_planes: each planar part face tilted at least DEG from its label's axis "
                         "onto one plane in the learned cloud; off: never (default: the pipeline's)")
    ap.add_argument("--draws", default="default",
                    help="with --mesh: the model's further draws after the first, entries STEPS/SEED/FALLBACKS/TURN"
                         "[/ANCHORS] joined by commas (e.g. 4/0/n/-,1/1/y/z,1/0/y/-/even; default: "
                         "policy.LEARNED_DRAWS)")
    ap.add_argument("--anchors", choices=ANCHOR_SPREADS, default="uniform",
                    help="how the model's anchors are drawn on the part: uniform (the pipeline's: independent "
                         "area-uniform samples) or even (Poisson-disk, blue noise; session 37's measurement, "
                         "see use_even_anchors), for every draw")
    ap.add_argument("--first-anchors", choices=ANCHOR_SPREADS, default="uniform",
                    help="with --mesh: the first draw's anchor spread only (the further draws take theirs from "
                         "--draws), e.g. --first-anchors even --draws 4/0/n/-,1/1/y/-,1/0/y/-/uniform")
    ap.add_argument("--no-spot-mend", action="store_true",
                    help="with --mesh: meshes off the part are not mended (PullbackConfig.capture_spots=False; the "
                         "code before session 45), for a same-code comparison")
    ap.add_argument("--json", default=str(ROOT / "benchmarks/results/unseen_parts.json"))
    ap.add_argument("--make-only", metavar="DIR", help="only write the parts as STEP files into DIR and stop (no model): "
                    "a folder for `polycubenet mesh` or benchmarks/bench_auto_cost.py --parts")
    args = ap.parse_args(argv)
    try:
        draws = parse_draws(args.draws)
    except ValueError as exc:
        ap.error(str(exc))
    if args.make_only:
        Path(args.make_only).mkdir(parents=True, exist_ok=True)
        for p, desc in make_parts(Path(args.make_only), args.count, args.seed, args.family):
            print(f"{p}  {desc}  (sharpest convex edge {knife_edge_deg(p):.0f} deg)")
        return 0
    from polycubenet.inference import resolve_steps

    if args.anchors == "even":
        use_even_anchors()
    args.steps = int(resolve_steps(args.steps, "cpu", args.checkpoint)[1])
    t0 = time.perf_counter()
    folder = Path(tempfile.mkdtemp(prefix="unseen-parts-"))
    made = make_parts(folder, args.count, args.seed, args.family)
    rows, _ = part_rows(args.checkpoint, [p for p, _ in made], 4096, args.steps)
    for r, (p, desc) in zip(rows, made):
        r["shape"] = desc
        r["knife_edge_deg"] = round(knife_edge_deg(p), 1)
    examples = sorted((ROOT / "examples/parts").glob("*.step"))
    maps = tuple(args.learned_maps.split(",")) if args.learned_maps else None
    if args.snap_planes != "default":
        args.snap_planes = None if args.snap_planes == "off" else float(args.snap_planes)
    meshed = mesh_learned([p for p, _ in made], args.checkpoint, args.steps, args.draw_seed, maps,
                          args.snap_planes, draws, args.first_anchors, not args.no_spot_mend) if args.mesh else {}
    ex_meshed = mesh_learned(examples, args.checkpoint, args.steps, args.draw_seed, maps, args.snap_planes,
                             draws, args.first_anchors, not args.no_spot_mend) if args.mesh else {}
    ex_rows, _ = part_rows(args.checkpoint, examples, 4096, args.steps)
    print(f"\n{'part':<18} {'genus':>5} {'first draw':<28} {'learned mesh: SJ, Hausdorff':<28} shape")
    for r in rows:
        m = meshed.get(r["part"])
        ms = "" if m is None else (("valid, draw %d%s" % (m[2], (", " + m[6].replace("exact", "realised", 1)) if str(m[6]).startswith("exact") else "")) if m[0] else "no") + (
            f" {m[1]:.3f}" if isinstance(m[1], float) else f" {m[1]}") + (
            f" {100 * m[4]:.1f}%" if m[4] is not None else "")
        print(f"{r['part']:<18} {r['genus']:>5} {r['category']:<28} {ms:<28} {r['shape']}")
    acc = sum(r["accepted"] for r in rows)
    ex_acc = sum(r["accepted"] for r in ex_rows)
    print(f"\nunseen parts: learned polycube accepted {acc}/{len(rows)} ({acc / max(1, len(rows)):.0%}); "
          f"example parts: {ex_acc}/{len(ex_rows)} ({ex_acc / max(1, len(ex_rows)):.0%})  (first draw, at extraction)")

    def counts(m: dict) -> tuple[int, int, int]:
        return (sum(v[2] == 1 for v in m.values()), sum(bool(v[0]) for v in m.values()),
                sum(bool(v[0]) and str(v[6]).startswith("exact") for v in m.values()))

    if meshed:
        (u1, u, ur), (e1, e, er) = counts(meshed), counts(ex_meshed)
        print(f"meshed valid and faithful through the learned source (--polycube learned): unseen {u}/{len(rows)} "
              f"({u1} by the first draw, {ur} realised exactly), examples {e}/{len(examples)} ({e1} by the first "
              f"draw, {er} realised exactly)")
    write_json(args.json, {"checkpoint": args.checkpoint, "snap_planes": args.snap_planes, "seed": args.seed, "family": args.family, "count": len(rows), "steps": args.steps,
                           "draw_seed": args.draw_seed, "learned_maps": maps, "draws": args.draws, "first_anchors": args.first_anchors,
                           "spot_mend": not args.no_spot_mend,
                           "accepted": acc, "examples_accepted": ex_acc, "examples": len(ex_rows),
                           "meshed_valid": counts(meshed)[1] if meshed else None,
                           "meshed_first_draw": counts(meshed)[0] if meshed else None,
                           "meshed_realised": counts(meshed)[2] if meshed else None,
                           "examples_meshed_realised": counts(ex_meshed)[2] if meshed else None,
                           "examples_meshed_valid": counts(ex_meshed)[1] if meshed else None,
                           "examples_meshed_first_draw": counts(ex_meshed)[0] if meshed else None,
                           "rows": rows, "example_rows": ex_rows,
                           "mesh": {k: list(v) for k, v in meshed.items()},
                           "example_mesh": {k: list(v) for k, v in ex_meshed.items()},
                           "seconds": round(time.perf_counter() - t0, 1)})
    print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
