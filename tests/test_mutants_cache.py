"""The preprocessing cache key (preprocess.batch.cache_key): what must make a new entry, and what must not.

Found by mutation testing: dropping the settings, the file's size or modification time, or the intrinsics from the
key left every cache test green, yet each would hand a rerun a face made from other settings, another version of
the file, or another camera's intrinsics."""

import os

from facerec3d.preprocess.batch import cache_key
from facerec3d.preprocess.pipeline import PreprocessConfig


def test_the_key_follows_the_settings_and_the_file(tmp_path):
    scan = tmp_path / "face.abs"
    scan.write_bytes(b"x" * 100)
    os.utime(scan, ns=(1_000_000_000, 1_000_000_000))
    key = cache_key(scan, PreprocessConfig())
    assert cache_key(scan, PreprocessConfig()) == key  # the same file and settings: the same entry
    assert cache_key(tmp_path / "." / "face.abs", PreprocessConfig()) == key  # the same file by another path
    assert cache_key(scan, PreprocessConfig(crop_radius_mm=70.0)) != key  # other settings
    os.utime(scan, ns=(1_000_000_000, 2_000_000_000))
    assert cache_key(scan, PreprocessConfig()) != key  # the file was touched (rewritten in place)
    os.utime(scan, ns=(1_000_000_000, 1_000_000_000))
    assert cache_key(scan, PreprocessConfig()) == key
    scan.write_bytes(b"y" * 101)  # another size at the same modification time (a copy that kept it)
    os.utime(scan, ns=(1_000_000_000, 1_000_000_000))
    assert cache_key(scan, PreprocessConfig()) != key


def test_the_key_of_a_depth_frame_follows_its_intrinsics_by_content(tmp_path):
    frame = tmp_path / "person" / "front_1.png"
    frame.parent.mkdir()
    frame.write_bytes(b"\x89PNG" + b"\0" * 60)
    bare = cache_key(frame, PreprocessConfig())
    found = tmp_path / "intrinsics.json"  # in a parent folder: found and read with the frame
    found.write_text('{"fx": 570.0, "fy": 570.0, "cx": 320.0, "cy": 240.0}')
    beside = cache_key(frame, PreprocessConfig())
    assert beside != bare
    found.write_text('{"fx": 580.0, "fy": 580.0, "cx": 320.0, "cy": 240.0}')  # another camera
    assert cache_key(frame, PreprocessConfig()) not in (bare, beside)
    given = tmp_path / "other.json"  # given explicitly: its content counts, not the one found
    given.write_text('{"fx": 570.0, "fy": 570.0, "cx": 320.0, "cy": 240.0}')
    assert cache_key(frame, PreprocessConfig(), given) == beside
    given.write_text('{"fx": 600.0, "fy": 600.0, "cx": 320.0, "cy": 240.0}')
    assert cache_key(frame, PreprocessConfig(), given) != beside
