#!/usr/bin/env python
"""Train the ORB vocabulary of ggfslam's place recognition (the packaged default is built by this script).

Descriptors come from (a) frames of the procedural synthetic room rendered with several seeds (each seed
gives other textures and another trajectory) and (b) real images: image folders, TUM-layout folders
(``rgb.txt``) or Replica NICE-SLAM folders (``results/frame*.jpg``). Images are only read, never copied.

The packaged vocabulary was made with the defaults (from the repository root):

    python scripts/train_vocabulary.py

which reads ``$GGFSLAM_DATA`` (default ``../shared/data``): tum_fr3_cabinet_kf and replica_office0_mini.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import cv2
import numpy as np

from ggfslam.backend.place_recognition import Vocabulary
from ggfslam.data.paths import default_data_root, list_files
from ggfslam.data.synthetic import TRAJECTORY_KINDS, SyntheticSequence

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
DEFAULT_OUTPUT = Path(__file__).resolve().parents[1] / "ggfslam" / "backend" / "vocabulary" / "orb_vocab.npz"
DEFAULT_FOLDERS = ("tum_fr3_cabinet_kf", "replica_office0_mini")  # under the shared data root


def image_files(folder: Path) -> list[Path]:
    """Colour images of a TUM folder (rgb.txt), a Replica folder (results/frame*), an rgb/ folder or a plain one."""
    rgb_list = folder / "rgb.txt"
    if rgb_list.is_file():
        files = []
        for line in rgb_list.read_text().splitlines():
            fields = line.split()
            if len(fields) >= 2 and not line.lstrip().startswith("#"):
                files.append(folder / fields[1])
        return files
    if (folder / "results").is_dir():
        return [p for p in list_files(folder / "results", IMAGE_SUFFIXES) if p.name.startswith("frame")]
    if (folder / "rgb").is_dir():
        return list_files(folder / "rgb", IMAGE_SUFFIXES)
    return list_files(folder, IMAGE_SUFFIXES)


def subsample(items: list, max_items: int) -> list:
    """At most ``max_items`` items spread evenly over the list (all of them if max_items <= 0)."""
    if max_items <= 0 or len(items) <= max_items:
        return list(items)
    return [items[i] for i in np.linspace(0, len(items) - 1, max_items).round().astype(int)]


def orb_descriptors(orb: cv2.ORB, grey: np.ndarray) -> np.ndarray:
    """ORB descriptors [N, 32] uint8 of a grey uint8 image (empty when none are found)."""
    _, desc = orb.detectAndCompute(grey, None)
    return desc if desc is not None else np.zeros((0, 32), np.uint8)


def to_grey(rgb: np.ndarray) -> np.ndarray:
    """Grey uint8 image [H, W] from a float RGB image [H, W, 3] in [0, 1]."""
    return cv2.cvtColor(np.clip(rgb * 255.0 + 0.5, 0, 255).astype(np.uint8), cv2.COLOR_RGB2GRAY)


def main(argv: list[str] | None = None) -> int:
    """Command line entry point."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("folders", nargs="*", type=Path,
                    help="image / TUM / Replica folders (default: the shared real data folders)")
    ap.add_argument("--max-images", type=int, default=80, help="at most this many images per folder (0 = all)")
    ap.add_argument("--synthetic-seeds", type=int, nargs="*", default=[101, 102, 103, 104, 105, 106],
                    help="seeds of the synthetic room renders (textures and trajectory differ per seed)")
    ap.add_argument("--synthetic-frames", type=int, default=40, help="frames used per synthetic seed")
    ap.add_argument("--synthetic-size", type=int, nargs=2, default=[640, 480], metavar=("W", "H"))
    ap.add_argument("--features", type=int, default=1000, help="ORB features per image")
    ap.add_argument("--branching", type=int, default=10)
    ap.add_argument("--depth", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0, help="seed of the clustering")
    ap.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = ap.parse_args(argv)

    t0 = time.perf_counter()
    orb = cv2.ORB_create(nfeatures=args.features)
    per_image: list[np.ndarray] = []
    for k, seed in enumerate(args.synthetic_seeds):
        # alternate trajectory kinds so the room is seen from the ring, the racetrack and along a wall
        kind = TRAJECTORY_KINDS[k % len(TRAJECTORY_KINDS)]
        n_render = max(args.synthetic_frames * 10, 1)  # one frame every ~10 cm of a longer walk
        seq = SyntheticSequence(n_render, *args.synthetic_size, trajectory=kind, seed=seed)
        for i in np.linspace(0, n_render - 1, args.synthetic_frames).round().astype(int):
            per_image.append(orb_descriptors(orb, to_grey(seq[int(i)].rgb)))
        print(f"synthetic seed {seed} ({kind}): {args.synthetic_frames} frames", file=sys.stderr)
    folders = args.folders or [default_data_root() / name for name in DEFAULT_FOLDERS]
    for folder in folders:
        if not folder.is_dir():
            print(f"error: {folder}: folder not found", file=sys.stderr)
            return 2
        files = subsample(image_files(folder), args.max_images)
        for path in files:
            img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
            if img is None:
                print(f"error: {path}: cannot decode image", file=sys.stderr)
                return 2
            per_image.append(orb_descriptors(orb, img))
        print(f"{folder}: {len(files)} images", file=sys.stderr)
    per_image = [d for d in per_image if len(d)]
    n_desc = sum(len(d) for d in per_image)
    print(f"training on {n_desc} descriptors from {len(per_image)} images "
          f"(branching {args.branching}, depth {args.depth}, seed {args.seed})", file=sys.stderr)
    voc = Vocabulary.train(per_image, branching=args.branching, depth=args.depth, seed=args.seed)
    out = voc.save(args.output)
    print(f"{voc} -> {out} ({out.stat().st_size / 1024:.0f} KiB) in {time.perf_counter() - t0:.0f} s",
          file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
