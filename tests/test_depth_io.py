"""Depth frames of depth cameras: 16-bit PNG / TIFF / .npy with pinhole intrinsics, read like any other scan."""

import csv
import json

import numpy as np
import pytest
from PIL import Image

from facerec3d import ScanFormatError
from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.protocols import split
from facerec3d.io import Intrinsics, load_scan, save_scan, write_depth_image
from facerec3d.io.depth import frame_to_scan, read_depth_image, scan_to_frame

KINECT = Intrinsics(fx=365.5, fy=366.0, cx=59.0, cy=74.0, depth_unit_mm=0.25)


def frame(rows=149, cols=119, seed=0) -> np.ndarray:
    """A Z-depth image (mm) of a sphere 1.2 m away, with missing pixels and quantised to the unit."""
    v, u = np.mgrid[0:rows, 0:cols].astype(float)
    r2 = (u - cols / 2) ** 2 + (v - rows / 2) ** 2
    depth = 1200.0 - np.sqrt(np.maximum(60.0**2 - r2 * 0.5, 0.0))
    depth[np.random.default_rng(seed).random(depth.shape) < 0.05] = np.nan
    return np.round(depth / KINECT.depth_unit_mm) * KINECT.depth_unit_mm


def test_depth_png_reads_to_the_same_points_as_the_equivalent_abs(tmp_path):
    depth = frame()
    write_depth_image(tmp_path / "f.png", depth, KINECT)
    KINECT.save(tmp_path / "intrinsics.json")
    png = load_scan(tmp_path / "f.png")
    # the same frame as an FRGC range image, from the pinhole model applied independently here
    v, u = np.indices(depth.shape, dtype=float)
    xyz = np.stack([(u - KINECT.cx) * depth / KINECT.fx, -(v - KINECT.cy) * depth / KINECT.fy, -depth], -1)
    from facerec3d import FaceScan

    save_scan(FaceScan.from_range_image(xyz, np.isfinite(depth)), tmp_path / "f.abs")
    ref = load_scan(tmp_path / "f.abs")
    assert png.grid_shape == ref.grid_shape == depth.shape
    np.testing.assert_array_equal(png.grid, ref.grid)
    np.testing.assert_allclose(png.points, ref.points, atol=1e-3)  # .abs keeps 6 decimals
    # a point sits where the camera saw it: back-projection gives the depth image again
    np.testing.assert_allclose(scan_to_frame(png, KINECT), depth, equal_nan=True)
    assert png.meta.extra["pixel_focal"] == pytest.approx(np.sqrt(365.5 * 366.0))


@pytest.mark.parametrize("suffix", ["png", "tif", "npy"])
def test_every_depth_container_reads_alike_and_intrinsics_are_found_in_a_parent_folder(tmp_path, suffix):
    depth = frame(40, 30)
    KINECT.save(tmp_path / "intrinsics.json")
    (tmp_path / "s001").mkdir()
    target = tmp_path / "s001" / f"front_1.{suffix}"
    if suffix == "npy":
        np.save(target, np.nan_to_num(depth / KINECT.depth_unit_mm).astype(np.uint16))
    else:
        write_depth_image(target, depth, KINECT)
    scan = load_scan(target)
    expected = frame_to_scan(depth, KINECT)
    np.testing.assert_allclose(scan.points, expected.points, atol=1e-9)


def test_intrinsics_given_explicitly_override_and_depth_scale_in_metres(tmp_path):
    depth = frame(40, 30)
    write_depth_image(tmp_path / "f.png", depth, KINECT)
    cam = tmp_path / "cam.json"
    cam.write_text(json.dumps({"fx": 365.5, "fy": 366.0, "cx": 59.0, "cy": 74.0, "depth_scale_m": 0.00025}))
    scan = load_scan(tmp_path / "f.png", intrinsics=cam)
    np.testing.assert_allclose(-scan.points[:, 2], depth[np.isfinite(depth)], atol=1e-9)


def test_png_without_intrinsics_says_what_it_needs(tmp_path):
    write_depth_image(tmp_path / "f.png", frame(20, 20), KINECT)
    with pytest.raises(ScanFormatError, match="intrinsics"):
        load_scan(tmp_path / "f.png")


BAD_INTRINSICS = [
    ("{not json", "not valid JSON"),
    ("[1, 2]", "JSON object"),
    ('{"fx": 365, "fy": 365, "cx": 59}', "'cy'"),
    ('{"fx": "365", "fy": 365, "cx": 59, "cy": 74}', "'fx' must be a finite number"),
    ('{"fx": -1, "fy": 365, "cx": 59, "cy": 74}', "positive"),
    ('{"fx": 365, "fy": -365, "cx": 59, "cy": 74}', "positive"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "depth_unit_mm": 0}', "depth unit"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "width": 7, "height": 9}', "intrinsics are for 9x7"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "encoding": "depth32"}', "'encoding' must be one of plain, depth16"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "encoding": "depth16", "min_confidence": 1.5}', "'min_confidence'"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "depth_units_mm": 0.1}',
     r"unknown field 'depth_units_mm' \(did you mean 'depth_unit_mm'\?\)"),  # read as 1 mm units, 10× off, before
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "depth_scale_m": 0.001, "depth_unit_mm": 10}',
     "depth_unit_mm and depth_scale_m disagree"),
    ('{"fx": 365, "fy": 365, "cx": 59, "cy": 74, "note": "' + "x" * 70_000 + '"}', "intrinsics file over 64 KiB"),
]


@pytest.mark.parametrize("text, reason", BAD_INTRINSICS)
def test_bad_intrinsics_give_one_line_naming_the_file(tmp_path, text, reason):
    write_depth_image(tmp_path / "f.png", frame(20, 20), KINECT)
    (tmp_path / "intrinsics.json").write_text(text)
    with pytest.raises(ScanFormatError, match=reason) as e:
        load_scan(tmp_path / "f.png")
    assert "\n" not in str(e.value)
    assert "f.png" in str(e.value) or "intrinsics.json" in str(e.value)


@pytest.mark.parametrize("make, reason", [
    (lambda p: p.write_bytes(b"\x89PNG\r\n\x1a\n" + b"\0" * 40), "not a readable depth image"),
    (lambda p: p.write_bytes(b""), "not a readable depth image"),
    (lambda p: Image.new("RGB", (8, 8)).save(p), "not a depth image"),
    (lambda p: Image.new("I;16", (8, 8)).save(p), "no valid points"),  # all zero: nothing measured
])
def test_bad_depth_images_give_one_line_naming_the_file(tmp_path, make, reason):
    KINECT.save(tmp_path / "intrinsics.json")
    target = tmp_path / "f.png"
    make(target)
    with pytest.raises(ScanFormatError, match=reason) as e:
        load_scan(target)
    assert str(target) in str(e.value) and "\n" not in str(e.value)


def test_an_npz_archive_named_npy_beside_intrinsics_is_one_line_not_a_crash(tmp_path):
    """Found by the service's upload fuzzing: an .npz archive (a zip) named .npy, with intrinsics beside it, made
    the depth-frame check call .ndim on NumPy's archive object (AttributeError, a 500 from the service)."""
    KINECT.save(tmp_path / "intrinsics.json")
    target = tmp_path / "f.npy"
    np.savez(tmp_path / "f.npz", depth=frame())
    (tmp_path / "f.npz").rename(target)
    with pytest.raises(ScanFormatError) as e:
        load_scan(target)
    assert str(target) in str(e.value) and "\n" not in str(e.value)
    with pytest.raises(ScanFormatError, match="archive") as e:
        read_depth_image(target, KINECT)
    assert str(target) in str(e.value)


def test_huge_depth_header_is_refused_before_decoding(tmp_path):
    """A PNG header claiming 40000 x 40000 pixels is refused from its header alone (memory stays bounded)."""
    import struct
    import zlib

    KINECT.save(tmp_path / "intrinsics.json")
    ihdr = struct.pack(">IIBBBBB", 40000, 40000, 16, 0, 0, 0, 0)
    chunk = lambda kind, data: struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    (tmp_path / "f.png").write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b""))
    with pytest.raises(ScanFormatError, match="absurd size|not a readable"):
        load_scan(tmp_path / "f.png")


def test_manifest_of_depth_frames_with_a_pose_column_gives_pose_subsets(tmp_path):
    KINECT.save(tmp_path / "intrinsics.json")
    rows = ["path,subject,pose,role"]
    for s in ("a", "b"):
        for k, pose in enumerate(("front", "front", "left", "up")):
            write_depth_image(tmp_path / f"{s}{k}.png", frame(20, 20, seed=k), KINECT)
            rows.append(f"{s}{k}.png,{s},{pose},{'gallery' if k == 0 else 'probe'}")
    (tmp_path / "manifest.csv").write_text("\n".join(rows) + "\n")
    ds = open_dataset(tmp_path / "manifest.csv")
    assert [r.pose for r in ds.records[:4]] == ["front", "front", "left", "up"]
    sp = split(ds, "roles")
    assert {k: len(v) for k, v in sp.subsets.items()} == {"pose:front": 2, "pose:left": 2, "pose:up": 2}
    assert load_scan(ds.records[1].path).grid_shape == (20, 20)


def test_android_depth16_frames_keep_the_range_bits_and_leave_out_what_the_sensor_is_unsure_of(tmp_path):
    """Android's DEPTH16 (phones' time-of-flight cameras): 13 bits of range in mm under 3 bits of confidence (0:
    100 %, 1: 0 %, k: (k - 1)/7). Read as plain depth, each pixel would lie up to 57 m away; decoded, the frame is
    the plain one less the pixels below `min_confidence`, and a face in it is found where the generator put it."""
    from facerec3d.datasets.synthetic import SENSOR_PROFILES, DatasetConfig, write_dataset
    from facerec3d.preprocess import Preprocessor, landmarks_in_input_frame

    plain_root = write_dataset(tmp_path / "plain", DatasetConfig(subjects=1, scans=1,
                                                                scanner=SENSOR_PROFILES["kinect-v2"]), fmt="png")
    plain_root = plain_root.parent  # write_dataset gives its manifest
    row = next(csv.DictReader(open(plain_root / "manifest.csv")))
    plain = np.asarray(Image.open(plain_root / row["path"])).astype(np.uint16)
    assert plain.max() < 8192 and (plain > 0).sum() > 5000  # millimetres, as DEPTH16 holds them; a head and torso
    rng = np.random.default_rng(3)
    code = rng.choice(np.array([0, 1, 2, 3, 4, 5, 6, 7], np.uint16), size=plain.shape,
                      p=[0.4, 0.1, 0.1, 0.1, 0.1, 0.1, 0.05, 0.05])
    frame16 = tmp_path / "phone" / "f.png"
    frame16.parent.mkdir()
    Image.fromarray(np.where(plain > 0, (code << 13) | plain, 0).astype(np.uint16)).save(frame16)
    intrinsics = json.loads((plain_root / "intrinsics.json").read_text())
    reference = load_scan(plain_root / row["path"])
    for min_confidence, kept in ((None, code != 1), (0.5, (code == 0) | (code >= 5)), (0.0, np.ones_like(code, bool))):
        given = {} if min_confidence is None else {"min_confidence": min_confidence}
        (frame16.parent / "intrinsics.json").write_text(json.dumps(dict(intrinsics, encoding="depth16", **given)))
        scan = load_scan(frame16)
        assert scan.grid_shape == reference.grid_shape
        seen = reference.index_image()
        np.testing.assert_array_equal(scan.index_image() >= 0, (seen >= 0) & kept)
        np.testing.assert_array_equal(scan.points, reference.points[seen[(seen >= 0) & kept]])
    (frame16.parent / "intrinsics.json").write_text(json.dumps(dict(intrinsics, encoding="depth16")))
    face = Preprocessor()(load_scan(frame16))  # a tenth of the face's pixels left out (0 % confidence)
    truth = np.array([float(row[f"nose_tip_{a}"]) for a in "xyz"])
    assert np.linalg.norm(landmarks_in_input_frame(face)["nose_tip"] - truth) <= 10.0
    (frame16.parent / "intrinsics.json").write_text(json.dumps(intrinsics))  # the same file read as plain depth
    assert np.median(-load_scan(frame16).points[:, 2]) > 8192.0


def test_intrinsics_made_in_code_are_checked_as_a_file_is():
    """`Intrinsics(fx=-1, ...)` was accepted and a frame read with it failed with "math domain error"."""
    from facerec3d.io.depth import Intrinsics

    for bad in ({"fx": -1.0}, {"fy": 0.0}, {"cx": float("nan")}, {"depth_unit_mm": 0.0}):
        with pytest.raises(ValueError, match="intrinsics: "):
            Intrinsics(**{"fx": 365.0, "fy": 365.0, "cx": 59.0, "cy": 74.0, **bad})
    assert Intrinsics(fx=365.0, fy=365.0, cx=59.0, cy=74.0).fx == 365.0


def test_depth16_ranges_use_all_13_bits_whatever_the_confidence(tmp_path):
    """DEPTH16's range is the 13 low bits (0-8191 mm): ranges beyond 4095 mm keep their 12th bit, under any
    confidence code that is kept (0: 100 %, 7: 6/7)."""
    ranges = np.array([[500, 4095, 4096], [5000, 8191, 1234]], np.uint16)
    codes = np.array([[0, 7, 0], [7, 0, 7]], np.uint16)
    Image.fromarray((codes << 13) | ranges).save(tmp_path / "f.png")
    cam = Intrinsics(fx=500.0, fy=500.0, cx=1.0, cy=0.5, encoding="depth16")
    scan = read_depth_image(tmp_path / "f.png", cam)
    assert scan.n_points == 6
    np.testing.assert_array_equal(scan_to_frame(scan, cam), ranges)


def test_a_cameras_own_invalid_value_marks_no_measurement(tmp_path):
    """A camera marking missing pixels with 65535 (not 0): those pixels are no points; the others read in the
    depth unit as usual."""
    units = np.full((4, 5), 4000, np.uint16)
    units[1, 2] = units[3, 0] = 65535
    Image.fromarray(units).save(tmp_path / "f.png")
    cam = Intrinsics(fx=500.0, fy=500.0, cx=2.0, cy=1.5, depth_unit_mm=0.25, invalid=65535)
    cam.save(tmp_path / "intrinsics.json")
    scan = load_scan(tmp_path / "f.png")
    expected = np.where(units == 65535, np.nan, 1000.0)
    assert scan.n_points == 18
    np.testing.assert_array_equal(scan_to_frame(scan, cam), expected)
