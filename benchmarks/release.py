"""The same work timed with an earlier release of facerec3d, in the same run: the ratio figures of the benches.

    python benchmarks/release.py [--ref 6c9c085] FILE... [--intrinsics J]    # this tree against the release

`release_tree(ref)` extracts that commit of this repository (`git archive`) into
`~/.cache/facerec3d-bench/REF/`, once. `time_files(tree, files)` runs the timing in a child Python whose
`facerec3d` is that tree (PYTHONPATH; `tree=None`: this checkout), one BLAS thread, so both versions read, preprocess
and enrol the very same files the same way: the first file is preprocessed once before timing (Numba
compilation, cold caches: not steady state), then each file is read, preprocessed (`Preprocessor()`) and enrolled
(`icp`'s template: normals, boundary, the voxel lookup), each step timed on its own. A failure to acquire is
recorded (None) and the run goes on. The release must read the files: `.abs` / `.abs.gz` range scans and depth
frames (PNG + intrinsics) are read by every release since 6c9c085.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import shutil
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
RELEASE = "6c9c085"  # the previous release the preprocessing speed issue measures against
CACHE = Path(os.environ.get("FACEREC3D_BENCH_CACHE", Path.home() / ".cache" / "facerec3d-bench"))

_CHILD = r"""
import json, os, sys, time
import facerec3d
from facerec3d.errors import FaceRec3DError
from facerec3d.io import load_scan
from facerec3d.matching.methods import make_method
from facerec3d.preprocess import Preprocessor

files, intrinsics, faces = json.loads(sys.argv[1]), sys.argv[2] or None, sys.argv[3] == "faces"
pre, icp = (lambda face: face) if faces else Preprocessor(), make_method("icp")
icp.enroll(pre(load_scan(files[0], intrinsics)))  # compilation and cold caches: not timed
rows = []
for f in files:
    t0 = time.perf_counter()
    scan = load_scan(f, intrinsics)
    t1 = time.perf_counter()
    try:
        face = pre(scan)
    except FaceRec3DError:
        rows.append([t1 - t0, None, None])
        continue
    t2 = time.perf_counter()
    icp.enroll(face)
    rows.append([t1 - t0, t2 - t1, time.perf_counter() - t2])
print(json.dumps({"package": os.path.dirname(facerec3d.__file__), "rows": rows}))
"""


def release_tree(ref: str = RELEASE) -> Path:
    """This repository at commit `ref`, extracted once under the bench cache; raises RuntimeError (one line) when
    this checkout has no git history holding it."""
    target = CACHE / ref
    if (target / "facerec3d" / "__init__.py").exists():
        return target
    try:
        blob = subprocess.run(["git", "-C", str(ROOT), "archive", "--format=tar", ref], check=True,
                              capture_output=True).stdout
    except (OSError, subprocess.CalledProcessError) as e:
        why = e.stderr.decode(errors="replace").strip() if isinstance(e, subprocess.CalledProcessError) else str(e)
        raise RuntimeError(f"release {ref} is not in this checkout's git history ({why})") from None
    partial = target.parent / f"{ref}.partial"
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    with tarfile.open(fileobj=io.BytesIO(blob)) as tar:
        tar.extractall(partial, filter="data")
    os.replace(partial, target)
    return target


def time_files(tree: Path | None, files: list[Path], intrinsics: Path | None = None, faces: bool = False) -> np.ndarray:
    """(n, 3) seconds per file: read, preprocess, enrol (NaN after a failure to acquire), timed by `tree`'s
    facerec3d (None: this checkout's) in a child process with one BLAS thread; `faces`: the files are faces
    already preprocessed (`.npz`), only read and enrolled (preprocessing 0)."""
    env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
               PYTHONPATH=str(tree or ROOT))
    files = [Path(f).resolve() for f in files]  # the child runs elsewhere (cwd below): paths as the caller meant them
    intrinsics = Path(intrinsics).resolve() if intrinsics else None
    out = subprocess.run([sys.executable, "-c", _CHILD, json.dumps([str(f) for f in files]), str(intrinsics or ""),
                          "faces" if faces else "scans"],
                         env=env, capture_output=True, text=True, cwd=tempfile.gettempdir())
    if out.returncode:
        raise RuntimeError(f"timing with {tree or ROOT} failed: {out.stderr.strip().splitlines()[-1:]}")
    result = json.loads(out.stdout.strip().splitlines()[-1])
    expected = (tree or ROOT) / "facerec3d"
    if Path(result["package"]).resolve() != expected.resolve():
        raise RuntimeError(f"the child imported facerec3d from {result['package']}, not {expected}")
    return np.array([[np.nan if v is None else v for v in row] for row in result["rows"]], dtype=float)


def compare(files: list[Path], intrinsics: Path | None = None, ref: str = RELEASE,
            faces: bool = False) -> dict[str, tuple[float, float]]:
    """{"preprocess" | "enrol" | "read": (median ms of this tree, median ms of release `ref`)} over `files`
    (`time_files`)."""
    here = time_files(None, files, intrinsics, faces)
    then = time_files(release_tree(ref), files, intrinsics, faces)
    names = ("read", "preprocess", "enrol")
    return {name: (float(np.nanmedian(here[:, k])) * 1e3, float(np.nanmedian(then[:, k])) * 1e3)
            for k, name in enumerate(names)}


def report(label: str, figures: dict[str, tuple[float, float]], ref: str = RELEASE) -> None:
    """One line per step: this tree's median ms, the release's, and the speed-up (release ÷ this tree)."""
    for name in ("preprocess", "enrol", "read"):
        now, then = figures[name]
        if not now and not then:
            continue
        print(f"  {label}, {name}: {now:.0f} ms per file, release {ref} {then:.0f} ms: {then / now:.2f}× as fast "
              f"(median, one core, steady state)")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", type=Path)
    ap.add_argument("--intrinsics", type=Path)
    ap.add_argument("--ref", default=RELEASE)
    args = ap.parse_args()
    try:
        report(f"{len(args.files)} files", compare(args.files, args.intrinsics, args.ref), args.ref)
    except RuntimeError as e:
        sys.exit(f"release.py: {e}")


if __name__ == "__main__":
    main()
