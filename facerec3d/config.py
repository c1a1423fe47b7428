"""Settings files: TOML or JSON into the typed config dataclasses (partial, nested, unknown keys refused).

Every value is checked against its field's type (`float`, `int`, `bool`, `str`, `X | None`, tuples, nested
configs) and range (`RANGES`, by field name), and the config's own checks (`__post_init__`) run; a wrong value
raises `SettingsError` naming the file, the dotted field (`resample.resolution_mm`) and the reason, on one line.
"""

from __future__ import annotations

import dataclasses
import difflib
import functools
import json
import math
import tomllib
import types
import typing
from pathlib import Path
from typing import Any

from facerec3d.errors import SettingsError

POSITIVE = (0.0, math.inf, False)  # (low, high, low allowed): > 0
NON_NEGATIVE = (0.0, math.inf, True)  # >= 0
FRACTION = (0.0, 1.0, True)  # in [0, 1]
ANY = (-math.inf, math.inf, True)
MAX_GRID_SIDE = 2000  # cells a side of the largest range image facerec3d reads (io.common.MAX_POINTS is its square)
MAX_INT = 2**31 - 1  # counts, seeds and sizes: larger ones are mistakes (and overflow NumPy's integers)

#: Range of each numeric field, by name (the same name means the same kind of quantity in every config);
#: numbers not named here must be >= 0. Sizes, radii, steps and counts that something is divided by or
#: sampled at must be > 0.
RANGES: dict[str, tuple[float, float, bool]] = {
    **dict.fromkeys((
        # preprocessing
        "crop_radius_mm", "coverage_radius_mm", "window", "distance_mm", "k", "sample_mm",
        "window_mm", "separation_mm", "candidates", "context_mm", "seen_radius_mm", "seen_radius_px",
        "tip_radius_mm", "ring_mm", "crown_mm", "crown_reach_mm", "crown_depth_mm", "max_roll_deg", "finalists",
        "screened", "iterations", "start_distance_mm", "end_distance_mm", "radius_mm", "max_points", "nose_candidates",
        "core_radius_mm", "inlier_mm", "ring_px", "resolution_mm", "half_width_mm", "edge_factor",
        # matching
        "max_iterations", "coarse_points", "distance_start", "distance_end", "max_reach_mm", "voxel_size",
        "normal_neighbours", "step_mm", "sigma_mm", "committee_radius", "radius", "nms_radius", "max_keypoints",
        "patch_radius", "patch_bins", "max_offset", "ransac_iterations", "n_components", "pca_components"),
        POSITIVE),
    **dict.fromkeys(("min_coverage", "rim_coverage", "min_disc_coverage", "min_coarse_inliers", "min_inliers", "min_seen",
                     "min_overlap", "variance", "pca_share"), FRACTION),
    "start_yaws": ANY,  # degrees, either way
    "min_y_mm": ANY,  # a height from the nose tip (the cascade's screen: -15 mm, below it)
}

#: Fields that name a file (a model): a relative path in a settings file is taken from that file's folder, as a
#: user who keeps a model beside the file that names it expects, wherever the command runs from (from the working
#: folder when no such file is there: the way settings files were read before 2026-12-06).
FILE_FIELDS = frozenset({"proposer", "model"})


#: The method `evaluate`, `enroll` and the service use when none is named: the z-score fusion of whole-face ICP,
#: region ICP and the learned embedding (FusionConfig's defaults), chosen across every kind of data at once
#: (`benchmarks/default_bench.py`, `benchmarks/real_bench.py`, docs/methods.md): the best mean rank-1 over the
#: synthetic sensor profiles, outside-model faces and the rap3df-2019 held-out half together, and on that held-out
#: half above the fusion of icp and region-icp it replaced; region ICP stays in it for the unseen real sets of issue
#: 21, where it was the strongest single method. Its scores are normalised per probe over the gallery, so its
#: thresholds hardly depend on the sensor (DEFAULT_THRESHOLDS). A name of matching.registry.METHODS.
DEFAULT_METHOD = "fusion"

#: Default verification thresholds (score = similarity) by method, used only where the gallery has no calibrated
#: threshold (`facerec3d gallery G calibrate`, evaluation.calibrate; gallery.service.gallery_threshold; `verify
#: --help` names them): ICP's plane-capped −MSE (mm², `plane_cap_mm`) at the equal error rate of the synthetic
#: test60 protocol (0.7 mm laser-like scans: −1.81; real Kinect v2 frames need about −3.7, so calibrate; the book's
#: −MSE of the kept pairs had −1.0 and −5.9).
DEFAULT_THRESHOLDS: dict[str, float] = {"fusion": 4.0, "embedding": 0.5, "icp": -1.8}
#   fusion (the default members icp, region-icp and embedding: z-scores summed, per probe over the gallery): 4.0 is
#   near its threshold at FMR 1 % on real Kinect v2 frames (rap3df-2019, an 80-person gallery: 4.82, 4.41 with the
#   book's ICP score) and among those of the 15-person synthetic sets (3.8–6.5; so few impostor pairs that one moves
#   it): a cohort-normalised score depends on the sensor less than ICP's (at FMR 1 %: −1.5 mm² on laser scans, −2.6 on
#   the real Kinect frames), but it grows with the gallery's size. Galleries still calibrate their own.
#   embedding (cosine of the shipped model's embeddings): 0.5 lies between its FMR-1 % thresholds on synthetic
#   scans (about 0.4) and on the real Kinect frames (0.62, where real faces crowd together): calibrate.


class Settings(dict):
    """A settings table that remembers the file it was read from, for error messages."""

    def __init__(self, data: dict, source: str | Path | None = None):
        super().__init__(data)
        self.source = None if source is None else str(source)


def read_settings(path: str | Path) -> Settings:
    """A TOML (.toml) or JSON settings file as a dict; errors name the file."""
    kind = "JSON" if str(path).endswith(".json") else "TOML"
    try:
        text = Path(path).read_text(encoding="utf-8")
        data = json.loads(text) if kind == "JSON" else tomllib.loads(text)
    except (tomllib.TOMLDecodeError, json.JSONDecodeError, UnicodeDecodeError) as e:
        raise SettingsError(path, None, f"not valid {kind}: {e}".splitlines()[0]) from None
    except ValueError:  # Python's limit on the digits of an integer (4,300)
        raise SettingsError(path, None, f"not usable {kind}: a number of thousands of digits") from None
    except RecursionError:
        raise SettingsError(path, None, f"not usable {kind}: lists or tables nested thousands deep") from None
    except OSError as e:
        raise SettingsError(path, None, f"cannot read ({e.strerror or e})") from None
    if not isinstance(data, dict):
        raise SettingsError(path, None, f"a settings file holds a table of fields, not {type(data).__name__}")
    return Settings(data, path)


def from_dict(cls, data: dict[str, Any], source: str | Path | None = None, prefix: str = "", base=None):
    """A config dataclass from a (partial, nested) dict, every value checked (module docstring). `source` is the
    file named in errors (default: the file a `Settings` was read from); `prefix` the dotted section; `base` the
    instance whose other fields it keeps (else the class's defaults)."""
    source = source if source is not None else getattr(data, "source", None)
    if not isinstance(data, dict):
        raise SettingsError(source, prefix.rstrip(".") or None, f"must be a table of {cls.__name__} settings")
    known = {f.name for f in dataclasses.fields(cls)}
    retired = getattr(cls, "RETIRED", {})  # settings removed since: stored at the value that did nothing, they are
    for name in set(data) & set(retired) - known:  # dropped (a gallery enrolled then stays readable), else refused
        if data[name] != retired[name]:
            raise SettingsError(source, prefix + name, f"was removed (only {retired[name]!r} is still read), "
                                                       f"not {data[name]!r}"[:200])
        data = {k: v for k, v in data.items() if k != name}
    if unknown := sorted(map(str, set(data) - known)):
        close = difflib.get_close_matches(unknown[0], sorted(known), n=1)
        hint = f"did you mean {close[0]!r}?" if close else f"this table's settings: {', '.join(sorted(known))}"
        more = f"; also unknown: {', '.join(unknown[1:])}" if unknown[1:] else ""
        raise SettingsError(source, prefix + unknown[0], f"unknown setting ({hint}){more}"[:400])
    hints = typing.get_type_hints(cls)
    values = {name: _check(hints[name], value, source, prefix + name,
                           _default(cls, name) if base is None else getattr(base, name))
              for name, value in data.items()}
    try:
        return dataclasses.replace(base, **values) if base is not None else cls(**values)
    except SettingsError as e:  # the config's own checks naming one of its fields (`check_cells`): in this file
        raise e.within(source, prefix.rstrip(".") or None) from None  # and section
    except ValueError as e:  # the config's own checks (__post_init__)
        raise SettingsError(source, prefix.rstrip(".") or None, str(e)) from None


def _default(cls, name: str):
    """The default value of field `name` of dataclass `cls` (None when it has none)."""
    f = next(f for f in dataclasses.fields(cls) if f.name == name)
    if f.default is not dataclasses.MISSING:
        return f.default
    return f.default_factory() if f.default_factory is not dataclasses.MISSING else None


def _check(hint, value, source, name: str, default=None):
    """`value` as a field of type `hint` (dotted name `name`) holds it; SettingsError if it cannot. A partial table
    for a dataclass field changes only the fields it names of that field's `default` (the coarse rigid fit of
    `[detect.coarse]` stays rigid when a file sets only its points)."""
    def fail(reason: str):
        raise SettingsError(source, name, f"{reason}, not {value!r}"[:200])

    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        (hint,) = [a for a in args if a is not type(None)]
        return _check(hint, value, source, name)
    if dataclasses.is_dataclass(hint):  # checked as a whole once merged into the default
        return from_dict(hint, value, source, name + ".", default if isinstance(default, hint) else None)
    if hint is Any:
        return value
    if hint is bool:
        return value if isinstance(value, bool) else fail("must be true or false")
    if hint is str:
        if not isinstance(value, str):
            fail("must be a text")
        return _beside(value, source) if name.rsplit(".", 1)[-1] in FILE_FIELDS else value
    if hint in (int, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)) or hint is int and not isinstance(value, int):
            fail("must be an integer" if hint is int else "must be a number")
        return _in_range(hint, value, source, name)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            fail("must be a list")
        each = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(each) != len(value):
            fail(f"must be a list of {len(each)}")
        return tuple(_check(h, v, source, name) for h, v in zip(each, value))
    if origin is dict:
        if not isinstance(value, dict):
            fail("must be a table")
        return {str(k): _check(args[1], v, source, f"{name}.{k}") for k, v in value.items()}
    raise TypeError(f"settings of type {hint} are not checked: add them to config._check")


def _beside(path: str, source) -> str:
    """A `FILE_FIELDS` value: a relative path resolved against the folder of the settings file `source` when the file
    is there (an absolute path, "", "shipped" or a path found nowhere else stay as they are)."""
    if not path or path == "shipped" or Path(path).is_absolute() or source is None or not Path(source).is_file():
        return path
    beside = Path(source).resolve().parent / path
    return str(beside) if beside.is_file() else path


def check_ranges(config, prefix: str = "") -> None:
    """The range checks `from_dict` makes of a settings file (`RANGES`, by field name; finite numbers), made of a
    config built in Python (`PreprocessConfig(crop_radius_mm=-5)`): SettingsError naming the dotted field."""
    hints = _hints(type(config))
    for f in dataclasses.fields(config):
        value, name = getattr(config, f.name), prefix + f.name
        if dataclasses.is_dataclass(value):
            check_ranges(value, name + ".")
        elif isinstance(value, (int, float)) and not isinstance(value, bool) and (hint := _number(hints[f.name])):
            _in_range(hint, value, None, name)
        elif isinstance(value, tuple) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value):
            for v in value:
                _in_range(float, v, None, name)


def check_cells(field: str, cell_mm: float, span_mm: float, span: str) -> None:
    """Refuse the setting `field`, a cell size of `cell_mm` that lays `span` (words, `span_mm` long) on a square
    grid wider than the largest scan facerec3d reads (MAX_GRID_SIDE² = io.common.MAX_POINTS): SettingsError naming
    `field`, when the settings are checked, before any work. The bound is far above any real use (the default
    resampling grid is 191 × 191 cells; at 0.1 mm, finer than any face scanner samples, 1901 × 1901) and keeps a
    scan's grid and the arrays made from it under a few hundred MB; a finer grid made every scan fail (a MemoryError,
    NumPy's "array is too big"), and a face on it could not be read back from the cache. A cell <= 0 or NaN is left
    to its range check (`check_ranges`)."""
    side = MAX_GRID_SIDE
    across = span_mm / cell_mm + 1 if cell_mm > 0 else 0.0  # cells along a side
    if across > side:
        raise SettingsError(None, field, f"{cell_mm:g} mm cells lay {span} = {span_mm:g} mm, on {across:.6g} cells "
                                         f"a side, more than the {side} × {side} of the largest scan facerec3d reads: "
                                         "use larger cells")


def _number(hint) -> type | None:
    """int or float for a field of that type, or of that type or None (`max_normal_angle: float | None`); else None."""
    if hint in (int, float):
        return hint
    options = set(typing.get_args(hint)) - {type(None)}
    return options.pop() if len(options) == 1 and options <= {int, float} else None


@functools.lru_cache(maxsize=None)
def _hints(cls) -> dict:
    """A config class's type hints (resolved once: they are the slow part of a check)."""
    return typing.get_type_hints(cls)


def _in_range(hint: type, value: int | float, source, name: str) -> int | float:
    """`value` as a `hint` (int or float) in the field's range (`RANGES`)."""
    low, high, low_ok = RANGES.get(name.rsplit(".", 1)[-1], NON_NEGATIVE)
    if isinstance(value, float) and not math.isfinite(value) or hint is float and abs(value) > 1e300:
        raise SettingsError(source, name, f"must be a finite number, not {value!r}"[:200])
    if value < low or value == low and not low_ok or value > high:
        want = {POSITIVE: "> 0", NON_NEGATIVE: ">= 0", FRACTION: "in [0, 1]"}[(low, high, low_ok)]
        raise SettingsError(source, name, f"must be {want}, not {value!r}"[:200])
    if hint is int and value > MAX_INT:
        raise SettingsError(source, name, f"must be at most {MAX_INT}, not {value!r}"[:200])
    return hint(value)
