"""Where the face detector puts the nose on real depth frames, drawn: one contact sheet per head pose.

    python benchmarks/detect_sheet.py [--data ../shared/data/rap3df-2019] [--poses front,burned,up,down,left,right]
                                      [--out runs/detect] [--jobs 2] [--cache DIR] [--against OLD/detections.csv]

Real frames have no ground truth, so the detector is judged by eye: each frame of a rap3df-2019-style folder
(manifest.csv with path, subject, pose; intrinsics.json) is preprocessed as every command does it (`Preprocessor()`,
through the preprocessing cache when `--cache` is given), the nose tip it found is projected back into the depth
image (red circle; none for a failure to acquire, whose reason goes to the CSV) and the frames of each pose are
tiled into OUT/<pose>.png, labelled with their subject. OUT/detections.csv holds every frame's nose pixel (u, v),
depth and failure. A wrong detection is plain to see: a circle on hair, an ear or the neck. This is how the
turned-head misdetections of docs/methods.md were found; rap3df-2019 is not shipped (academic use only): without
the folder the bench says so and stops.

`--against OLD/detections.csv` (the CSV of an earlier run, e.g. of another checkout of the detector) also draws
OUT/moved.png: only the frames whose nose moved more than `MOVED_PX` pixels or whose failure to acquire came or went,
the earlier nose in blue (larger circle), this run's in red, and prints how many. Judging those few tiles by eye is
how each detector change of December 2026 was checked on all 521 frames (docs/methods.md, turned heads).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from facerec3d.io.depth import Intrinsics, read_depth_image
from facerec3d.preprocess import landmarks_in_input_frame
from facerec3d.preprocess.batch import preprocess_files

TILE = (119, 149)  # width, height of a tile (rap3df-2019's frame size; other frames are scaled to it)
COLUMNS = 12
MOVED_PX = 3.0  # --against: a nose that moved more than this many pixels (~10 mm at 1.2 m on a Kinect v2) is drawn


def earlier_noses(path: Path) -> dict[str, tuple[float, float] | None]:
    """path -> (u, v) of each frame of an earlier run's detections.csv, None for a failure to acquire."""
    with open(path, newline="") as f:
        return {r["path"]: None if r["failure"] or not r["u"] else (float(r["u"]), float(r["v"]))
                for r in csv.DictReader(f)}


def project(point: np.ndarray, intrinsics: Intrinsics) -> tuple[float, float]:
    """The pixel (u, v) of a camera-frame point (mm; the camera looks along −z, y up: `io.depth.frame_to_scan`)."""
    x, y, z = point
    return intrinsics.cx + intrinsics.fx * x / -z, intrinsics.cy - intrinsics.fy * y / -z


def shaded(path: Path, intrinsics: Intrinsics) -> Image.Image:
    """The depth frame as a grey image, near bright, over the 1st–60th depth percentiles; no data black."""
    xyz, valid = read_depth_image(path, intrinsics).to_range_image()
    depth = np.where(valid, -xyz[..., 2], np.nan)
    lo, hi = np.nanpercentile(depth, [1, 60]) if valid.any() else (0.0, 1.0)
    grey = np.nan_to_num(np.clip((hi - depth) / max(hi - lo, 1e-6), 0, 1) * 255)
    return Image.fromarray(grey.astype(np.uint8)).convert("RGB")


def contact_sheet(tiles: list[Image.Image]) -> Image.Image:
    """Tiles of TILE size, COLUMNS to a row."""
    sheet = Image.new("RGB", (COLUMNS * TILE[0], -(-len(tiles) // COLUMNS) * TILE[1]))
    for k, tile in enumerate(tiles):
        sheet.paste(tile, ((k % COLUMNS) * TILE[0], (k // COLUMNS) * TILE[1]))
    return sheet


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, default=Path(__file__).resolve().parents[2] / "shared/data/rap3df-2019")
    ap.add_argument("--poses", default="front,burned,up,down,left,right")
    ap.add_argument("--out", type=Path, default=Path("runs/detect"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--cache", help="preprocessing cache folder (default: none, every frame preprocessed)")
    ap.add_argument("--against", type=Path, help="an earlier run's detections.csv: draw the frames that moved")
    args = ap.parse_args()
    if not (args.data / "manifest.csv").exists():
        sys.exit(f"detect_sheet.py: {args.data} has no manifest.csv: this bench needs the rap3df-2019 frames "
                 "(not shipped; academic use only) or a folder laid out like them (--data)")
    intrinsics = Intrinsics.load(args.data / "intrinsics.json")
    try:
        before = earlier_noses(args.against) if args.against else None
    except (OSError, KeyError, ValueError) as e:
        sys.exit(f"detect_sheet.py: {args.against}: not a detections.csv of this bench ({e})")
    poses = args.poses.split(",")
    with open(args.data / "manifest.csv", newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["pose"] in poses]
    paths = [args.data / r["path"] for r in rows]
    outcomes = list(preprocess_files(paths, jobs=args.jobs, cache=args.cache, intrinsics=args.data / "intrinsics.json"))
    args.out.mkdir(parents=True, exist_ok=True)
    sheets: dict[str, list[Image.Image]] = {pose: [] for pose in poses}
    moved: list[Image.Image] = []
    with open(args.out / "detections.csv", "w", newline="") as f:
        out = csv.writer(f)
        out.writerow(["path", "subject", "pose", "u", "v", "depth_mm", "failure"])
        for row, path, outcome in zip(rows, paths, outcomes):
            tile = shaded(path, intrinsics)
            draw = ImageDraw.Draw(tile)
            now = None
            if outcome.face is None:
                out.writerow([row["path"], row["subject"], row["pose"], "", "", "", outcome.error])
            else:
                nose = landmarks_in_input_frame(outcome.face)["nose_tip"]
                now = u, v = project(nose, intrinsics)
                draw.ellipse([u - 4, v - 4, u + 4, v + 4], outline=(255, 0, 0), width=2)
                out.writerow([row["path"], row["subject"], row["pose"], f"{u:.1f}", f"{v:.1f}", f"{-nose[2]:.0f}", ""])
            draw.text((2, 2), row["subject"], fill=(255, 255, 0))
            sheets[row["pose"]].append(tile.resize(TILE))
            if before is not None and row["path"] in before:
                then = before[row["path"]]
                if (then is None) != (now is None) or (now and np.hypot(now[0] - then[0], now[1] - then[1]) > MOVED_PX):
                    if then is not None:
                        u0, v0 = then
                        draw.ellipse([u0 - 6, v0 - 6, u0 + 6, v0 + 6], outline=(0, 128, 255), width=2)
                    draw.text((2, TILE[1] - 12), row["pose"] + (" was FTA" if then is None else "")
                              + (" now FTA" if now is None else ""), fill=(255, 255, 0))
                    moved.append(tile.resize(TILE))
    for name, tiles in [*sheets.items(), ("moved", moved)]:
        if tiles:
            contact_sheet(tiles).save(args.out / f"{name}.png")
    if before is not None:
        print(f"{len(moved)} frames moved more than {MOVED_PX:g} px or changed failure against {args.against}"
              + (f": {args.out / 'moved.png'}" if moved else ""))
    failed = sum(o.face is None for o in outcomes)
    print(f"{len(rows)} frames, {failed} failures to acquire; sheets: "
          + ", ".join(str(args.out / f"{p}.png") for p in poses if sheets[p]) + f"; {args.out / 'detections.csv'}")


if __name__ == "__main__":
    main()
