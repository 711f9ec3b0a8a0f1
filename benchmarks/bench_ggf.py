"""Ablation of the Geometric-Gaussian Field: the same runs with the field off, on alone, with AMR, and with
AMR and AOF; plus, on synthetic scenes, how many anchors on planar faces and on curved objects end planar.

Sequences as in ``bench_mapping.py`` (``synthetic:N``, ``replica:N``, dataset folders, config files). Each
variant is a whole ``ggfslam.slam.run`` in a fresh process. Reported per run: PSNR, SSIM, depth L1 (cm) and
normal error (degrees) against the input depth, and ``mesh_depth_l1_cm`` / ``mesh_normal_error_deg``
against the ground-truth mesh of generated sequences (``ggfslam.eval.mesh_geometry``: every 5th frame, the
mesh ray cast at the ATE-aligned estimated pose, over the pixels where the input had depth), ATE, mapping iterations/s and the mapping time per
iteration relative to the run with the field off (meaningful only when nothing else loads the machine). On synthetic
sequences (ground-truth mesh with planar/curved labels): the fraction of anchors with P_2D > threshold
among anchors within 5 cm of a planar face and of a curved object (``ggfslam.eval.planarity``).

One JSON document goes to stdout; progress goes to stderr.

Usage: ``python benchmarks/bench_ggf.py synthetic:120 replica:200 [--variants off,ggf_amr_aof] [--set K=V]``
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_mapping import _run_one  # noqa: E402
from bench_tracking import (comma_choices, finish_report, guarded_run, log, prepared_sequences,  # noqa: E402
                            start_report)

VARIANTS = {
    "off": {"enabled": False},
    "ggf": {"enabled": True, "amr": False, "aof": False},
    "ggf_amr": {"enabled": True, "amr": True, "aof": False},
    "ggf_amr_aof": {"enabled": True, "amr": True, "aof": True},
}


def _run_variant(raw: dict, out_dir: str) -> dict:
    """One run (in a worker process) plus the planarity of its anchors against a synthetic scene's mesh."""
    row = _run_one(raw, out_dir)
    os.dup2(2, 1)
    from ggfslam.saved_run import load_mapper

    cfg, mapper, _ = load_mapper(out_dir)
    row["ggf"] = mapper.stats().get("ggf")
    row.update(_mesh_figures(cfg, mapper, Path(out_dir)))
    if mapper.ggf is not None and cfg.dataset.kind == "synthetic" and cfg.dataset.synthetic.source == "procedural":
        from ggfslam.data.synthetic import make_scene
        from ggfslam.eval.planarity import planar_fractions
        from ggfslam.geometry.depth import transform_points

        syn = cfg.dataset.synthetic
        scene = make_scene(syn.seed, syn.textureless_wall)
        pl = mapper.planarity()
        # the map lives in the estimate's world frame: move its points onto the ground truth's
        pts = transform_points(_alignment(cfg, Path(out_dir)), pl["surface"].numpy().astype(np.float64))
        for key, name in (("p2d", "planarity"), ("prior", "planarity_prior")):
            row[name] = planar_fractions(pts, pl[key].numpy(), scene.mesh, scene.triangle_planar,
                                         cfg.ggf.planar_threshold)
    return row


def _alignment(cfg, run_dir: Path) -> np.ndarray:
    """SE(3) [4, 4] from the run's world frame to the ground truth's (fitted to all poses)."""
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.eval.mesh_geometry import ground_truth_alignment
    from ggfslam.rundir import GROUNDTRUTH_FILE, TRAJECTORY_FILE

    est = read_tum_trajectory(run_dir / TRAJECTORY_FILE)
    gt = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    return ground_truth_alignment(est[0], est[1], gt[0], gt[1], cfg.eval.max_time_diff)[0]


def _mesh_figures(cfg, mapper, run_dir: Path) -> dict:
    """Depth L1 and normal error against the sequence's ground-truth mesh (``mesh.ply`` beside a generated
    sequence), or nothing when it has none."""
    from ggfslam.data import sources
    from ggfslam.data.trajectory_io import read_tum_trajectory
    from ggfslam.eval.mesh_geometry import mesh_geometry_metrics
    from ggfslam.rundir import GROUNDTRUTH_FILE, TRAJECTORY_FILE

    dataset = sources.open_dataset_from_config(cfg.dataset)
    root = getattr(dataset, "root", None)
    if root is None or not (Path(root) / "mesh.ply").is_file() or not (run_dir / GROUNDTRUTH_FILE).is_file():
        return {}
    est = read_tum_trajectory(run_dir / TRAJECTORY_FILE)
    gt = read_tum_trajectory(run_dir / GROUNDTRUTH_FILE)
    return mesh_geometry_metrics(mapper, Path(root) / "mesh.ply", est[0], est[1], gt[0], gt[1], mapper.intr,
                                 stride=5, max_diff=cfg.eval.max_time_diff, dataset=dataset)


def main(argv: list[str] | None = None) -> int:
    """Run the ablation and print its JSON report; returns the exit status (1 if any run failed)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequences", nargs="+", help="dataset folder, config .yaml, synthetic:N or replica:N")
    ap.add_argument("--variants", default=",".join(VARIANTS), help=f"comma-separated subset of {list(VARIANTS)}")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                    help="config override applied to every run (repeatable)")
    ap.add_argument("--keep", metavar="DIR", help="keep the run directories under DIR (default: discarded)")
    args = ap.parse_args(argv)
    variants = comma_choices(ap, args.variants, VARIANTS, "variant")

    report, stdout = start_report("ggf", args.overrides, variants=variants)
    scratch = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_ggf-"))
    ready, failed = prepared_sequences(args.sequences, args.overrides, report)
    for spec, raw in ready:
        base_rate = None
        for v in variants:
            run_raw = {**raw, "ggf": {**raw.get("ggf", {}), **VARIANTS[v]}}
            out = scratch / f"{str(raw.get('name', 'run')).replace('/', '_')}-{v}"
            log(f"{spec} [{v}] -> {out}")
            row = {"sequence": spec, "variant": v}
            row.update(guarded_run(f"{spec} [{v}]", _run_variant, run_raw, str(out)))
            failed |= "error" in row
            if "error" not in row:
                rate = row["mapping_iterations_per_s"]
                base_rate = rate if v == "off" else base_rate
                if base_rate:
                    row["time_per_iteration_vs_off"] = base_rate / rate
                pl = row.get("planarity", {})
                log(f"  PSNR {row['psnr']:.2f} dB, depth L1 {row['depth_l1_cm']:.2f} cm, mesh depth L1 "
                    f"{row.get('mesh_depth_l1_cm', float('nan')):.2f} cm, mesh normal "
                    f"{row.get('mesh_normal_error_deg', float('nan')):.1f} deg, {rate:.2f} it/s"
                    + (f", planar faces {pl['planar_face_fraction']:.2f}, curved {pl['curved_object_fraction']:.2f}"
                       if pl else ""))
            report["runs"].append(row)
    return finish_report(report, stdout, scratch, bool(args.keep), failed)


if __name__ == "__main__":
    sys.exit(main())
