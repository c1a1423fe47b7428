"""Training faces for the learned embedding: the synthetic scanner's faces through the project's own preprocessing.

Each identity is a face of the synthetic generator (`datasets.synthetic`) that no benchmark or test uses (its
own generator seed and subject numbers from `FIRST_SUBJECT` on), half of them from the model's prior and half
outside the model's span (`outside-model`: wider spread, a non-linear deformation, occluders). Each of its scans
is taken by a sensor drawn from `sensors` (laser, Kinect v2 at 1 mm or 8-bit steps, RealSense), at a random
head pose (yaw up to ±45°, pitch ±20°, roll ±10°: real Kinect frames reach 30–45°) with a random expression on
half of them, and goes through the whole preprocessing a user's scan goes through (`Preprocessor`: spikes,
detection, crop, frontalisation, resampling), so the network learns faces with the artefacts it will meet: depth
steps, flying pixels, self-occlusion at pose, residual alignment error. A scan that fails to preprocess is
counted (FTA) and left out.

What is kept of a face is its input window of depth (`matching.embedding.window_depth`) with a margin around it,
so that training can shift it (more alignment error) before `input_channels`. The set is saved as one .npz (no
pickle) with the recipe that made it, and reused when the recipe is the same.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from facerec3d.errors import FaceRec3DError
from facerec3d.matching.embedding import InputRecipe, seen_depth, window_depth
from facerec3d.scan import FaceScan
from facerec3d.workers import Workers

FIRST_SUBJECT = 100_000  # training identities are subject numbers from here on (tests and benchmarks use 0, 1, ...)
SENSORS = ("frgc", "kinect-v2", "kinect-v2-8bit", "realsense")
IDENTITIES = ("model", "outside-model")
EXPRESSIONS = ("smile", "open-mouth", "surprise", "frown", "puffed-cheeks")


@dataclass(frozen=True)
class DataRecipe:
    """What `synthetic_training_set` makes (recorded in the model card)."""

    identities: int = 1200
    scans: int = 6  # per identity
    sensors: tuple[str, ...] = SENSORS  # drawn per scan
    identity_profiles: tuple[str, ...] = IDENTITIES  # taken in turn by identity
    seed: int = 2026  # the generator's seed (identity coefficients) and every draw of poses and sensors
    max_yaw: float = 45.0  # degrees either way (--max-yaw)
    max_pitch: float = 20.0  # degrees up or down (--max-pitch)
    max_roll: float = 10.0
    expression_share: float = 0.5  # share of scans with an expression (strength 0.3–1)
    margin: int = 4  # extra input cells kept on each side of the window, for shifted crops in training

    def __post_init__(self) -> None:
        from facerec3d.datasets.synthetic import IDENTITY_PROFILES, SENSOR_PROFILES

        if self.identities < 2 or self.scans < 2:
            raise ValueError("need at least 2 identities and 2 scans per identity")
        if not (0 <= self.max_yaw <= 90 and 0 <= self.max_pitch <= 60 and 0 <= self.max_roll <= 45):
            raise ValueError("head poses: need 0 ≤ max_yaw ≤ 90, 0 ≤ max_pitch ≤ 60, 0 ≤ max_roll ≤ 45 (degrees)")
        for field_, names, known in (("sensors", self.sensors, SENSOR_PROFILES),
                                     ("identity_profiles", self.identity_profiles, IDENTITY_PROFILES)):
            if not names or set(names) - set(known):
                raise ValueError(f"{field_}: use one or more of {', '.join(known)} (given {', '.join(names)})")


@dataclass
class TrainingSet:
    """Input windows with their margin (N, m, m) mm (NaN: unseen), integer identity labels, the sensor of each."""

    windows: np.ndarray
    labels: np.ndarray
    sensors: np.ndarray
    info: dict[str, Any]

    def save(self, path: str | Path) -> None:
        with open(path, "wb") as f:
            np.savez_compressed(f, windows=self.windows.astype(np.float16), labels=self.labels,
                                sensors=self.sensors.astype(str), info=np.array(json.dumps(self.info)))

    def joined(self, other: "TrainingSet") -> "TrainingSet":
        """This set and another (labels kept as they are: give the other its own range)."""
        return TrainingSet(np.concatenate([self.windows, other.windows]), np.concatenate([self.labels, other.labels]),
                           np.concatenate([self.sensors.astype(str), other.sensors.astype(str)]),
                           {**self.info, "real": other.info, "scans": int(len(self.labels) + len(other.labels))})

    @classmethod
    def load(cls, path: str | Path) -> "TrainingSet":
        try:
            with np.load(path, allow_pickle=False) as d:
                return cls(d["windows"].astype(np.float32), d["labels"].astype(np.int64), d["sensors"],
                           json.loads(str(d["info"])))
        except (OSError, ValueError, KeyError) as e:
            raise FaceRec3DError(f"{path}: not a facerec3d training set ({e})") from None


def training_window(face: FaceScan, inputs: InputRecipe, margin: int) -> np.ndarray:
    """A preprocessed face's input window of depth with `margin` more cells on each side (float32 mm, NaN unseen)."""
    wider = InputRecipe(inputs.half_width_mm + margin * inputs.step_mm, inputs.step_mm, inputs.depth_scale_mm)
    return window_depth(seen_depth(face), wider).astype(np.float32)


def training_pose(rng: np.random.Generator, recipe: DataRecipe, first: bool = False) -> np.ndarray:
    """A training scan's head pose (yaw, pitch, roll; degrees), uniform within the recipe's ranges; an identity's
    first scan is near-frontal (a fifth of the ranges), as an enrolment would be."""
    pose = rng.uniform(-1, 1, 3) * (recipe.max_yaw, recipe.max_pitch, recipe.max_roll)
    return pose * 0.2 if first else pose


def _identity_scans(identity: int, recipe: DataRecipe, inputs: InputRecipe) -> list[tuple[np.ndarray | None, str]]:
    """The windows (None: failed to preprocess) and sensors of one training identity's scans."""
    from facerec3d.datasets.synthetic import FaceScanner, ScanSpec, identity_profile, sensor_profile
    from facerec3d.preprocess.pipeline import Preprocessor

    rng = np.random.default_rng([recipe.seed, identity, 4242])
    profile = identity_profile(recipe.identity_profiles[identity % len(recipe.identity_profiles)])
    subject = FIRST_SUBJECT + identity
    preprocess = Preprocessor()
    scanners: dict[str, FaceScanner] = {}
    out = []
    for k in range(recipe.scans):
        sensor = recipe.sensors[rng.integers(len(recipe.sensors))]
        if sensor not in scanners:
            scanners[sensor] = FaceScanner(sensor_profile(sensor), seed=recipe.seed, identity=profile)
        expression, strength = "neutral", 1.0
        if rng.random() < recipe.expression_share:
            expression, strength = EXPRESSIONS[rng.integers(len(EXPRESSIONS))], float(rng.uniform(0.3, 1.0))
        pose = training_pose(rng, recipe, first=k == 0)
        occluders = profile.occluders
        occluder = occluders[rng.integers(len(occluders))] if rng.random() < 0.5 else None
        spec = ScanSpec(subject, expression, strength, *map(float, pose), seed=k, occluder=occluder)
        try:
            out.append((training_window(preprocess(scanners[sensor].scan(spec).scan), inputs, recipe.margin), sensor))
        except FaceRec3DError:
            out.append((None, sensor))
    return out


def synthetic_training_set(recipe: DataRecipe = DataRecipe(), inputs: InputRecipe = InputRecipe(),
                           workers: Workers | None = None, progress: bool = True, first: int = 0) -> TrainingSet:
    """Make the training set of `recipe` on `workers` (default: this process): its identities from `first` on
    (each identity's scans depend on the recipe's seed and the identity alone, so a set can be made in parts)."""
    from tqdm import tqdm

    workers = workers or Workers.create(1)
    windows, labels, sensors, failures = [], [], [], 0
    items = range(first, recipe.identities)
    for identity, scans in zip(items, tqdm(workers.imap(_identity_scans, items, recipe, inputs),
                                           total=len(items), desc="training faces", unit="identity",
                                           disable=not progress)):
        for window, sensor in scans:
            if window is None:
                failures += 1
                continue
            windows.append(window)
            labels.append(identity)
            sensors.append(sensor)
    if not windows:
        raise FaceRec3DError("no training scan could be preprocessed")
    info = {"recipe": _jsonable(recipe), "input": asdict(inputs), "preprocess": _preprocess_digest(),
            "scans": len(windows), "failures": failures}
    return TrainingSet(np.stack(windows), np.asarray(labels, np.int64), np.asarray(sensors), info)


def _preprocess_digest() -> str:
    """The digest of the preprocessing the training faces are made with (`_identity_scans`: the defaults)."""
    from facerec3d.preprocess.pipeline import PreprocessConfig

    return PreprocessConfig().digest()


def _jsonable(recipe: DataRecipe) -> dict[str, Any]:
    return json.loads(json.dumps(asdict(recipe)))


def cached_training_set(path: str | Path, recipe: DataRecipe, inputs: InputRecipe, workers: Workers | None = None,
                        progress: bool = True) -> TrainingSet:
    """The training set saved at `path` when it was made with the same recipes and preprocessing, else a new one
    saved there. A saved set of the same recipe with fewer identities is extended (only the new identities are
    made). A set made by other preprocessing settings (another version's) is made again: its faces are not what
    preprocessing gives the network now."""
    path = Path(path)
    have: TrainingSet | None = None
    if path.is_file():
        data = TrainingSet.load(path)
        saved = data.info.get("recipe", {})
        same = data.info.get("input") == asdict(inputs) and data.info.get("preprocess") == _preprocess_digest()
        if same and saved == _jsonable(recipe):
            return data
        if same and saved.get("identities", 0) < recipe.identities and \
                {**saved, "identities": recipe.identities} == _jsonable(recipe):
            have = data
    first = have.info["recipe"]["identities"] if have is not None else 0
    data = synthetic_training_set(recipe, inputs, workers, progress, first=first)
    if have is not None:
        data = TrainingSet(np.concatenate([have.windows, data.windows]), np.concatenate([have.labels, data.labels]),
                           np.concatenate([have.sensors.astype(str), data.sensors.astype(str)]),
                           {**data.info, "scans": int(len(have.labels) + len(data.labels)),
                            "failures": int(have.info["failures"] + data.info["failures"])})
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    data.save(tmp)
    tmp.replace(path)
    return data


def chosen_subjects(subjects: list[str], choice: str | None) -> set[str]:
    """The subjects `choice` names: all (None), 'even' / 'odd' (every other subject in sorted order: the tuning /
    held-out halves of benchmarks/real_bench.py), or a file with one subject per line."""
    order = sorted(set(subjects))
    if choice is None:
        return set(order)
    if choice in ("even", "odd"):
        return set(order[0 if choice == "even" else 1::2])
    try:
        wanted = {line.strip() for line in Path(choice).read_text().splitlines() if line.strip()}
    except OSError as e:
        raise FaceRec3DError(f"{choice}: not 'even', 'odd' or a readable file of subjects ({e.strerror})") from None
    if not wanted & set(order):
        raise FaceRec3DError(f"{choice}: none of its subjects is in the dataset")
    return wanted


def real_training_set(source: str | Path, subjects: str | None, inputs: InputRecipe, margin: int,
                      workers: Workers | None = None, cache: str | Path | None = None,
                      first_label: int = 0) -> TrainingSet:
    """Real people's faces as training identities (labels from `first_label` on): the dataset's scans of the
    chosen `subjects` (`chosen_subjects`), preprocessed as any scan is (cached in `cache`)."""
    from facerec3d.datasets.catalog import open_dataset
    from facerec3d.preprocess.batch import preprocess_files

    records = open_dataset(source).records
    keep = chosen_subjects([r.subject for r in records], subjects)
    records = [r for r in records if r.subject in keep]
    people = sorted({r.subject for r in records})
    windows, labels, failures = [], [], 0
    for record, outcome in zip(records, preprocess_files([r.path for r in records], workers=workers, cache=cache)):
        if outcome.face is None:
            failures += 1
            continue
        windows.append(training_window(outcome.face, inputs, margin))
        labels.append(first_label + people.index(record.subject))
    if not windows:
        raise FaceRec3DError(f"{source}: no scan of the chosen subjects could be preprocessed")
    info = {"source": str(source), "subjects": len(people), "choice": subjects, "scans": len(windows),
            "failures": failures}
    return TrainingSet(np.stack(windows), np.asarray(labels, np.int64), np.full(len(windows), "real"), info)
