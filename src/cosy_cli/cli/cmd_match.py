"""``cosy match`` (multi-view candidate matching) and ``cosy synth-candidates`` (candidates from GT).

Imports stay light (no torch, no trimesh): the stage modules are imported when a command runs.
"""

from __future__ import annotations

import os
from pathlib import Path

import click

from .. import console
from .common import dataset_options, user_errors


@click.command("match")
@dataset_options("BOP dataset folder (scene_camera.json per scene, models/ with models_info.json).")
@click.option("--candidates", "candidates", required=True, type=click.Path(path_type=Path),
              help="Candidates CSV (BOP results: scene_id,im_id,obj_id,score,R,t,time; pose in the camera, mm).")
@click.option("--out", required=True, type=click.Path(path_type=Path),
              help="Output folder: matches.csv, view_pairs.csv, groups.json, candidates.csv.")
@click.option("--conf", default="paper", show_default=True,
              help="Named configuration (paper: the paper's values + cosy's additions (refit, adaptive "
                   "threshold, 1-2 object links); paper-fixed: the fixed 2 cm and >= 3 inliers; paper-norefit: "
                   "as published, also without the least-squares refit).")
@click.option("--views-per-group", type=click.IntRange(min=2), default=None,
              help="Split each scene's images (sorted by im_id) into consecutive groups of N (default: one group).")
@click.option("--known-cameras", is_flag=True,
              help="Take camera poses from cam_R_w2c/cam_t_w2c and only associate candidates (no RANSAC).")
@click.option("--groups", "grouping", type=click.Choice(["scene", "instant", "targets"]), default=None,
              help="Views of a group: scene (all of a scene, or --views-per-group), instant (the sensors' images of "
                   "one im_id, with --sensor rig), targets (one group per entry of "
                   "test_targets_multiview_bop25.json) [scene].")
@click.option("--threshold-mm", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Inlier threshold on the symmetric distance D_l, mm: the floor of the adaptive threshold, "
                   "the threshold itself with --threshold-rel 0 --adaptive-k 0 [paper: 20].")
@click.option("--threshold-rel", type=click.FloatRange(min=0), default=None,
              help="Ceiling of the inlier threshold: max(threshold_mm, this x the objects' distance to the "
                   "cameras); RANSAC runs with it (0: the fixed threshold_mm) [0.1].")
@click.option("--adaptive-k", type=click.FloatRange(min=0), default=None,
              help="Final inlier threshold per group: clip(k x the median inlier distance relative to the "
                   "distance x distance, threshold_mm, ceiling) (0: keep the ceiling) [3].")
@click.option("--weak-links/--no-weak-links", default=None,
              help="Link views through 1-2 objects where RANSAC (>= min_inliers) cannot: two objects that agree, "
                   "or one object without symmetry, with no label contradicting [on].")
@click.option("--max-rotation-deg", type=click.FloatRange(min=0, max=180, min_open=True), default=None,
              help="A pair of candidates whose relative rotation is farther than this from its view pair's is no "
                   "inlier, whatever its distance (objects without a continuous symmetry) [180: off].")
@click.option("--ransac-iterations", type=click.IntRange(min=1), default=None,
              help="Max hypotheses (pairs of candidate pairs) per view pair [paper: 2000].")
@click.option("--ransac-confidence", type=click.FloatRange(min=0, max=1, min_open=True), default=None,
              help="Stop drawing hypotheses once two inlier pairs were drawn with this probability "
                   "(1: always --ransac-iterations) [0.99].")
@click.option("--min-inliers", type=click.IntRange(min=1), default=None,
              help="Inliers for a view pair to be linked [paper: 3].")
@click.option("--score-threshold", type=float, default=None, help="Ignore candidates scoring below [0.0].")
@click.option("--symmetry-steps", type=click.IntRange(min=1), default=None,
              help="Steps per continuous symmetry axis [paper: 64].")
@click.option("--refit/--no-refit", default=None,
              help="Least-squares refit of each view pair's pose on its inliers [on].")
@click.option("--seed", type=int, default=None, help="Seed of the RANSAC sampling [0].")
@click.option("--label-groups", "label_groups", default=None, metavar="auto|none|A:B,C:D",
              help="Labels whose candidates may be matched together, the object taking the label with most "
                   "evidence (score x fit): auto = look-alike models (chamfer <= 2 % of the diameter), none = "
                   "same label only (the paper), or groups of obj_ids like 6:7,5:8 [auto; paper-norefit: none].")
@click.option("--cross-label-hypotheses/--no-cross-label-hypotheses", default=None,
              help="Let candidate pairs of grouped labels make RANSAC hypotheses too (default: view-pair poses "
                   "and links from same-label pairs as in the paper, grouped labels only add associations) [off].")
@click.option("--hypotheses", type=click.IntRange(min=1, max=64), default=None,
              help="Pose hypotheses per candidate to choose from, read from the candidates' sidecar NAME.hypotheses.csv "
                   "(cosy estimate --hypotheses N): each detection takes the one that agrees with the other views; "
                   "candidates.csv of OUT holds the chosen poses [1: the CSV's pose only, as the paper].")
@click.option("--hypothesis-penalty", type=click.FloatRange(min=0, max=100, max_open=True), default=None,
              help="With --hypotheses: cost of each hypothesis rank, in units of the inlier threshold, when "
                   "associations and objects are chosen (a runner-up must agree this much better) [0.5].")
@click.option("--overwrite", is_flag=True, help="Recompute even if OUT exists and is complete.")
@user_errors
def match(dataset: Path, split: str, candidates: Path, out: Path, conf: str, views_per_group, known_cameras: bool,
          grouping, threshold_mm, threshold_rel, adaptive_k, weak_links, max_rotation_deg, ransac_iterations, ransac_confidence, min_inliers, score_threshold, symmetry_steps, refit, seed,
          label_groups, cross_label_hypotheses, hypotheses, hypothesis_penalty, overwrite: bool) -> None:
    """Match object candidates across views (CosyPose stage 2): RANSAC per view pair, scene graph.

    Writes OUT atomically; skips when OUT is complete (unless --overwrite). Lengths in mm.
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from ..multiview import match_stage

    c = match_stage.resolve_conf(conf, views_per_group=views_per_group, known_cameras=known_cameras or None,
                                 groups=grouping,
                                 threshold_mm=threshold_mm, threshold_rel=threshold_rel, adaptive_k=adaptive_k,
                                 weak_links=weak_links, max_rotation_deg=max_rotation_deg,
                                 ransac_iterations=ransac_iterations,
                                 ransac_confidence=ransac_confidence,
                                 min_inliers=min_inliers, score_threshold=score_threshold,
                                 symmetry_steps=symmetry_steps, refit=refit, seed=seed, label_groups=label_groups,
                                 cross_label_hypotheses=cross_label_hypotheses, hypotheses=hypotheses,
                                 hypothesis_penalty=hypothesis_penalty)
    match_stage.main(c, dataset, split, candidates, out, overwrite=overwrite, log=console.echo)


@click.command("synth-candidates")
@click.option("--dataset", required=True, type=click.Path(path_type=Path), help="BOP dataset with ground truth.")
@click.option("--split", default="test", show_default=True)
@click.option("--out", required=True, type=click.Path(path_type=Path), help="Candidates CSV to write (BOP results).")
@click.option("--profile", type=click.Choice(["realistic", "clean"]), default="realistic", show_default=True,
              help="clean: exact GT poses, no misses, flips or false positives.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--gt-out", type=click.Path(path_type=Path), default=None,
              help="Sidecar CSV: GT instance of each candidate (-1 for false positives).")
@click.option("--lookalikes", default=None,
              help="Look-alike pairs like 6:7,3:4 ('none': no confusions; default: found from model sizes).")
@click.option("--p-miss", type=float, default=None, help="Probability of a missed detection [realistic: 0.1].")
@click.option("--depth-rel", type=float, default=None, help="Std of the relative depth error [0.01].")
@click.option("--lateral-mm", type=float, default=None, help="Std of the error across the viewing ray, mm [1].")
@click.option("--rot-deg", type=float, default=None, help="RMS rotation error, degrees [2].")
@click.option("--p-flip", type=float, default=None, help="Probability of a symmetric flip [0.5].")
@click.option("--p-gross", type=float, default=None, help="Probability of a gross error [0.03].")
@click.option("--p-lookalike", type=float, default=None, help="Probability of a look-alike label swap [0.1].")
@click.option("--fp-per-image", type=float, default=None, help="Mean false positives per image [0.3].")
@click.option("--min-visib-fract", type=float, default=None, help="Only GT instances this visible [0.1].")
@user_errors
def synth_candidates(dataset: Path, split: str, out: Path, profile: str, seed: int, gt_out, lookalikes,
                     **knobs) -> None:
    """Simulate single-view candidates from GT (misses, noise, flips, gross errors, look-alikes, false positives)."""
    from ..synth import candidates as sc

    sc.main(dataset, split, out, profile=profile, seed=seed, gt_out=gt_out, lookalikes=lookalikes, log=console.echo,
            **knobs)


COMMANDS = [match, synth_candidates]
