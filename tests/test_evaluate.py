"""The held-out evaluation's breakdown by the ground truth's thinnest slab."""
import numpy as np
import pytest

from polycubenet.data import Polycube
from polycubenet.evaluate import by_thinnest_slab, thinnest_slab


def test_thinnest_slab_is_the_minimal_grids():
    # two equal cells along x: the plane at 0.02 separates nothing, so the minimal grid drops it
    full = Polycube(np.array([0.0, 0.02, 0.5]), np.array([0.0, 0.3]), np.array([0.0, 0.2]), np.ones((2, 1, 1), bool))
    assert thinnest_slab(full) == pytest.approx(0.2)
    # an L: one cell of the 0.02 slab empty along y, so that slab is a real step
    occ = np.ones((2, 2, 1), bool)
    occ[0, 1, 0] = False
    step = Polycube(np.array([0.0, 0.02, 0.5]), np.array([0.0, 0.1, 0.3]), np.array([0.0, 0.2]), occ)
    assert thinnest_slab(step) == pytest.approx(0.02)


def test_by_thinnest_slab_bins_and_rates():
    rows = [{"gt_thinnest_slab": t, "exact": e} for t, e in
            [(0.026, True), (0.029, False), (0.029, False), (0.03, True), (0.049, True), (0.05, False), (0.2, True)]]
    b = by_thinnest_slab(rows)
    assert list(b) == ["< 0.03", "0.03-0.05", ">= 0.05"]
    assert b["< 0.03"] == {"pairs": 3, "exact": pytest.approx(1 / 3)}
    assert b["0.03-0.05"] == {"pairs": 2, "exact": 1.0}  # 0.03 falls in the upper bin
    assert b[">= 0.05"] == {"pairs": 2, "exact": 0.5}
    assert by_thinnest_slab(rows[:1])["0.03-0.05"] == {"pairs": 0, "exact": None}


def test_plane_errors_count_planes_without_a_partner_within_the_tolerance():
    from polycubenet.evaluate import plane_errors

    occ = np.ones((2, 2, 1), bool)
    occ[0, 1, 0] = False
    gt = Polycube(np.array([0.0, 0.2, 0.5]), np.array([0.0, 0.1, 0.3]), np.array([0.0, 0.2]), occ)
    assert plane_errors(gt, gt) == (0, 0)
    near = Polycube(np.array([0.0, 0.21, 0.5]), np.array([0.0, 0.1, 0.3]), np.array([0.0, 0.2]), occ)
    assert plane_errors(near, gt) == (0, 0)  # 0.01 off: the same plane
    moved = Polycube(np.array([0.0, 0.25, 0.5]), np.array([0.0, 0.1, 0.3]), np.array([0.0, 0.2]), occ)
    assert plane_errors(moved, gt) == (1, 1)  # the step moved: one plane added, one missed
    box = Polycube(np.array([0.0, 0.5]), np.array([0.0, 0.3]), np.array([0.0, 0.2]), np.ones((1, 1, 1), bool))
    assert plane_errors(box, gt) == (0, 2) and plane_errors(gt, box) == (2, 0)  # the step's two planes


def test_evaluate_reads_the_clouds_of_the_generator_it_is_given(tmp_path):
    """``evaluate(generator=...)`` scores that generator's clouds: one that hands back the part's own
    samples scores the identity reference's Chamfer, pair by pair (the model's draws would not)."""
    import dataclasses

    import numpy as np

    from polycubenet.evaluate import evaluate
    from polycubenet.model.checkpoint import publish
    from polycubenet.synth.shards import write_dataset
    from polycubenet.train import TrainConfig, train

    data = tmp_path / "pairs"
    write_dataset(data, count=2, seed=322, per_shard=2, n_cond=128, n_target=128, progress=False)
    cfg = TrainConfig(preset="tiny", steps=2, batch=2, points=64, warmup=1, ckpt_every=2, log_every=1, seed=5, threads=1)
    train(data, tmp_path / "run", cfg, progress=False)
    ck = publish(tmp_path / "run" / "last.pt", tmp_path / "tiny.pt")

    def identity(conds, n, **kw):
        return [np.hstack([np.asarray(c, np.float32)[:n], np.zeros((min(n, len(c)), 3), np.float32)]) for c in conds]

    common = dict(count=2, n_out=128, steps=1, structure=False, progress=False, device="cpu")
    own = evaluate(ck, data, generator=identity, **common)
    drawn = evaluate(ck, data, **common)
    assert [r["chamfer"] for r in own["rows"]] == [r["chamfer_identity"] for r in own["rows"]]
    assert [r["chamfer"] for r in drawn["rows"]] != [r["chamfer_identity"] for r in drawn["rows"]]


def test_feature_class_reads_the_recorded_deformation(tmp_path):
    """A shard's pairs are classed by the cuts their recorded deformation makes: a whole slanted end before a
    chamfered edge before neither; pairs written with ``whole_slants`` include slanted ends, plain ones none."""
    from polycubenet.synth.shards import feature_class, list_shards, load_shard, write_dataset

    assert feature_class(None) is None
    assert feature_class({"maps": [{"kind": "round_edge", "style": "fillet"}]}) == "neither"
    assert feature_class({"maps": [{"kind": "round_edge", "style": "chamfer"}, {"kind": "twist"}]}) == "chamfer"
    assert feature_class({"maps": [{"kind": "round_edge", "style": "chamfer"}, {"kind": "slant_end"}]}) == "slanted end"
    slants, plain = tmp_path / "slants", tmp_path / "plain"
    write_dataset(slants, count=8, seed=6, per_shard=8, n_cond=64, n_target=64, cad_features=True,
                  whole_slants=True, progress=False)
    write_dataset(plain, count=8, seed=6, per_shard=8, n_cond=64, n_target=64, progress=False)
    s, p = load_shard(list_shards(slants)[0]), load_shard(list_shards(plain)[0])
    got = [s.feature(k) for k in range(len(s))]
    assert "slanted end" in got and all(g in ("slanted end", "chamfer", "neither") for g in got)
    assert all(p.feature(k) != "slanted end" for k in range(len(p)))
    for k in range(len(s)):  # the class follows the pair's own maps
        kinds = [m["kind"] for m in s.meta["pairs"][k]["deformation"]["maps"]]
        assert (s.feature(k) == "slanted end") == ("slant_end" in kinds)


def test_by_genus_splits_the_rates_by_the_pairs_own_genus():
    from polycubenet.evaluate import by_genus

    rows = [{"genus": 5, "exact": False, "genus_match": False, "error": "4 components"},
            {"genus": 0, "exact": True, "genus_match": True, "error": None},
            {"genus": 5, "exact": True, "genus_match": True, "error": None},
            {"genus": 0, "exact": False, "genus_match": True, "error": None}]
    b = by_genus(rows)
    assert list(b) == ["0", "5"]  # ascending, only the genera present
    assert b["0"] == {"pairs": 2, "exact": 0.5, "genus_match": 1.0, "extracted": 1.0}
    assert b["5"] == {"pairs": 2, "exact": 0.5, "genus_match": 0.5, "extracted": 0.5}


def test_by_feature_counts_exact_and_extracted_per_class():
    from polycubenet.evaluate import by_feature

    rows = [{"feature": "slanted end", "exact": False, "error": "x"}, {"feature": "slanted end", "exact": True, "error": None},
            {"feature": "neither", "exact": False, "error": None}, {"feature": None, "exact": True, "error": None}]
    b = by_feature(rows)
    assert list(b) == ["slanted end", "neither"]  # no chamfer pair: left out; a row without a class: in none
    assert b["slanted end"] == {"pairs": 2, "exact": 0.5, "extracted": 0.5}
    assert b["neither"] == {"pairs": 1, "exact": 0.0, "extracted": 1.0}


def test_by_ribs_counts_exact_and_extracted_per_number_of_gussets():
    from polycubenet.evaluate import by_ribs

    rows = [{"ribs": 1, "exact": False, "error": "x"}, {"ribs": 1, "exact": True, "error": None},
            {"ribs": 0, "exact": True, "error": None}, {"ribs": None, "exact": False, "error": None},
            {"ribs": 2, "exact": False, "error": None}]
    b = by_ribs(rows)
    assert list(b) == ["0", "1", "2"]  # ascending; a row from a shard without features: in none
    assert b["0"] == {"pairs": 1, "exact": 1.0, "extracted": 1.0}
    assert b["1"] == {"pairs": 2, "exact": 0.5, "extracted": 0.5}
    assert b["2"] == {"pairs": 1, "exact": 0.0, "extracted": 1.0}


def test_slant_moves_reads_the_share_of_the_way_a_generator_takes_slanted_faces(tmp_path):
    """``slant_moves`` scores a generator by how far it takes each part point toward its target's plane: one that
    leaves the part where it is moves nothing, one that returns the targets moves all the way, one halfway 0.5;
    the slanted points are there only where the pairs have slanted faces."""
    from scipy.spatial import cKDTree

    from polycubenet.evaluate import slant_moves
    from polycubenet.synth.shards import list_shards, load_shard, write_dataset

    data = tmp_path / "slants"
    write_dataset(data, count=6, seed=6, per_shard=6, n_cond=256, n_target=256, cad_features=True,
                  whole_slants=True, progress=False)
    s = load_shard(list_shards(data)[0])
    pre = np.concatenate([np.asarray(s["target_on_shape"][k], float) for k in range(len(s))])
    tgt = np.concatenate([np.asarray(s["target_points"][k], float) for k in range(len(s))])
    tree = cKDTree(pre)

    def toward(share):
        def gen(conds, n, *, anchors, **kw):
            out = []
            for a in anchors:
                _, j = tree.query(a[:, :3])  # each anchor is a target point's preimage: its own target
                out.append(np.hstack([a[:, :3] + share * (tgt[j] - a[:, :3]), np.zeros_like(a[:, 3:])]))
            return out
        return gen

    got = {share: slant_moves(None, data, 6, generator=toward(share), progress=False) for share in (0.0, 0.5, 1.0)}
    assert got[1.0]["by_feature"]["slanted end"]["pairs_with_slanted_points"] > 0
    for share, r in got.items():
        assert r["all"]["moved_median"] == pytest.approx(share, abs=1e-6)
    assert got[1.0]["all"]["err_slanted_median"] == pytest.approx(0.0, abs=1e-9)
    assert got[0.5]["all"]["short_rate"] == 1.0 and got[1.0]["all"]["short_rate"] == 0.0
    assert got[0.0]["all"]["err_slanted_median"] > 0.01  # left where it was: at least MIN_MOVE from the plane

    # the step count reaches the generator (a multi-step draw is read as the policy would run it)
    seen = []

    def by_steps(conds, n, *, steps, **kw):
        seen.append(steps)
        return toward(1.0 / steps)(conds, n, **kw)

    r8 = slant_moves(None, data, 6, generator=by_steps, progress=False, steps=8)
    assert set(seen) == {8} and r8["steps"] == 8
    assert r8["all"]["moved_median"] == pytest.approx(1.0 / 8, abs=1e-6)


def test_point_moves_bins_the_slanted_points_by_their_share_of_the_largest_displacement():
    """A ramp left as it was at its pivot end and moved fully at its far end reads 0 in the first bin and 1 in the
    last; the flat points (normal on an axis) are not in the bins."""
    from polycubenet.evaluate import SHARE_BINS, point_moves

    n = 200
    s = np.linspace(0.0, 1.0, n)
    slope = np.tan(np.radians(30.0))
    anchors = np.stack([s, np.zeros(n), 1.0 - 0.2 * s], axis=1)  # a slanted end: 0.2 below the plane z = 1 at s = 1
    normals = np.tile([slope, 0.0, 1.0], (n, 1))
    targets = anchors.copy()
    targets[:, 2] = 1.0
    tn = np.tile([0.0, 0.0, 1.0], (n, 1))
    cloud = anchors + (s > 0.5)[:, None] * (targets - anchors)  # the far half moved, the near half left
    r = point_moves(anchors, normals, cloud, targets, tn)
    assert len(r["moved_by_share"]) == len(SHARE_BINS)
    assert r["moved_by_share"][0] == pytest.approx(0.0) and r["moved_by_share"][-1] == pytest.approx(1.0)
    assert r["slanted_points"] == int((0.2 * s >= 0.01).sum())
