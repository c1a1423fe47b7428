"""Learned-embedding speed: embedding a face and comparing embeddings, against ICP measured in the same run.

    python benchmarks/embedding_bench.py [--faces 200] [--gallery 10000] [--model facerec3d/models/embedding.onnx]

One process, one thread (onnxruntime intra-op threads 1, BLAS limited to 1), steady state: the ONNX session is
opened, Numba's ICP code compiled and the gallery's stacked matrix made before any figure is taken (those first
calls are reported on their own as "first use").

* embed: ms per preprocessed face (`EmbeddingMatcher.prepare`: the input window, its normals, the network), over
  `--faces` faces one at a time (as enrolment and a probe do), and per face in batches of 64; the peer is ICP's
  enrolment of the same faces (`ICPMatcher.enroll`: its search index) and its probe preparation.
* compare: comparisons per second of one probe against a gallery of `--gallery` embedding templates
  (`EmbeddingMatcher.scores`: one matrix-vector product), against ICP's comparisons per second of a prepared probe
  against 20 enrolled faces (`ICPMatcher.scores`).

Faces: synthetic identities in preprocessed form (`datasets.frontal`, no scanner), enough for timing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
from threadpoolctl import threadpool_limits

from facerec3d.datasets.frontal import frontal_face
from facerec3d.matching.base import Template
from facerec3d.matching.embedding import SHIPPED_MODEL, EmbeddingConfig, EmbeddingMatcher
from facerec3d.matching.icp import ICPMatcher


def per_call(fn, items) -> float:
    t0 = time.perf_counter()
    for x in items:
        fn(x)
    return (time.perf_counter() - t0) / len(items)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--faces", type=int, default=200)
    ap.add_argument("--gallery", type=int, default=10000)
    ap.add_argument("--model", default=str(SHIPPED_MODEL))
    args = ap.parse_args()
    faces = [frontal_face(s, pose_deg=2.0, noise_mm=0.3, seed=s) for s in range(args.faces)]
    emb = EmbeddingMatcher(EmbeddingConfig(model=args.model, threads=1))
    icp = ICPMatcher()
    with threadpool_limits(1):
        t0 = time.perf_counter()
        emb.prepare(faces[0])
        first_embed = time.perf_counter() - t0
        t0 = time.perf_counter()
        icp.scores(icp.prepare(faces[0]), [icp.enroll(faces[1])])
        first_icp = time.perf_counter() - t0
        embed_s = per_call(emb.prepare, faces)
        starts = range(0, len(faces), 64)
        batch_s = per_call(lambda i: emb.embed(faces[i:i + 64]), starts) * len(starts) / len(faces)
        icp_enrol_s = per_call(icp.enroll, faces[: min(50, len(faces))])
        icp_prepare_s = per_call(icp.prepare, faces[: min(50, len(faces))])

        rng = np.random.default_rng(0)
        vectors = rng.normal(size=(args.gallery, emb.embed(faces[:1]).shape[1])).astype(np.float32)
        vectors /= np.linalg.norm(vectors, axis=1, keepdims=True)
        gallery = [Template(f"g{i}", None, "embedding", {"embedding": v}) for i, v in enumerate(vectors)]
        probes = [emb.prepare(f) for f in faces[:50]]
        t0 = time.perf_counter()
        emb.scores(probes[0], gallery)  # stacks the gallery once (kept while the gallery is the same)
        first_stack = time.perf_counter() - t0
        emb_cmp_s = per_call(lambda p: emb.scores(p, gallery), probes) / args.gallery
        icp_gallery = [icp.enroll(f) for f in faces[:20]]
        icp_probes = [icp.prepare(frontal_face(s, pose_deg=3.0, noise_mm=0.3, seed=500 + s)) for s in range(5)]
        icp_cmp_s = per_call(lambda p: icp.scores(p, icp_gallery), icp_probes) / len(icp_gallery)

    print(f"model {args.model}; one process, one thread; {args.faces} faces, gallery of {args.gallery} embeddings")
    print(f"first use (not in the figures below): open the ONNX session and embed one face {first_embed * 1e3:.0f} ms; "
          f"ICP's first comparison (Numba JIT or cache load) {first_icp * 1e3:.0f} ms; stacking the gallery "
          f"{first_stack * 1e3:.1f} ms")
    print(f"embed one face:       {embed_s * 1e3:7.2f} ms   (in batches of 64: {batch_s * 1e3:.2f} ms per face)")
    print(f"  ICP enrolment:      {icp_enrol_s * 1e3:7.2f} ms per face ({icp_enrol_s / embed_s:.1f}x the embedding's); "
          f"ICP probe preparation {icp_prepare_s * 1e3:.2f} ms ({icp_prepare_s / embed_s:.1f}x)")
    print(f"compare:              {1 / emb_cmp_s:12,.0f} comparisons per second "
          f"({emb_cmp_s * 1e9:.0f} ns each)")
    print(f"  ICP:                {1 / icp_cmp_s:12,.0f} comparisons per second ({icp_cmp_s * 1e3:.2f} ms each): "
          f"the embedding compares {icp_cmp_s / emb_cmp_s:,.0f}x faster")
    print(f"targets (issue 22): embed <= 20 ms per face on one core: {'met' if embed_s <= 0.020 else 'NOT met'}; "
          f">= 500,000 comparisons per second per process: {'met' if 1 / emb_cmp_s >= 5e5 else 'NOT met'}")


if __name__ == "__main__":
    main()
