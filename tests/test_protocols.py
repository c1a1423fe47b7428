"""Gallery / probe splits of the evaluation protocols (chapter §8.4); only file names matter here."""

import pytest

from facerec3d.datasets.catalog import open_dataset
from facerec3d.datasets.protocols import split


def touch(root, names):
    for name in names:
        p = root / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text("")


def test_bosphorus_neutral_gallery_and_every_subset(tmp_path):
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
                     "pose": ["bs000_YR_R30_0"], "occlusion": ["bs000_O_EYE_0"],
                     "E": ["bs000_E_HAPPY_0"], "E_HAPPY": ["bs000_E_HAPPY_0"], "LFAU": ["bs001_LFAU_12_0"],
                     "CAU": ["bs001_CAU_A22_0"], "YR": ["bs000_YR_R30_0"]}


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
    from facerec3d.errors import InputError

    with pytest.raises(InputError, match=r"^split takes a Dataset .*, not PosixPath"):  # was an AttributeError
        split(tmp_path / "m.csv")


def test_every_bosphorus_type_and_emotion_is_a_subset(tmp_path):
    types = ["E_ANGER", "E_HAPPY", "E_SURPRISE", "LFAU_12", "UFAU_4", "CAU_A22", "YR_R10", "YR_L45", "PR_U", "PR_D",
             "CR_RD", "O_MOUTH", "O_GLASSES"]
    touch(tmp_path, ["bs000/bs000_N_N_0.bnt", *(f"bs000/bs000_{t}_0.bnt" for t in types)])
    ds = open_dataset(tmp_path)
    sp = split(ds)
    names = {k: sorted(ds.records[sp.probes[j]].label for j in v) for k, v in sp.subsets.items()}
    assert names["E"] == ["E_ANGER", "E_HAPPY", "E_SURPRISE"]
    assert {k: names[k] for k in ("E_ANGER", "E_HAPPY", "E_SURPRISE")} == {
        "E_ANGER": ["E_ANGER"], "E_HAPPY": ["E_HAPPY"], "E_SURPRISE": ["E_SURPRISE"]}
    assert (names["LFAU"], names["UFAU"], names["CAU"]) == (["LFAU_12"], ["UFAU_4"], ["CAU_A22"])
    assert (names["YR"], names["PR"], names["CR"]) == (["YR_L45", "YR_R10"], ["PR_D", "PR_U"], ["CR_RD"])
    assert names["occlusion"] == ["O_GLASSES", "O_MOUTH"] and names["pose"] == sorted(
        ["YR_R10", "YR_L45", "PR_U", "PR_D", "CR_RD"])
    assert len(names["non-neutral"]) == 6 and "neutral" not in names  # the one N scan is the gallery


def test_pose_column_keeps_turned_probes_out_of_the_expression_subsets(tmp_path):
    """A ±25° yaw probe is neutral in expression but not frontal: it is in its pose subset only, and a frontal
    neutral scan is preferred for the gallery even when a turned one comes first."""
    (tmp_path / "m.csv").write_text("path,subject,expression,pose\n1a.abs,1,neutral,yaw\n1b.abs,1,neutral,\n"
                                    "1c.abs,1,neutral,frontal\n1d.abs,1,smile,yaw\n1e.abs,1,smile,\n")
    ds = open_dataset(tmp_path / "m.csv")
    sp = split(ds)
    assert [ds.records[i].scan_id for i in sp.gallery] == ["1b"]
    names = {k: sorted(ds.records[sp.probes[j]].scan_id for j in v) for k, v in sp.subsets.items()}
    assert names == {"neutral": ["1c"], "non-neutral": ["1e"], "pose:yaw": ["1a", "1d"], "pose:frontal": ["1c"]}


def test_frgc_first_neutral_is_the_earliest_semester(tmp_path):
    touch(tmp_path, ["nd1/Spring2004range/1d1.abs", "nd1/Fall2003range/1d2.abs", "nd1/Spring2003range/1d3.abs"])
    ds = open_dataset(tmp_path)
    assert [ds.records[i].scan_id for i in split(ds).gallery] == ["1d3"]  # not the alphabetically first folder


def test_frgc_exp3_masks_by_hand(tmp_path):
    """ROC I: same semester; ROC II: same academic year (Fall 2003 and Spring 2004: every pair); ROC III: target
    (gallery column) in Fall 2003, query (probe row) in Spring 2004. Spring 2003 is left out."""
    names = ["nd1/Spring2003range/1d0.abs", "nd1/Fall2003range/1d1.abs", "nd1/Fall2003range/2d2.abs",
             "nd1/Spring2004range/1d3.abs", "nd1/Spring2004range/2d4.abs", "nd1/Spring2004range/2d5.abs"]
    touch(tmp_path, names)
    ds = open_dataset(tmp_path)
    sp = split(ds, "frgc-exp3")
    ids = [ds.records[i].scan_id for i in sp.probes]
    assert sp.gallery == sp.probes and sp.exclude_self and sorted(ids) == ["1d1", "1d3", "2d2", "2d4", "2d5"]
    assert [ds.records[i].scan_id for i in sp.excluded] == ["1d0"] and "Spring 2003" in sp.note
    fall = {"1d1", "2d2"}
    for name, rule in (("ROC I", lambda q, t: (q in fall) == (t in fall)), ("ROC II", lambda q, t: True),
                       ("ROC III", lambda q, t: q not in fall and t in fall)):
        expected = [[rule(q, t) for t in ids] for q in ids]
        assert sp.masks[name].tolist() == expected, name
    # a manifest's session column gives the semester too; a scan without one is refused
    (tmp_path / "m.csv").write_text("path,subject,session\na.abs,1,Fall 2003\nb.abs,1,spring2004\n")
    assert split(open_dataset(tmp_path / "m.csv"), "frgc-exp3").masks["ROC III"].tolist() == [[False, False],
                                                                                                [True, False]]
    (tmp_path / "n.csv").write_text("path,subject\na.abs,1\n")
    with pytest.raises(ValueError, match="no FRGC semester"):
        split(open_dataset(tmp_path / "n.csv"), "frgc-exp3")


def test_a_persons_folder_of_a_recording_is_read_through_the_manifest_above_it(tmp_path):
    """`enroll frames/04201` (a depth-camera recording's person, its manifest.csv at the top) was refused as "no
    FRGC or Bosphorus scans found": it is that person's rows of the manifest; a folder no manifest lists still is."""
    from facerec3d.datasets.catalog import DatasetError
    from facerec3d.datasets.synthetic import DatasetConfig, ScannerConfig, write_dataset

    write_dataset(tmp_path / "frames", DatasetConfig(subjects=2, scans=2, scanner=ScannerConfig(rows=48, cols=64)),
                  "png")
    whole = open_dataset(tmp_path / "frames")
    person = whole.records[-1].subject
    one = open_dataset(tmp_path / "frames" / person)
    assert [r.path for r in one.records] == [r.path for r in whole.records if r.subject == person]
    assert len(one) == 2 and one.layout == "manifest"
    (tmp_path / "frames" / "notes").mkdir()
    with pytest.raises(DatasetError, match="no FRGC .* scans found, and no manifest.csv"):
        open_dataset(tmp_path / "frames" / "notes")


def test_a_manifest_listing_a_scan_twice_is_refused_and_subjects_keep_their_inner_white_space(tmp_path):
    """A scan listed twice was its own probe (a self-match inflating rank-1, silently): refused on reading, naming
    the line. A subject 'person a' is read as it is (score files percent-encode it: tests/test_first_hour.py)."""
    from facerec3d.datasets.catalog import DatasetError, read_manifest

    touch(tmp_path, ["a/1.abs", "a/2.abs", "b/1.abs"])
    (tmp_path / "ok.csv").write_text("path,subject\na/1.abs,a\na/2.abs,a\nb/1.abs, b \n")
    assert [r.subject for r in read_manifest(tmp_path / "ok.csv").records] == ["a", "a", "b"]
    (tmp_path / "twice.csv").write_text("path,subject\na/1.abs,a\na/2.abs,a\nb/../a/1.abs,a\n")
    with pytest.raises(DatasetError, match=r"twice\.csv, line 4: b/\.\./a/1\.abs is listed on line 2 already"):
        read_manifest(tmp_path / "twice.csv")
    (tmp_path / "space.csv").write_text("path,subject\na/1.abs, person a \n")
    assert read_manifest(tmp_path / "space.csv").records[0].subject == "person a"
    (tmp_path / "blank.csv").write_text("path,subject\na/1.abs,  \n")
    with pytest.raises(DatasetError, match=r"blank\.csv, line 2: empty path or subject"):
        read_manifest(tmp_path / "blank.csv")


def test_a_manifest_and_a_csv_score_file_with_a_byte_order_mark_are_read(tmp_path):
    """Excel's "CSV UTF-8" starts the file with a byte-order mark: the manifest was read as a point cloud by
    `enroll` (its header was '\\ufeffpath,subject'), refused as headerless by `evaluate`, and a CSV score file had
    "no column for claimed_id"."""
    from facerec3d.datasets.catalog import read_manifest
    from facerec3d.evaluation.scorefile import read_score_matrix
    from facerec3d.gallery.service import scan_paths, scan_records

    touch(tmp_path, ["a/1.abs", "b/1.abs"])
    (tmp_path / "b1.csv").write_bytes(b"\xef\xbb\xbfpath,subject\na/1.abs,04200\nb/1.abs,04201\n")
    assert [r.subject for r in read_manifest(tmp_path / "b1.csv").records] == ["04200", "04201"]
    assert [r.subject for r in scan_records([tmp_path / "b1.csv"])] == ["04200", "04201"]
    assert scan_paths([tmp_path / "b1.csv"]) == [tmp_path / "a/1.abs", tmp_path / "b/1.abs"]
    (tmp_path / "s.csv").write_bytes(b"\xef\xbb\xbfbio_ref_subject_id,probe_subject_id,probe_template_id,score\n"
                                     b"a,a,p1,1\nb,a,p1,0\n")
    m = read_score_matrix(tmp_path / "s.csv", "csv")
    assert list(m.gallery_ids) == ["a", "b"] and m.S.tolist() == [[1.0, 0.0]]


def test_a_manifest_label_gives_the_bosphorus_type_of_a_file_of_any_name(tmp_path):
    """A manifest `path,subject,label` whose labels are Bosphorus scan types (N_N, E_SURPRISE) was refused by the
    bosphorus protocol as having no scan types (with no expression column every record had no category), though the
    docs say such a label is enough: the label types the scan, its gallery is the N scan, its probes the subsets."""
    touch(tmp_path, ["p0_a.bnt", "p0_b.bnt", "p1_a.bnt", "p1_c.bnt", "p1_d.bnt"])
    (tmp_path / "m.csv").write_text("path,subject,label\np0_a.bnt,p0,N_N\np0_b.bnt,p0,E_HAPPY\n"
                                    "p1_c.bnt,p1,E_SURPRISE\np1_a.bnt,p1,N_N\np1_d.bnt,p1,YR_R10\n")
    ds = open_dataset(tmp_path / "m.csv")
    sp = split(ds, "bosphorus")
    assert sorted(ds.records[i].scan_id for i in sp.gallery) == ["p0_a", "p1_a"]
    names = {k: sorted(ds.records[sp.probes[j]].scan_id for j in v) for k, v in sp.subsets.items()}
    assert names == {"non-neutral": ["p0_b", "p1_c"], "pose": ["p1_d"], "E": ["p0_b", "p1_c"], "YR": ["p1_d"],
                     "E_HAPPY": ["p0_b"], "E_SURPRISE": ["p1_c"]}
    assert [r.expression for r in ds.records] == ["neutral", "non-neutral", "non-neutral", "neutral", None]


def test_bosphorus_subject_without_a_neutral_scan_is_not_enrolled(tmp_path):
    # the gallery is each subject's first NEUTRAL (N) scan: bs001 has none, so none of its scans is in the gallery
    # (its probes are searches of a person not enrolled), rather than its first expression or pose scan
    touch(tmp_path, ["bs000/bs000_N_N_0.bnt", "bs000/bs000_E_HAPPY_0.bnt",
                     "bs001/bs001_E_ANGER_0.bnt", "bs001/bs001_YR_R30_0.bnt"])
    ds = open_dataset(tmp_path)
    sp = split(ds, "bosphorus")
    assert [ds.records[i].scan_id for i in sp.gallery] == ["bs000_N_N_0"]
    assert sorted(ds.records[i].scan_id for i in sp.probes) == ["bs000_E_HAPPY_0", "bs001_E_ANGER_0",
                                                               "bs001_YR_R30_0"]
