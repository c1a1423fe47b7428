"""Real-data benchmark: facerec3d against two Open3D anchors on real Kinect v2 depth frames (rap3df-2019).

    python benchmarks/real_bench.py [--data ../shared/data/rap3df-2019] [--methods icp,...] [--jobs 2]
                                    [--out runs/real] [--anchors o3d-raw,o3d-fair] [--cache DIR] [--options JSON]
                                    [--preprocess-config FILE] [--train DIR] [--scores LABEL=FILE,...]
                                    [--seeds N]

Data: the rap3df-2019 folder (80 people, 521 Kinect v2 depth frames, 149 x 119 16-bit PNGs in mm,
`intrinsics.json`, `manifest.csv` with `path,subject,pose,role`; see its README.md). It comes from the
public repository Piemontez/rap3df-database (folder rap3df_data_02), academic and study use only: it is
read in place, never copied into the project. Gallery = the manifest's `gallery` rows (the first `front`
frame of each person), probes = its `probe` rows (441 frames: front, burned, up, down, left, right).

Systems, all scored on the same frames in the same run (score: higher = more similar):

- anchor `o3d-raw`, the plain Open3D recipe (`raw_face`, `raw_score`): points straight from the
  depth PNG, nose = the nearest point to the camera, 80 mm crop around it, point-to-point
  `registration_icp` (10 mm) of the probe onto the gallery face, both noses moved to the origin,
  score = -inlier_rmse. On these frames the nearest point is often an isolated flying pixel
  (hair, ear and shoulder edges): its 80 mm crop then holds that one point, i.e. no face (below).
- anchor `o3d-fair`, a fair Open3D recipe (`fair_face`, `fair_score`): depth smoothed by a masked
  Gaussian (sigma 1.5 px), nose = the nearest pixel in a band of rows below the top of the head
  (the rule, chosen by looking at where it lands on the frames, not by recognition rates, is in
  `find_nose_fair`), 110 mm crop, point-to-plane ICP at 15 mm then 6 mm (normals on the gallery
  face: hybrid KD-tree search, radius 10 mm, at most 30 neighbours), score = -inlier_rmse.
  DOWNSAMPLED: the probe (ICP's source) is voxel-downsampled to 6 mm (`--fair-voxel`, 0 = off;
  ~870 instead of ~1550 points; the gallery face keeps every point). At full resolution this
  anchor costs ~23 CPU-ms per comparison, ~7.5 min for its 35k ICPs with --jobs 2 on 2 idle cores;
  with the 6 mm voxel ~14 ms, ~4.5 min. A 2 mm voxel, the usual choice, would remove nothing: a
  pixel is 2.7-3.8 mm wide at these distances. On the tuning half the voxel left rank-1
  front+burned unchanged (59.1 %) and moved rank-1 all from 38.7 % to 40.2 %.
- each facerec3d method of `--methods` (default `icp`; `NAME` with the `--options` settings, or
  `NAME=settings.toml`, reported as NAME:stem-of-the-file), run through `facerec3d.evaluation.run.evaluate`
  on the same manifest with no preprocessing cache (`cache=None`), so its preprocessing is really
  measured; its score matrix is read back from the run's `scores.txt`. A method that raises is
  reported as failed (one line) and the benchmark goes on. Learnt methods (pca, lda, a fusion with them) are
  trained on `--train` (default: a synthetic kinect-v2 set of 60 generator identities x 5 scans, written under
  bench-out/data/train-kinect-v2 on first use): no real person is both trained on and tested.

A frame that gives no face (no valid pixel, no nose, or fewer than MIN_POINTS = 100 points in the
crop) is a failure to acquire (probe, FTA) or to enrol (gallery, FTE): every comparison with it
scores -inf, as does an ICP in which no point found a correspondence. (Without this rule a 1-point
crop would match every face with rmse 0.)

Every system is measured by the same code (`identification_metrics`), for three subject groups:
subjects in sorted order, the *tuning half* (even index: s000, s002, ...), on which facerec3d's defaults
were chosen, the *held-out half* (odd index) — the honest figure — and *all*. Each half is its own
closed-set problem: probes AND gallery are restricted to that half's subjects (40-person gallery).
Figures (ISO/IEC 19795-1 conventions):

- FTA = failed probes / probes, FTE = failed gallery frames / gallery frames;
- rank-1 per pose, over front+burned (looking at the camera) and over all probes, each over EVERY
  probe of the group: a failed probe, a probe whose subject failed to enrol, and a tie at the top
  (the genuine score not strictly above every impostor score, e.g. -inf against -inf) all count
  as misses;
- EER and VR at FMR 0.1 % (sklearn.metrics.roc_curve) over every probe x gallery pair of the group,
  genuine when the subjects agree; a pair not compared (failed probe or gallery, no ICP fit) scores
  -inf, i.e. is rejected (generalised FAR/FRR: an FTA rejects genuine users and accepts no one).

Each group's table also gives, for facerec3d's methods, the ratios method / anchor of rank-1 all and
of rank-1 front+burned; the best method (`*`) is the one with the highest rank-1 all on the tuning
half. Times: anchors, seconds of preprocessing (one process) and wall seconds of matching (including
starting the worker processes), and CPU-milliseconds per comparison (process time summed over the
workers, so it holds on a busy machine too; the load average before and after is reported; Open3D
has no JIT, so nothing is compiled); facerec3d, its own `timings` from metrics.json and the wall
time of `evaluate`. The first facerec3d method run includes Numba's JIT
compilation unless Numba's on-disk cache is already warm (reported), and every method's
preprocessing runs on cold (no) cache.

`--seeds N` runs every method that draws ICP's probe points at random (icp, region-icp, a fusion with either)
N times, with ICP's `seed` 0 ... N-1 (labels NAME@seed0, ...), and adds a row NAME (mean of N seeds) to each
table: each figure averaged over the seeds, with the lowest and highest rank-1 over all probes in the notes. The
seed draws which 1,000 of a probe's points ICP aligns and scores; on these 40-person halves two seeds differ by
up to ~5 points of rank-1 (docs/methods.md, "Reading the real figures"), so a variant is compared with its
baseline by the mean over seeds, not by one run.

`--scores LABEL=FILE,...` adds systems from score files without running anything: a fusion of earlier runs'
members, e.g. `facerec3d fuse OUT/icp/scores.txt OUT/region-icp/scores.txt OUT/embedding/scores.txt --rule
weighted-sum --weights 2,1,1 --out w211.txt`, then `--methods '' --anchors '' --scores w211=w211.txt` (the `fusion`
method's own scores are exactly the `fuse` of its members' with its settings).

Writes OUT/real_bench.json (everything), OUT/real_bench.md (the tables) and, per method, facerec3d's
run folder OUT/<method>/.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ.setdefault(_var, "1")  # one BLAS / OpenMP thread per process, set before NumPy/Open3D load

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import multiprocessing  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from concurrent.futures import ProcessPoolExecutor  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402
from scipy.ndimage import binary_erosion, gaussian_filter  # noqa: E402
from sklearn.metrics import roc_curve  # noqa: E402

try:
    import open3d as o3d  # noqa: E402
    _O3D_ERROR = None
except (ImportError, OSError) as e:  # OSError: a shared library (libusb-1.0) is missing
    o3d, _O3D_ERROR = None, e

POSES = ("front", "burned", "up", "down", "left", "right")
MIN_POINTS = 100  # a crop with fewer points is no face
DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "rap3df-2019"

RAW = dict(crop_mm=80.0, max_corr_mm=10.0)
FAIR = dict(sigma_px=1.5, crop_mm=110.0, max_corr_mm=(15.0, 6.0), normal_radius_mm=10.0, normal_max_nn=30,
            erode_px=2, window=(0.2, 2 / 3), probe_voxel_mm=6.0)


# ---------------------------------------------------------------------------------------------- data


def read_manifest(data: Path) -> list[dict]:
    """The manifest's rows (`path` made absolute), in file order."""
    with open(data / "manifest.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    for r in rows:
        r["path"] = str(data / r["path"])
    return rows


def read_depth(path: str) -> np.ndarray:
    """A 16-bit depth PNG as float mm (0 = no measurement)."""
    return np.asarray(Image.open(path), dtype=np.float64)


def depth_to_points(depth: np.ndarray, mask: np.ndarray, intr: dict) -> tuple[np.ndarray, np.ndarray]:
    """(points (n, 3) in mm, their (row, col) pixels): X = (u-cx) d/fx, Y = -(v-cy) d/fy, Z = -d."""
    v, u = np.nonzero(mask)
    d = depth[v, u] * intr.get("depth_unit_mm", 1.0)
    pts = np.column_stack([(u - intr["cx"]) * d / intr["fx"], -(v - intr["cy"]) * d / intr["fy"], -d])
    return pts, np.column_stack([v, u])


def crop(points: np.ndarray, nose: np.ndarray, radius: float) -> np.ndarray | None:
    """The points within `radius` mm of the nose, moved so the nose is the origin; None if too few."""
    kept = points[np.linalg.norm(points - nose, axis=1) <= radius] - nose
    return kept if len(kept) >= MIN_POINTS else None


# ------------------------------------------------------------------------------------------- anchors


def raw_face(path: str, intr: dict) -> np.ndarray | None:
    """Open3D recipe ("raw"): every valid pixel of the PNG as a point; nose = the point of largest Z
    (nearest the camera); the points within 80 mm of it, nose at the origin. None when no face."""
    depth = read_depth(path)
    mask = depth > 0
    if not mask.any():
        return None
    pts, _ = depth_to_points(depth, mask, intr)
    return crop(pts, pts[np.argmax(pts[:, 2])], RAW["crop_mm"])


def raw_score(probe: "o3d.geometry.PointCloud", gallery: "o3d.geometry.PointCloud") -> float:
    """Open3D recipe: point-to-point ICP of the probe onto the gallery face (both noses at the origin,
    identity start, max correspondence distance 10 mm, Open3D's default 30 iterations);
    score = -inlier_rmse, -inf when no point found a correspondence."""
    reg = o3d.pipelines.registration
    r = reg.registration_icp(probe, gallery, RAW["max_corr_mm"], np.eye(4),
                             reg.TransformationEstimationPointToPoint())
    return -r.inlier_rmse if r.fitness > 0 else -math.inf


def smooth_depth(depth: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """Masked (normalised) Gaussian smoothing: G*(depth*mask) / G*mask on valid pixels, 0 elsewhere,
    so missing pixels neither pull the depth towards 0 nor get filled in."""
    m = mask.astype(np.float64)
    num = gaussian_filter(depth * m, sigma, mode="constant")
    den = gaussian_filter(m, sigma, mode="constant")
    return np.where(mask, num / np.maximum(den, 1e-12), 0.0)


def find_nose_fair(depth: np.ndarray, mask: np.ndarray) -> tuple[int, int] | None:
    """The nose pixel (row, col) of a smoothed depth frame, or None.

    Rule: the rows that hold data run from the top of the head (the first row with at least 5 valid
    pixels, so stray flying pixels above the hair do not count) to the bottom of the frame (the
    shoulders always reach it in these crops). The nose is the nearest pixel (smallest smoothed depth)
    in the band from 1/5 to 2/3 of the way down those rows, among pixels at least 2 px inside the valid
    region (mask eroded twice: the flying pixels at the edges of hair and ears are left out). Below the
    band lie the shoulders, chest and hands, often nearer than the nose when the head is tilted back;
    in its top fifth hair, and the forehead of a bowed head, often are. The band was chosen by
    looking at where the rule lands on the frames (with a band starting at the top, about 50 of the
    521 frames put the nose on the hair), not by recognition rates. It still misses some: with the
    head bowed (pose `down`) the forehead is often the nearest point of the face.
    """
    rows = np.flatnonzero(mask.sum(axis=1) >= 5)
    if rows.size == 0:
        return None
    top, bottom = rows[0], rows[-1]
    lo = top + int(FAIR["window"][0] * (bottom - top + 1))
    hi = top + int(np.ceil(FAIR["window"][1] * (bottom - top + 1)))
    inner = binary_erosion(mask, iterations=FAIR["erode_px"])
    inner[:lo] = False
    inner[hi:] = False
    if not inner.any():
        return None
    flat = np.where(inner, depth, np.inf).argmin()
    return tuple(int(i) for i in np.unravel_index(flat, depth.shape))


def fair_face(path: str, intr: dict) -> np.ndarray | None:
    """Fair recipe: masked Gaussian smoothing (sigma 1.5 px) of the depth, points of the valid pixels,
    nose by `find_nose_fair`, the points within 110 mm of it, nose at the origin. None when no face."""
    depth = read_depth(path)
    mask = depth > 0
    smooth = smooth_depth(depth, mask, FAIR["sigma_px"])
    nose = find_nose_fair(smooth, mask)
    if nose is None:
        return None
    pts, pix = depth_to_points(smooth, mask, intr)
    at = np.flatnonzero((pix[:, 0] == nose[0]) & (pix[:, 1] == nose[1]))[0]
    return crop(pts, pts[at], FAIR["crop_mm"])


def fair_score(probe: "o3d.geometry.PointCloud", gallery: "o3d.geometry.PointCloud") -> float:
    """Fair recipe: point-to-plane ICP of the probe onto the gallery face (normals on the gallery),
    identity start (noses at the origin), first with a 15 mm then a 6 mm max correspondence distance
    (Open3D's default 30 iterations each); score = -inlier_rmse of the 6 mm stage, -inf when no point
    found a correspondence."""
    reg = o3d.pipelines.registration
    T = np.eye(4)
    r = None
    for dist in FAIR["max_corr_mm"]:
        r = reg.registration_icp(probe, gallery, dist, T, reg.TransformationEstimationPointToPlane())
        T = r.transformation
    return -r.inlier_rmse if r.fitness > 0 else -math.inf


ANCHORS = {"o3d-raw": (raw_face, raw_score), "o3d-fair": (fair_face, fair_score)}


def to_cloud(points: np.ndarray | None, normals: bool) -> "o3d.geometry.PointCloud | None":
    """An Open3D point cloud of the points (with normals estimated by a hybrid KD-tree search)."""
    if points is None:
        return None
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    if normals:
        pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=FAIR["normal_radius_mm"],
                                                                 max_nn=FAIR["normal_max_nn"]))
    return pc


_WORKER: dict = {}


def fair_probe(points: np.ndarray | None) -> "o3d.geometry.PointCloud | None":
    """The fair recipe's probe cloud: voxel-downsampled (FAIR['probe_voxel_mm'], off when 0/None) to keep
    the run short; the gallery face, ICP's target, keeps every point and its normals."""
    pc = to_cloud(points, False)
    voxel = FAIR["probe_voxel_mm"]
    return pc.voxel_down_sample(voxel) if pc is not None and voxel else pc


def _init_worker(anchor: str, probes: list, gallery: list, fair_settings: dict) -> None:
    """Process-pool initializer: one thread, quiet Open3D, the faces as Open3D clouds."""
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    FAIR.update(fair_settings)  # the parent's settings (command line), not this module's defaults
    fair = anchor == "o3d-fair"
    _WORKER.update(score=ANCHORS[anchor][1], probes=[fair_probe(p) if fair else to_cloud(p, False) for p in probes],
                   gallery=[to_cloud(g, fair) for g in gallery])


def _score_row(i: int) -> tuple[list[float], float]:
    """Probe i against every gallery face (-inf where either is no face), and the CPU seconds it took."""
    t0 = time.process_time()
    p, score = _WORKER["probes"][i], _WORKER["score"]
    row = [-math.inf if p is None or g is None else score(p, g) for g in _WORKER["gallery"]]
    return row, time.process_time() - t0


def run_anchor(anchor: str, gallery_rows: list, probe_rows: list, intr: dict, jobs: int) -> dict:
    """One anchor on the manifest: its (probes x gallery) score matrix, failures and times."""
    face = ANCHORS[anchor][0]
    t0 = time.perf_counter()
    gallery = [face(r["path"], intr) for r in gallery_rows]
    probes = [face(r["path"], intr) for r in probe_rows]
    prep_s = time.perf_counter() - t0
    load = os.getloadavg()[0]
    t0 = time.perf_counter()
    ctx = multiprocessing.get_context("spawn")  # fresh interpreters: env (1 thread) set before Open3D loads
    with ProcessPoolExecutor(jobs, ctx, initializer=_init_worker, initargs=(anchor, probes, gallery, FAIR)) as pool:
        rows = list(pool.map(_score_row, range(len(probes)), chunksize=4))
    match_s = time.perf_counter() - t0
    S = np.array([r for r, _ in rows], dtype=float).reshape(len(probes), len(gallery))
    cpu_s = sum(c for _, c in rows)
    n = S.size
    return {"S": S, "S_strangers": S, "failed_probe": np.array([p is None for p in probes]),  # raw ICP errors
            "failed_gallery": np.array([g is None for g in gallery]),
            "points": float(np.median([len(f) for f in gallery + probes if f is not None])),
            "timings": {"preprocess_s": prep_s, "frames": len(probes) + len(gallery), "match_s": match_s,
                        "comparisons": n,
                        "wall_ms_x_jobs_per_comparison": 1000 * match_s * jobs / max(n, 1),
                        "cpu_ms_per_comparison": 1000 * cpu_s / max(n, 1),
                        "load_avg_before": load, "load_avg_after": os.getloadavg()[0]}}


# ----------------------------------------------------------------------------------------- facerec3d


def numba_cache_warm() -> bool:
    """Whether facerec3d's Numba on-disk cache (`__pycache__/*.nbi`) already exists (no JIT then)."""
    import facerec3d

    return any(Path(facerec3d.__file__).parent.rglob("__pycache__/*.nbi"))


def method_specs(text: str, options: dict | None) -> list[tuple[str, str, dict | None]]:
    """(label, method, settings) of each `--methods` entry: `name` (with the --options settings; label = name) or
    `name=settings.toml` (label = name:stem of the file), as methods_bench takes them."""
    from facerec3d.config import read_settings

    specs = []
    for item in (m.strip() for m in text.split(",")):
        if item:
            method, _, config = item.partition("=")
            specs.append((f"{method}:{Path(config).stem}" if config else method, method,
                          read_settings(config) if config else options))
    if len({label for label, _, _ in specs}) < len(specs):
        raise SystemExit(f"real_bench: --methods names a system twice: {text}")
    return specs


def _merged(base: dict | None, extra: dict) -> dict:
    """`base` with the tables of `extra` merged in, nested tables field by field (neither is changed)."""
    out = dict(base or {})
    for key, value in extra.items():
        out[key] = _merged(out.get(key), value) if isinstance(value, dict) else value
    return out


def with_seed(method: str, options: dict | None, seed: int) -> dict | None:
    """The method's settings with ICP's probe-subset `seed` set wherever ICP runs (icp, region-icp's regions, a
    fusion's icp and region-icp members); None when the method draws nothing at random."""
    if method == "icp":
        return _merged(options, {"seed": seed})
    if method == "region-icp":
        return _merged(options, {"icp": {"seed": seed}})
    if method == "fusion":
        from facerec3d.matching.fusion import FusionConfig

        members = (options or {}).get("members", FusionConfig().members)
        seeded = {m: with_seed(m, ((options or {}).get("member_options") or {}).get(m), seed) for m in members}
        seeded = {m: o for m, o in seeded.items() if o is not None}
        return _merged(options, {"member_options": seeded}) if seeded else None
    return None


def seeded_specs(specs: list, seeds: int) -> tuple[list, dict[str, list[str]]]:
    """Each spec that draws at random, once per seed (label@seedK); and {label: its seeds' labels}."""
    out, runs = [], {}
    for label, method, options in specs:
        if seeds > 1 and with_seed(method, options, 0) is not None:
            runs[label] = [f"{label}@seed{k}" for k in range(seeds)]
            out += [(run, method, with_seed(method, options, k)) for k, run in enumerate(runs[label])]
        else:
            out.append((label, method, options))
    return out, runs


def mean_over_seeds(results: dict, runs: dict[str, list[str]]) -> list[str]:
    """Add to each group a row `label (mean of N seeds)` averaging the seeds' figures; the notes giving each
    group's lowest and highest rank-1 over all probes."""
    notes = []
    for label, names in runs.items():
        names = [n for n in names if n in results["all"]]
        if not names:
            continue
        spread = []
        for group, per_system in results.items():
            rows = [per_system[n] for n in names]
            per_system[f"{label} (mean of {len(rows)} seeds)"] = {
                k: (float(np.mean([r[k] for r in rows])) if all(isinstance(r.get(k), float) for r in rows)
                    else rows[0].get(k)) for k in rows[0]}
            r1 = [r["rank1_all"] for r in rows if r["rank1_all"] is not None]
            if r1:
                spread.append(f"{group} {pct(min(r1))}–{pct(max(r1))}")
        notes.append(f"{label}: rank-1 all over {len(names)} seeds: " + ", ".join(spread))
    return notes


def training_set(root: Path) -> Path:
    """The training set of learnt methods (PCA, LDA): synthetic Kinect v2 frames of 60 generator identities x 5
    scans (subjects numbered from 1000, seed 1; no real person in it), written under `root` once. Training on real
    subjects would need people outside the test set, which a 80-person set cannot spare."""
    from facerec3d.datasets.synthetic import DatasetConfig, sensor_profile, write_dataset

    if not (root / "manifest.csv").is_file():
        print(f"  writing the training set {root} (60 x 5 synthetic kinect-v2 scans) ...", flush=True)
        write_dataset(root, DatasetConfig(subjects=60, scans=5, first_subject=1000, seed=1,
                                          scanner=sensor_profile("kinect-v2")), "abs")
    return root


def tuning_manifest(data: Path, manifest: list[dict], out: Path) -> Path:
    """A manifest of every frame of the tuning half's people (gallery and probes; absolute paths), written under
    `out`: the training set of `--train tuning`. The held-out half's people are never in it."""
    tuning = subject_groups([r["subject"] for r in manifest])["tuning"]
    path = out / "train-tuning.csv"
    with open(path, "w", newline="", encoding="utf-8") as f:
        w = csv.writer(f)
        w.writerow(["path", "subject", "pose"])
        for r in manifest:
            if r["subject"] in tuning:
                w.writerow([str((data / r["path"]).resolve()), r["subject"], r["pose"]])
    return path


def parse_score_files(text: str) -> list[tuple[str, str]]:
    """(label, path) of each LABEL=FILE of `--scores`, comma-separated; a part without "=" continues the previous
    file's name (a path holding a comma)."""
    items: list[str] = []
    for part in text.split(","):
        if "=" in part or not items:
            items.append(part)
        elif part.strip():
            items[-1] += "," + part
    pairs = [x.split("=", 1) if "=" in x else [x, ""] for x in items if x.strip()]
    return [(label.strip(), path.strip()) for label, path in pairs]


def score_file_system(path: Path, data: Path, gallery_rows: list, probe_rows: list) -> dict:
    """A system from a score file (an evaluation's scores.txt, or `facerec3d fuse`'s): its score matrix over the
    manifest's probes and gallery, failures where it has no score.

    Rows are paired with the manifest's probes by (real_id, probe_label), label = the frame's path within the
    dataset (as the manifest gives it), columns by claimed_id = gallery subject. A probe with no row failed to
    acquire, a gallery subject never claimed failed to enrol."""
    from facerec3d.evaluation.scorefile import read_score_rows, strangers_file

    probe_at = {(r["subject"], Path(r["path"]).relative_to(data).as_posix()): i for i, r in enumerate(probe_rows)}
    gallery_at = {r["subject"]: j for j, r in enumerate(gallery_rows)}
    if len(gallery_at) != len(gallery_rows):
        raise ValueError("the manifest has several gallery frames for one subject; scores.txt cannot tell them apart")

    def matrix(file: Path) -> np.ndarray:
        S = np.full((len(probe_rows), len(gallery_rows)), np.nan)
        for claimed, real, label, score in zip(*read_score_rows(file)):
            i, j = probe_at.get((real, label)), gallery_at.get(claimed)
            if i is None or j is None:
                raise ValueError(f"{file}: row {claimed} {real} {label} matches no manifest probe/gallery frame")
            S[i, j] = score
        return S

    S = matrix(path)
    strangers = strangers_file(path)  # evaluate's or fuse's, beside it (scores normalised over the gallery:
    #   impostor pairs scored as strangers' claims)
    return {"S": np.where(np.isnan(S), -np.inf, S), "failed_probe": np.isnan(S).all(axis=1),
            "failed_gallery": np.isnan(S).all(axis=0),
            "S_strangers": matrix(strangers) if strangers.is_file() else None}


def run_method(method: str, data: Path, gallery_rows: list, probe_rows: list, out: Path, jobs: int,
               cache: Path | None = None, options: dict | None = None, label: str | None = None,
               train: Path | None = None, config: Any = None) -> dict:
    """One facerec3d method through its Python API (preprocessing `config`, default the defaults); the score
    matrix rebuilt from scores.txt (`score_file_system`)."""
    from facerec3d.evaluation.run import evaluate
    from facerec3d.preprocess import PreprocessConfig

    warm = numba_cache_warm()
    t0 = time.perf_counter()
    label = label or method
    metrics = evaluate(data / "manifest.csv", method=method, out=out / label, jobs=jobs, progress=False,
                       cache=cache, options=options, train=train, config=config or PreprocessConfig())
    wall_s = time.perf_counter() - t0
    system = score_file_system(out / label / "scores.txt", data, gallery_rows, probe_rows)
    if system["S_strangers"] is None and "strangers" not in metrics:  # scores that do not depend on the gallery:
        system["S_strangers"] = system["S"]                           # a stranger's claim scores as anyone's
    if metrics.get("failures_to_enrol", 0) != int(system["failed_gallery"].sum()):
        print(f"  note: {method}: metrics.json says {metrics.get('failures_to_enrol')} failures to enrol, "
              f"scores.txt shows {int(system['failed_gallery'].sum())} gallery subjects never scored")
    return {**system,
            "timings": {**metrics.get("timings", {}), "evaluate_wall_s": wall_s, "jobs": jobs,
                        "numba_cache_warm_before": warm,
                        "preprocess_cache": f"{cache} (may be warm)" if cache else "none (cold)"},
            "facerec3d_metrics": {k: metrics.get(k) for k in ("rank1", "rank1_all", "eer", "vr_at_far_0.001",
                                                              "failures", "failures_to_enrol", "n_gallery")},
            "failed_scans": metrics.get("failed_scans", [])}


# ------------------------------------------------------------------------------------------- metrics


def identification_metrics(S, probe_subjects, gallery_subjects, probe_poses, failed_probe,
                           failed_gallery=None, S_strangers=None) -> dict:
    """The benchmark's figures from a (probes x gallery) score matrix (higher = more similar).

    Failed probes / gallery frames (masks) and -inf / NaN entries are comparisons not made. Rank-1
    figures are over every probe given (a failure, an unenrolled subject or a tie at the top is a
    miss); EER and VR at FMR 0.1 % over every pair, a pair not made scoring -inf (rejected).
    `eer_strangers`: the EER with each impostor pair's score from `S_strangers` (a method normalised over
    the gallery, its impostors scored as strangers' claims: evaluate's scores.strangers.txt), None without."""
    S = np.array(S, dtype=float)
    ps, gs = np.asarray(probe_subjects), np.asarray(gallery_subjects)
    poses = np.asarray(probe_poses)
    failed_probe = np.asarray(failed_probe, dtype=bool)
    failed_gallery = np.zeros(len(gs), bool) if failed_gallery is None else np.asarray(failed_gallery, bool)
    S[np.isnan(S)] = -np.inf
    S[failed_probe] = -np.inf
    S[:, failed_gallery] = -np.inf
    genuine = ps[:, None] == gs[None, :]
    best_genuine = np.where(genuine, S, -np.inf).max(axis=1)
    best_impostor = np.where(genuine, -np.inf, S).max(axis=1)
    hit = np.isfinite(best_genuine) & (best_genuine > best_impostor)

    def rate(sel):
        return float(hit[sel].mean()) if sel.any() else None

    out = {"n_probes": int(len(ps)), "n_gallery": int(len(gs)),
           "fta": float(failed_probe.mean()) if len(ps) else None,
           "fte": float(failed_gallery.mean()) if len(gs) else None,
           "rank1_all": rate(np.ones(len(ps), bool)),
           "rank1_front_burned": rate(np.isin(poses, ["front", "burned"]))}
    for pose in POSES:
        out[f"rank1_{pose}"] = rate(poses == pose)
    out["eer"], out["vr_at_fmr_0.001"] = verification(genuine.ravel(), S.ravel())
    out["eer_strangers"] = None
    if S_strangers is not None:
        T = np.array(S_strangers, dtype=float)
        T[np.isnan(T)] = -np.inf
        T[failed_probe] = -np.inf
        T[:, failed_gallery] = -np.inf
        out["eer_strangers"] = verification(genuine.ravel(), np.where(genuine, S, T).ravel())[0]
    return out


def verification(y: np.ndarray, s: np.ndarray) -> tuple[float | None, float | None]:
    """(EER, VR at FMR 0.1 %) of scores s, genuine where y, a score of -inf rejected (None without both kinds)."""
    if not (y.any() and (~y).any()):
        return None, None
    finite = s[np.isfinite(s)]
    floor = (finite.min() - 1.0) if finite.size else 0.0
    fmr, tar, _ = roc_curve(y, np.where(np.isfinite(s), s, floor))
    fnmr = 1.0 - tar
    k = int(np.flatnonzero(fnmr <= fmr)[0])  # first point where FNMR has fallen to FMR
    if k == 0:
        eer = float(fmr[0])
    else:  # linear interpolation of the crossing between points k-1 and k
        d0, d1 = fnmr[k - 1] - fmr[k - 1], fnmr[k] - fmr[k]
        t = d0 / (d0 - d1) if d0 != d1 else 0.0
        eer = float(fmr[k - 1] + t * (fmr[k] - fmr[k - 1]))
    return eer, float(tar[fmr <= 1e-3].max())


def subject_groups(subjects: list[str]) -> dict[str, set]:
    """all, tuning half (even index in sorted order) and held-out half (odd index)."""
    order = sorted(set(subjects))
    return {"all": set(order), "tuning": set(order[0::2]), "held-out": set(order[1::2])}


def group_metrics(system: dict, group: set, probe_rows: list, gallery_rows: list) -> dict:
    """`identification_metrics` with probes and gallery restricted to the group's subjects."""
    pi = np.array([r["subject"] in group for r in probe_rows])
    gi = np.array([r["subject"] in group for r in gallery_rows])
    return identification_metrics(system["S"][np.ix_(pi, gi)],
                                  [r["subject"] for r, k in zip(probe_rows, pi) if k],
                                  [r["subject"] for r, k in zip(gallery_rows, gi) if k],
                                  [r["pose"] for r, k in zip(probe_rows, pi) if k],
                                  system["failed_probe"][pi], system["failed_gallery"][gi],
                                  None if system.get("S_strangers") is None else system["S_strangers"][np.ix_(pi, gi)])


# -------------------------------------------------------------------------------------------- report


COLUMNS = [("fta", "FTA/FTE"), ("rank1_front_burned", "R1 front+burned"), ("rank1_all", "R1 all"),
           *[(f"rank1_{p}", p) for p in POSES], ("eer", "EER"), ("eer_strangers", "EER strangers"),
           ("vr_at_fmr_0.001", "VR@0.1%")]


def pct(x) -> str:
    return "–" if x is None else f"{100 * x:.1f}%"


def ratio(a, b) -> str:
    return "–" if a is None or not b else f"{a / b:.2f}"


def tables(results: dict, anchors: list, methods: list, best: str | None) -> list[tuple[str, list, list]]:
    """One (heading, columns, rows) table per group; ratios = facerec3d method / anchor."""
    out = []
    for group, per_system in results.items():
        cols = ["system", *[c for _, c in COLUMNS]]
        for a in anchors:
            cols += [f"R1 all ÷ {a}", f"R1 f+b ÷ {a}"]
        rows = []
        for name, m in per_system.items():
            row = [name + (" *" if name == best else ""), f"{pct(m['fta'])}/{pct(m['fte'])}",
                   *[pct(m.get(k)) for k, _ in COLUMNS[1:]]]
            for a in anchors:
                if name in methods and a in per_system:
                    ref = per_system[a]
                    row += [ratio(m["rank1_all"], ref["rank1_all"]),
                            ratio(m["rank1_front_burned"], ref["rank1_front_burned"])]
                else:
                    row += ["", ""]
            rows.append(row)
        n = next(iter(per_system.values()), {})
        out.append((f"{group}: {n.get('n_probes')} probes, gallery {n.get('n_gallery')}", cols, rows))
    return out


def render(tbls, fmt: str) -> str:
    """The tables as aligned text or Markdown."""
    parts = []
    for heading, cols, rows in tbls:
        if fmt == "md":
            parts += [f"## {heading}", "", "| " + " | ".join(cols) + " |", "|" + "---|" * len(cols)]
            parts += ["| " + " | ".join(r) + " |" for r in rows]
        else:
            widths = [max(len(str(x)) for x in col) for col in zip(cols, *rows)]
            parts += [heading, "  ".join(c.rjust(w) for c, w in zip(cols, widths))]
            parts += ["  ".join(str(x).rjust(w) for x, w in zip(r, widths)) for r in rows]
        parts.append("")
    return "\n".join(parts)


def timing_lines(systems: dict) -> list[str]:
    lines = []
    for name, s in systems.items():
        t = s["timings"]
        if name in ANCHORS:
            lines.append(f"{name}: preprocessing {t['preprocess_s']:.1f} s ({t['frames']} frames, 1 process), matching "
                         f"{t['match_s']:.1f} s wall for {t['comparisons']} ICPs incl. worker start-up "
                         f"({t['wall_ms_x_jobs_per_comparison']:.2f} ms x jobs per comparison); "
                         f"{t['cpu_ms_per_comparison']:.2f} CPU-ms per comparison (process time, warm: no JIT); "
                         f"load average {t['load_avg_before']:.1f} before, {t['load_avg_after']:.1f} after")
        elif "score_file" in t:
            lines.append(f"{name}: from the score file {t['score_file']} (not timed)")
        else:
            jit = "no JIT (Numba cache warm)" if t.get("numba_cache_warm_before") else "INCLUDES Numba JIT compilation"
            lines.append(f"{name}: evaluate {t['evaluate_wall_s']:.1f} s wall ({jit}; preprocessing cache: "
                         f"{t.get('preprocess_cache', 'none (cold)')}): "
                         + ", ".join(f"{k} {v:.4g}" for k, v in t.items()
                                     if isinstance(v, float) and k != "evaluate_wall_s"))
    return lines


# ---------------------------------------------------------------------------------------------- main


NO_DATA = """\
real_bench: no rap3df-2019 data at {data}.
This benchmark needs the rap3df-2019 folder: 80 people, 521 real Kinect v2 depth frames as 16-bit PNGs in mm
(sNNN/<pose>_<k>.png, 149 x 119), with intrinsics.json and manifest.csv (path,subject,pose,role), laid out as
its README.md describes. The frames come from the public repository Piemontez/rap3df-database (folder
rap3df_data_02), whose README allows academic and study use only, so the data is never shipped with facerec3d.
Put the folder somewhere outside the project and point the benchmark at it:
    python benchmarks/real_bench.py --data /path/to/rap3df-2019"""

NO_OPEN3D = """\
real_bench: Open3D cannot be imported ({error}).
The anchors of this benchmark run Open3D's ICP: install it with  pip install -e ".[bench]"  (in the project's
virtual environment). On Debian/Ubuntu, Open3D also needs the system library libusb-1.0
(sudo apt-get install libusb-1.0-0)."""


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--data", type=Path, default=DEFAULT_DATA, help="the rap3df-2019 folder")
    ap.add_argument("--methods", default="icp",
                    help="facerec3d methods, comma separated ('' for none); NAME or NAME=settings.toml")
    ap.add_argument("--anchors", default=",".join(ANCHORS), help="anchors to run, comma separated")
    ap.add_argument("--jobs", type=int, default=2, help="processes")
    ap.add_argument("--fair-voxel", type=float, default=FAIR["probe_voxel_mm"],
                    help="voxel size (mm) the fair anchor's probes are downsampled to; 0 = every point")
    ap.add_argument("--out", type=Path, default=Path("runs/real"))
    ap.add_argument("--cache", type=Path, default=None,
                    help="preprocessing cache folder shared by the methods (default: none, so preprocessing is timed)")
    ap.add_argument("--options", type=json.loads, default=None,
                    help='method settings as JSON, as a --method-config file holds them (e.g. \'{"icp": {...}}\')')
    ap.add_argument("--preprocess-config", type=Path, default=None,
                    help="preprocessing settings (TOML/JSON, any subset, as `facerec3d preprocess --config`); e.g. "
                         "crop_radius_mm = 80 with [resample] half_width_mm = 80 to measure another crop")
    ap.add_argument("--scores", default="",
                    help="LABEL=FILE,...: systems read from score files (bob4, e.g. `facerec3d fuse` of earlier runs' "
                         "scores.txt), reported beside the methods, not run; the strangers' scores that evaluate and "
                         "fuse write beside a file (scores.strangers.txt) give its EER strangers")
    ap.add_argument("--seeds", type=int, default=1,
                    help="run each method that draws ICP's probe points at random with seeds 0..N-1 and report "
                         "their mean (default 1: the default seed only)")
    ap.add_argument("--train", type=Path, default=Path("bench-out/data/train-kinect-v2"),
                    help="training set of the learnt methods (pca, lda); written there (synthetic kinect-v2) if missing; "
                         "'tuning': every frame of the tuning half's people (then only the held-out figures are "
                         "honest), e.g. for the embedding adapted to the camera (adapt = \"wccn\")")
    args = ap.parse_args(argv)

    if not (args.data / "manifest.csv").is_file() or not (args.data / "intrinsics.json").is_file():
        print(NO_DATA.format(data=args.data), file=sys.stderr)
        return 2
    score_files = parse_score_files(args.scores)  # checked before any method runs
    if bad := next(((label, path) for label, path in score_files if not label or not Path(path).is_file()), None):
        ap.error(f"--scores {bad[0]}={bad[1]}: give LABEL=FILE with an existing score file")
    anchors = [a for a in args.anchors.split(",") if a]
    if anchors and o3d is None:  # only the anchors run Open3D
        print(NO_OPEN3D.format(error=_O3D_ERROR), file=sys.stderr)
        return 2
    if o3d is not None:
        o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    FAIR["probe_voxel_mm"] = args.fair_voxel or None
    intr = json.loads((args.data / "intrinsics.json").read_text())
    manifest = read_manifest(args.data)
    gallery_rows = [r for r in manifest if r["role"] == "gallery"]
    probe_rows = [r for r in manifest if r["role"] == "probe"]
    from facerec3d.matching.registry import make_matcher
    from facerec3d.preprocess import PreprocessConfig

    if args.seeds < 1:
        ap.error("--seeds must be at least 1")
    specs, seed_runs = seeded_specs(method_specs(args.methods, args.options), args.seeds)
    config = PreprocessConfig.load(args.preprocess_config) if args.preprocess_config else PreprocessConfig()
    methods = [label for label, _, _ in specs]
    unknown = set(anchors) - set(ANCHORS)
    if unknown:
        ap.error(f"unknown anchor(s) {sorted(unknown)}; choose from {list(ANCHORS)}")
    args.out.mkdir(parents=True, exist_ok=True)
    print(f"rap3df-2019: {len(gallery_rows)} gallery frames, {len(probe_rows)} probes; jobs {args.jobs}; out {args.out}")

    systems, failures = {}, {}
    for a in anchors:
        print(f"anchor {a}: {len(probe_rows)} x {len(gallery_rows)} Open3D ICPs ...", flush=True)
        systems[a] = run_anchor(a, gallery_rows, probe_rows, intr, args.jobs)
        np.savez_compressed(args.out / f"{a}_scores.npz", S=systems[a]["S"],  # scores only, no data
                            probes=[r["path"] for r in probe_rows], gallery=[r["path"] for r in gallery_rows])
        print("  " + timing_lines({a: systems[a]})[0], flush=True)
    trained_on_tuning = []
    for m, method, options in specs:
        print(f"facerec3d {m}: evaluate(...) ...", flush=True)
        try:
            train = None
            if make_matcher(method, options).needs_training:
                if str(args.train) == "tuning":
                    train = tuning_manifest(args.data, manifest, args.out)
                    trained_on_tuning.append(m)
                else:
                    train = training_set(args.train)
            systems[m] = run_method(method, args.data, gallery_rows, probe_rows, args.out, args.jobs, args.cache,
                                    options, label=m, train=train, config=config)
            print("  " + timing_lines({m: systems[m]})[0], flush=True)
        except Exception as e:  # noqa: BLE001 - a failing method is reported, the benchmark goes on
            reason = " ".join(f"{type(e).__name__}: {e}".split())
            failures[m] = reason
            print(f"  FAILED {m}: {reason[:300]}", flush=True)
    for label, path in score_files:
        if label in systems:
            ap.error(f"--scores {label}: a label not used by another system, please")
        systems[label] = {**score_file_system(Path(path), args.data, gallery_rows, probe_rows),
                          "timings": {"score_file": path}}
        methods.append(label)
    methods = [m for m in methods if m in systems]

    groups = subject_groups([r["subject"] for r in manifest])
    results = {g: {name: group_metrics(s, members, probe_rows, gallery_rows) for name, s in systems.items()}
               for g, members in groups.items()}
    seed_notes = mean_over_seeds(results, seed_runs)
    methods += [name for name in results["all"] if name not in systems]  # the means over seeds
    fair = [m for m in methods if m not in trained_on_tuning]  # a method trained on the tuning half would win there
    best = max(fair, key=lambda m: results["tuning"][m]["rank1_all"] or 0.0) if fair else None
    tbls = tables(results, anchors, methods, best)
    times = timing_lines(systems)
    notes = [f"* best facerec3d method (highest rank-1 all on the tuning half): {best}" if best else
             "no facerec3d method ran", *seed_notes, *(f"FAILED {m}: {r}" for m, r in failures.items()),
             *([f"* trained on the tuning half's people (--train tuning): {', '.join(trained_on_tuning)}; their "
                "tuning and all-80 figures are not honest, the held-out half is"] if trained_on_tuning else [])]
    print()
    print(render(tbls, "text"))
    print("\n".join(notes + ["", "Times:"] + times))

    md = ["# Real-data benchmark: rap3df-2019 (Kinect v2)", "",
          "Rank-1 over every probe of the group (failures, unenrolled subjects and ties count as misses); "
          "EER / VR over every pair, pairs not compared rejected. Halves: subjects by even (tuning) / odd "
          "(held-out) index in sorted order, each its own closed set.", "",
          render(tbls, "md"), *[f"- {n}" for n in notes], "", "## Times", "", *[f"- {t}" for t in times], ""]
    (args.out / "real_bench.md").write_text("\n".join(md), encoding="utf-8")
    report = {"data": str(args.data), "jobs": args.jobs, "anchors": {"o3d-raw": RAW, "o3d-fair": FAIR},
              "min_points": MIN_POINTS, "groups": {g: sorted(s) for g, s in groups.items()},
              "results": results, "best_method": best, "failed_methods": failures,
              "timings": {n: s["timings"] for n, s in systems.items()},
              "median_points": {n: s["points"] for n, s in systems.items() if "points" in s},
              "facerec3d_metrics": {n: s["facerec3d_metrics"] for n, s in systems.items() if "facerec3d_metrics" in s},
              "failed_scans": {n: s.get("failed_scans") or [r["path"] for r, f in zip(probe_rows, s["failed_probe"]) if f]
                               + [r["path"] for r, f in zip(gallery_rows, s["failed_gallery"]) if f]
                               for n, s in systems.items()}}
    (args.out / "real_bench.json").write_text(json.dumps(report, indent=1, default=str), encoding="utf-8")
    print(f"\nwrote {args.out / 'real_bench.json'} and {args.out / 'real_bench.md'}")
    if failures and not systems:  # every system asked for failed: nothing was measured
        print(f"real_bench: every method failed ({'; '.join(failures)})", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
