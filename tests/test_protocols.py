"""Gallery / probe splits of the evaluation protocols (chapter §8.4); only file names matter here."""

import pytest

from facerec3d.datasets.catalog import open_dataset
from facerec3d.evaluation.protocols import split


def touch(root, names):
    for name in names:
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("")


def test_bosphorus_neutral_gallery_and_separate_pose_and_occlusion(tmp_path):
    touch(tmp_path, ["bs000/bs000_N_N_0.bnt", "bs000/bs000_N_N_1.bnt", "bs000/bs000_E_HAPPY_0.bnt",
                     "bs000/bs000_YR_R30_0.bnt", "bs000/bs000_O_EYE_0.bnt",
                     "bs001/bs001_N_N_0.bnt", "bs001/bs001_LFAU_12_0.bnt", "bs001/bs001_CAU_A22_0.bnt"])
    ds = open_dataset(tmp_path)
    sp = split(ds)
    assert ds.layout == "bosphorus" and sp.protocol == "bosphorus"
    assert sorted(ds.records[i].scan_id for i in sp.gallery) == ["bs000_N_N_0", "bs001_N_N_0"]
    names = {k: sorted(ds.records[sp.probes[j]].scan_id for j in v) for k, v in sp.subsets.items()}
    assert names == {"neutral": ["bs000_N_N_1"],
                     "non-neutral": ["bs000_E_HAPPY_0", "bs001_CAU_A22_0", "bs001_LFAU_12_0"],
                     "pose": ["bs000_YR_R30_0"], "occlusion": ["bs000_O_EYE_0"]}


def test_frgc_gallery_is_the_first_neutral_scan(tmp_path):
    touch(tmp_path, ["a/1d1.abs", "a/1d2.abs", "a/1d3.abs", "a/2d4.abs", "a/2d5.abs"])
    (tmp_path / "m.csv").write_text("path,subject,expression\na/1d1.abs,1,smile\na/1d2.abs,1,neutral\n"
                                    "a/1d3.abs,1,neutral\na/2d4.abs,2,neutral\na/2d5.abs,2,frown\n")
    ds = open_dataset(tmp_path / "m.csv")
    sp = split(ds)
    assert sp.protocol == "frgc"
    assert [ds.records[i].scan_id for i in sp.gallery] == ["1d2", "2d4"]
    assert sorted(ds.records[i].scan_id for i in sp.probes) == ["1d1", "1d3", "2d5"]
    assert [ds.records[sp.probes[j]].scan_id for j in sp.subsets["neutral"]] == ["1d3"]


def test_roles_and_all_vs_all(tmp_path):
    touch(tmp_path, ["x.abs", "y.abs", "z.abs"])
    (tmp_path / "m.csv").write_text("path,subject,role\nx.abs,1,gallery\ny.abs,1,probe\nz.abs,2,probe\n")
    ds = open_dataset(tmp_path / "m.csv")
    sp = split(ds)
    assert sp.protocol == "roles" and sp.gallery == [0] and sp.probes == [1, 2]
    every = split(ds, "all-vs-all")
    assert every.gallery == every.probes == [0, 1, 2] and every.exclude_self
    with pytest.raises(ValueError, match="unknown protocol"):
        split(ds, "lfw")
