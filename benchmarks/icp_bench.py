"""ICP matching benchmark (chapter §8.6.1): ms per probe–gallery match against Open3D, and identification time.

    python benchmarks/icp_bench.py [--quick]

Faces are ICT-FaceKit morphable-model identities like preprocessed scans: the
face (model region 0) with the nose tip at the origin, rasterised on the 1 mm
x–y grid of preprocessing (§8.5.6) and cropped to 80 mm around the nose
(~18k points with the 95 mm crop). A probe is the same identity moved by a small random pose
(≤ 3°, ≤ 3 mm, as left by pose normalisation), rasterised on that grid, with
0.3 mm Gaussian depth noise; the ground truth is the inverse motion.

Prints, for facerec3d's ICP (both variants) and Open3D's point-to-point
`registration_icp` (same maximum iterations, maximum correspondence distance
= facerec3d's initial threshold; with the whole probe and with as many random
probe points as facerec3d's fine phase uses), the median ms per match and the
median alignment errors; then the time to score one probe against a gallery
of 466 enrolled identities. Everything runs on one core (OMP_NUM_THREADS=1,
process pinned to one CPU); Numba is compiled before timing.
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from facerec3d.datasets.frontal import CROP_MM, face_mesh, on_preprocessing_grid  # noqa: E402
from facerec3d.geometry.transforms import rotation_between, rotation_from_euler  # noqa: E402
from facerec3d.matching import ICPConfig, ICPMatcher, Template  # noqa: E402
from facerec3d.scan import FaceScan, ScanMeta  # noqa: E402

NOISE_MM = 0.3


def resampled_face(subject: int, R: np.ndarray, t: np.ndarray, noise: float, rng: np.random.Generator) -> FaceScan:
    """Identity `subject` moved by x -> R x + t, on the 1 mm preprocessing grid, cropped, with depth noise."""
    vertices, tris = face_mesh(subject)
    scan = on_preprocessing_grid(vertices @ R.T + t, tris)
    points = scan.points.copy()
    points[:, 2] += rng.normal(0.0, noise, len(points))
    return scan.replace(points=points, meta=ScanMeta(subject=str(subject)))


def probe_pair(subject: int, rng: np.random.Generator) -> tuple[FaceScan, FaceScan, np.ndarray, np.ndarray]:
    """(gallery, probe, R, t): the true probe-to-gallery motion x -> R x + t."""
    gallery = resampled_face(subject, np.eye(3), np.zeros(3), 0.0, rng)
    Rp = rotation_from_euler(*rng.uniform(-3.0, 3.0, 3))
    tp = rng.uniform(-3.0, 3.0, 3)
    probe = resampled_face(subject, Rp, tp, NOISE_MM, rng)
    return gallery, probe, Rp.T, -Rp.T @ tp


def timed(fn, repeats: int) -> tuple[float, object]:
    """(median seconds, last result) of repeated calls."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), out


def open3d_icp(probe: FaceScan, gallery: FaceScan, max_distance: float, iterations: int):
    import open3d as o3d

    reg = o3d.pipelines.registration
    src, dst = o3d.geometry.PointCloud(), o3d.geometry.PointCloud()
    src.points = o3d.utility.Vector3dVector(probe.points)
    dst.points = o3d.utility.Vector3dVector(gallery.points)
    criteria = reg.ICPConvergenceCriteria(max_iteration=iterations)
    return lambda: reg.registration_icp(src, dst, max_distance, np.eye(4), reg.TransformationEstimationPointToPoint(),
                                        criteria)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer pairs and repetitions, 100-face gallery")
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    n_pairs, repeats, n_gallery = (4, 5, 100) if args.quick else (12, 15, 466)
    rng = np.random.default_rng(7)
    pairs = [probe_pair(s, rng) for s in range(n_pairs)]
    print(f"faces: {np.mean([len(g) for g, *_ in pairs]):.0f} gallery points (1 mm grid, {CROP_MM:.0f} mm crop); "
          f"probes ≤3°/≤3 mm off with {NOISE_MM} mm noise; medians over {n_pairs} pairs × {repeats} runs, one core")

    rows = []
    for variant in ("point-to-point", "point-to-plane"):
        config = ICPConfig(variant=variant)
        matcher = ICPMatcher(config)
        ms, rot, tra, enrol_ms, prep_ms = [], [], [], [], []
        for gallery, probe, R, t in pairs:
            s, template = timed(lambda: matcher.enroll(gallery), 1)
            enrol_ms.append(s * 1e3)
            s, prepared = timed(lambda: matcher.prepare(probe), 1)
            prep_ms.append(s * 1e3)
            matcher.align(prepared, template)  # compile / warm up
            s, result = timed(lambda: matcher.align(prepared, template), repeats)
            ms.append(s * 1e3)
            rot.append(rotation_between(R, result.R))
            tra.append(float(np.linalg.norm(result.t - t)))
        rows.append((f"facerec3d {variant}", np.median(ms), np.median(rot), np.median(tra)))
        if variant == "point-to-point":
            p2p = rows[-1]
            print(f"facerec3d: enrol {np.median(enrol_ms):.0f} ms, prepare probe {np.median(prep_ms):.0f} ms, "
                  f"template {template.nbytes / 1024:.0f} KiB ({template.nbytes} bytes)")

    config = ICPConfig()
    try:
        import open3d  # noqa: F401
    except (ImportError, OSError) as e:  # OSError: a shared library such as libusb-1.0 is missing
        print(f"Open3D not available ({e}): `pip install open3d` (or `pip install facerec3d[bench]`) and, on "
              "Debian/Ubuntu, `apt-get install libusb-1.0-0` to compare with it.")
    else:
        subset = np.random.default_rng(0)
        for label, n_points in (("", None), (f", {config.fine_points}-pt probe", config.fine_points)):
            ms, rot, tra = [], [], []
            for gallery, probe, R, t in pairs:
                if n_points:
                    probe = probe.subset(subset.choice(probe.n_points, n_points, replace=False))
                run = open3d_icp(probe, gallery, config.distance_start * gallery.resolution(), config.max_iterations)
                run()
                s, result = timed(run, max(3, repeats // 3))
                T = np.asarray(result.transformation)
                ms.append(s * 1e3)
                rot.append(rotation_between(R, T[:3, :3]))
                tra.append(float(np.linalg.norm(T[:3, 3] - t)))
            rows.append((f"Open3D point-to-point{label}", np.median(ms), np.median(rot), np.median(tra)))

    print(f"\n{'method':38s} {'ms/match':>9s} {'rot err °':>10s} {'trans err mm':>13s}")
    for name, m, r, tr in rows:
        print(f"{name:38s} {m:9.2f} {r:10.3f} {tr:13.3f}")
    print("(facerec3d: gallery structures built at enrolment, probe normals and subset in prepare; "
          "Open3D builds its k-d tree in each call; steady state: each match timed after one untimed call, so JIT "
          "compilation and cold caches are left out; enrol / prepare: medians over the faces, the first holding "
          "the JIT)")
    for name, m, *_ in rows[2:]:
        print(f"speed-up ({name} ms / facerec3d point-to-point ms): {m / p2p[1]:.0f}×")

    print(f"\nidentification: enrolling {n_gallery} identities ...", flush=True)
    matcher = ICPMatcher(config)
    t0 = time.perf_counter()
    gallery: list[Template] = [matcher.enroll(resampled_face(s, np.eye(3), np.zeros(3), 0.0, rng))
                               for s in range(n_gallery)]
    enrol_s = time.perf_counter() - t0
    size = sum(t.nbytes for t in gallery)
    probe = matcher.prepare(pairs[0][1])
    matcher.scores(probe, gallery[:2])
    s, (scores, _) = timed(lambda: matcher.scores(probe, gallery), 3)
    rank = int(np.sum(scores > scores[0])) + 1
    print(f"gallery of {n_gallery}: enrolment {enrol_s / n_gallery * 1e3:.0f} ms/face, {size / 2**20:.0f} MiB in all; "
          f"scores() of one probe {s * 1e3:.0f} ms ({s / n_gallery * 1e3:.2f} ms/template); genuine rank {rank} "
          "(steady state: kernels compiled above, scores() warmed on 2 templates first)")


if __name__ == "__main__":
    main()
