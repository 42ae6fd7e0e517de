"""Soft targets of the box classifier for look-alikes whose distinguishing detail is hidden
(`cosy_cli.detection.classifier_train`: distinguishing points, their visible pixels against the
rendered depth, the targets; fine-tuning from a classifier checkpoint)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from cosy_cli.detection import classifier_train as ct
from cosy_cli.detection.data import visible_probe_pixels
from cosy_cli.errors import CosyError

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
SAMPLES = Path(__file__).resolve().parent.parent / "data_samples"
K = np.array([[500.0, 0, 159.5], [0, 500.0, 119.5], [0, 0, 1]])


def _box(ex=40.0, ey=30.0, ez=20.0):
    import trimesh

    return trimesh.creation.box(extents=(ex, ey, ez))


def _notched_box():
    """The 40 x 30 x 20 mm box (centred) with a slot 8 mm wide, 8 mm deep cut into its -y face
    over the whole height (x in [-4, 4], y in [-15, -7])."""
    import trimesh

    v = np.array([(-20, -15), (-4, -15), (-4, -7), (4, -7), (4, -15), (20, -15), (20, 15), (4, 15), (-4, 15),
                  (-20, 15)], float)
    f = np.array([(0, 1, 2), (0, 2, 8), (0, 8, 9), (2, 3, 7), (2, 7, 8), (3, 4, 5), (3, 5, 6), (3, 6, 7)])
    m = trimesh.creation.extrude_triangulation(v, f, 20.0)
    m.apply_translation((0, 0, -10.0))
    return m


def _facing(side: int, dist: float = 300.0) -> np.ndarray:
    """T_cam_obj: the object's -y face towards the camera (side -1) or its +y face (side +1)."""
    T = np.eye(4)
    T[:3, :3] = np.array([[1, 0, 0], [0, 0, -1], [0, 1, 0]], float) if side < 0 else \
        np.array([[-1, 0, 0], [0, 0, -1], [0, -1, 0]], float)
    T[2, 3] = dist
    return T


# ------------------------------------------------------------------------------------------------
# distinguishing points
# ------------------------------------------------------------------------------------------------
def test_distinguishing_points_are_the_notch_and_none_for_identical_models():
    box, notched = _box(), _notched_box()
    assert notched.is_watertight and abs(notched.volume - (40 * 30 * 20 - 8 * 8 * 20)) < 1e-6
    pa, pb = ct.distinguishing_points(box, notched, np.eye(4), 2.0, n=40_000)
    assert len(pa) > 100 and len(pb) > 100
    # a: the box's surface over the slot, farther than 2 mm from the slot's walls (|x| < 2) and floor
    assert np.all(np.abs(pa[:, 0]) <= 2.5) and np.all(pa[:, 1] <= -9.0 + 0.5)  # + the sampling slack
    # b: the slot's walls and floor, farther than 2 mm from the box's faces
    assert np.all(np.abs(pb[:, 0]) <= 4.0 + 1e-6) and np.all((pb[:, 1] >= -13.5) & (pb[:, 1] <= -7 + 1e-6))
    assert np.all(np.abs(pb[:, 2]) <= 8.5)
    assert np.any(np.abs(pb[:, 1] + 7) < 1e-6) and np.any(np.abs(np.abs(pb[:, 0]) - 4) < 1e-6)  # floor and walls
    qa, qb = ct.distinguishing_points(box, box.copy(), np.eye(4), 2.0, n=40_000)
    assert len(qa) == 0 and len(qb) == 0


def test_lookalike_fits_and_probes_from_the_models():
    meshes = {1: _box(), 2: _notched_box(), 3: _box(60, 30, 20)}
    fits = ct.lookalike_fits(meshes)
    assert [(f.a, f.b, f.frames_agree) for f in fits] == [(1, 2, True)]
    probes, partners = ct.lookalike_probes(meshes, [1, 2, 3], fits=fits, n=20_000)
    assert partners == {1: [2], 2: [1]} and 3 not in probes
    assert np.allclose(probes[1][0], probes[2][0])  # frames agree: the same points in both frames
    # an identical pair has nothing to tell them apart: no probes
    same = {1: _box(), 2: _box()}
    fits = ct.lookalike_fits(same)
    assert len(fits) == 1 and ct.lookalike_probes(same, [1, 2], fits=fits, n=5_000) == ({}, {})
    # on the shipped sample objects: 6 / 7 alone, the probes in the notch (a few mm, not the object)
    from cosy_cli.detection.train import load_dataset_objects

    m, _, _ = load_dataset_objects(SAMPLES)
    probes, partners = ct.lookalike_probes(m, sorted(m), n=20_000)
    assert partners == {6: [7], 7: [6]}
    assert np.ptp(probes[6][0], axis=0).max() < 12.0


# ------------------------------------------------------------------------------------------------
# visible pixels
# ------------------------------------------------------------------------------------------------
def test_visible_probe_pixels_against_a_depth_map():
    depth = np.full((2, 240, 320), 300.0, np.float32)
    depth[1, :, :160] = 0.0  # nothing drawn on the left of image 1
    T = np.stack([np.eye(4), np.eye(4)])
    # 4 points: on the surface (seen), 10 mm behind it (hidden), outside the image, behind the camera
    P = np.array([[0, 0, 300.0], [10, 0, 310.0], [1000, 0, 300.0], [0, 0, -50.0]])
    assert visible_probe_pixels(np.stack([K, K]), T, P, depth).tolist() == [1, 1]
    # image 1: the hidden point's pixel shows... it is at u = 159.5 + 500 * 10 / 310 > 160: still hidden;
    # a point over the empty left half counts (a missing part seen against the background)
    P2 = np.array([[-50, 0, 400.0], [-50.01, 0, 400.0]])  # two points, one pixel
    assert visible_probe_pixels(np.stack([K, K]), T, P2, depth).tolist() == [0, 1]
    # the tolerance: 2 mm + 2 pixel footprints (z / f = 0.6 mm at 300 mm): 3 mm behind counts, 4 mm not
    assert visible_probe_pixels(K[None], np.eye(4)[None], np.array([[0, 0, 303.0]]), depth[:1]).tolist() == [1]
    assert visible_probe_pixels(K[None], np.eye(4)[None], np.array([[0, 0, 304.0]]), depth[:1]).tolist() == [0]
    assert visible_probe_pixels(K[None, :, :], np.eye(4)[None], np.zeros((0, 3)), depth[:1]).tolist() == [0]


def test_rendered_notch_is_seen_from_its_side_only():
    from cosy_cli.rendering import SceneRenderer

    box, notched = _box(), _notched_box()
    pa, pb = ct.distinguishing_points(box, notched, np.eye(4), 2.0, n=40_000)
    probes = np.concatenate([pa, pb])
    occluder = np.eye(4)
    occluder[2, 3] = 200.0  # a big box between the camera and the object
    with SceneRenderer({1: box, 2: notched, 3: _box(100, 100, 10)}, 320, 240, znear=10.0, zfar=5000.0) as r:
        counts = {}
        for name, oid, side, occ in (("box front", 1, -1, False), ("notch front", 2, -1, False),
                                     ("box back", 1, 1, False), ("notch back", 2, 1, False),
                                     ("notch front hidden", 2, -1, True)):
            ids, T = [oid], [_facing(side)]
            if occ:
                ids, T = [oid, 3], [_facing(side), occluder]
            depth = r.render(K, ids, np.stack(T), with_rgb=False).depth
            counts[name] = int(visible_probe_pixels(K[None], _facing(side)[None], probes, depth[None])[0])
    # at 300 mm, 500 px focal (1.7 px / mm): the box's face over the slot, 4 x 20 mm, about 7 x 33 px;
    # the slot's floor, 8 x 16 mm (and the box's face over it, in front of it), about 13 x 27 px; plus
    # the slot's walls where they are within the depth tolerance (3.2 mm) of the face in front
    assert 150 < counts["box front"] < 400 and 250 < counts["notch front"] < 550, counts
    assert counts["box back"] == 0 and counts["notch back"] == 0 and counts["notch front hidden"] == 0, counts


# ------------------------------------------------------------------------------------------------
# targets and settings
# ------------------------------------------------------------------------------------------------
def test_soft_target_rows():
    obj_ids = [6, 7, 8]
    labels = np.array([0, 1, 0, 0, 2, 3, 1])
    px = np.array([[0], [1], [11], [50], [0], [-1], [-1]])
    t = ct.soft_target_rows(labels, px, {6: [7], 7: [6]}, obj_ids, 4, (2, 20))
    assert np.allclose(t.sum(1), 1)
    assert np.allclose(t[0], [0.5, 0.5, 0, 0]) and np.allclose(t[1], [0.5, 0.5, 0, 0])
    assert np.allclose(t[2], np.array([1, 0.5, 0, 0]) / 1.5)  # half way: the partner weighs 1/2
    assert np.allclose(t[3], [1, 0, 0, 0])
    assert np.allclose(t[4], [0, 0, 1, 0]) and np.allclose(t[5], [0, 0, 0, 1]) and np.allclose(t[6], [0, 1, 0, 0])
    # two hidden partners: a third each; no probes: one-hot
    t = ct.soft_target_rows(np.array([0]), np.array([[0, 0]]), {6: [7, 8]}, obj_ids, 4)
    assert np.allclose(t, [[1 / 3, 1 / 3, 1 / 3, 0]])
    assert np.allclose(ct.soft_target_rows(labels, None, {}, obj_ids, 4), np.eye(4)[labels])


def test_soft_target_settings():
    c = ct.resolve_conf(None)
    assert c["soft_targets"] == "lookalike" and c["soft_px"] == [2.0, 20.0] and c["soft_tol_mm"] == 2.0
    assert ct.resolve_conf({"soft_targets": None})["soft_targets"] == "none"
    for bad in ({"soft_targets": "maybe"}, {"soft_px": [20, 2]}, {"soft_px": [1]}, {"soft_tol_mm": 0}):
        with pytest.raises(CosyError):
            ct.resolve_conf(bad)


def test_sampler_gives_soft_targets_to_hidden_notches():
    from cosy_cli.detection.train import load_dataset_objects

    meshes, K0, size = load_dataset_objects(SAMPLES)
    conf = ct.resolve_conf({"confusable": [[6, 7]], "p_pair": 1.0, "class_weights": {"6": 5, "7": 5},
                            "max_objects": 3})
    s = ct.CropSampler(meshes, K0, (320, 240), conf, sorted(meshes), 3)
    try:
        x, y, t = s.batch_targets(48)
    finally:
        s.close()
    assert x.shape == (48, 112, 112, 3) and t.shape == (48, 9) and np.allclose(t.sum(1), 1)
    assert np.all(t[np.arange(48), y] >= 0.5 - 1e-6)
    soft = t.max(1) < 1
    assert soft.any() and np.all(np.isin(y[soft], [5, 6]))  # only objects 6 and 7 (classes 5, 6)
    assert np.allclose(t[soft][:, [5, 6]].sum(1), 1)


def test_fine_tune_from_a_classifier_checkpoint(tmp_path):
    """`cosy train classifier --init RUN/checkpoint.pt`: a new run starting at step 0 from the
    checkpoint's EMA weights; a bad init file is a user error."""
    import torch
    from click.testing import CliRunner

    from cosy_cli.cli.main import cli

    def run(args):
        return CliRunner().invoke(cli, [str(a) for a in args], catch_exceptions=False)

    base = ["train", "classifier", "--dataset", SAMPLES, "--batch-size", 8, "--checkpoint-every", 1]
    r = run(base + ["--out", tmp_path / "a", "--iterations", 1, "--soft-targets", "none"])
    assert r.exit_code == 0, r.output
    a = torch.load(tmp_path / "a" / "checkpoint.pt", map_location="cpu", weights_only=False)
    r = run(base + ["--out", tmp_path / "b", "--iterations", 1, "--lr", 1e-9, "--init", tmp_path / "a" / "checkpoint.pt"])
    assert r.exit_code == 0, r.output
    assert "fine-tuning from the EMA weights" in r.output and "soft targets" in r.output
    b = torch.load(tmp_path / "b" / "checkpoint.pt", map_location="cpu", weights_only=False)
    assert b["step"] == 1 and b["config"]["soft_targets"] == "lookalike"
    wa, wb = a["ema"]["state_dict"], b["model"]["state_dict"]
    conv = next(k for k in wa if k.endswith("weight") and wa[k].ndim == 4)
    assert torch.allclose(wa[conv], wb[conv], atol=1e-5)  # lr 1e-9: the checkpoint's EMA weights
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    r = run(base + ["--out", tmp_path / "c", "--iterations", 1, "--init", tmp_path / "junk.pt"])
    assert r.exit_code == 2 and "junk.pt" in r.output
