"""The versioned output folders (campaign.versioned) in every state a killed writer can leave them:
a half-written version, a complete one never made current, a temporary link, an older plain
folder moved half-way. Plain files, no pipeline: what plan, calibrate and diagnose rely on."""

import errno
import os

import pytest

from campaign.errors import StorageError
from campaign.versioned import VersionedFolder


def publish(vf, vid, text):
    with vf.new_version(vid) as v:
        (v.path / "a.txt").write_text(text)
        (v.path / "b.txt").write_text(text)
    return vid


def read(vf):
    cur = vf.current()
    return None if cur is None else ((cur / "a.txt").read_text(), (cur / "b.txt").read_text())


def test_a_version_becomes_current_whole_and_two_are_kept(tmp_path):
    vf = VersionedFolder(tmp_path, "out", "outs", keep=2)
    assert vf.current() is None and vf.current_id() is None
    for k in range(1, 4):
        publish(vf, f"2026010{k}T000000Z-00000{k}", f"v{k}")
        assert read(vf) == (f"v{k}", f"v{k}") and os.readlink(tmp_path / "out") == f"outs/2026010{k}T000000Z-00000{k}"
    assert vf.versions() == ["20260102T000000Z-000002", "20260103T000000Z-000003"]
    assert vf.current_id() == "20260103T000000Z-000003"


def test_a_failed_version_leaves_the_current_one_and_no_trace(tmp_path):
    vf = VersionedFolder(tmp_path, "out", "outs")
    publish(vf, "20260101T000000Z-000001", "old")
    with pytest.raises(KeyboardInterrupt):
        with vf.new_version("20260102T000000Z-000002") as v:
            (v.path / "a.txt").write_text("half")
            raise KeyboardInterrupt
    with pytest.raises(StorageError, match=r"out: cannot write the new version \(No space left on device\); nothing "
                                           r"of it was kept, the current one is unchanged"):
        with vf.new_version("20260103T000000Z-000003") as v:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    assert read(vf) == ("old", "old") and vf.versions() == ["20260101T000000Z-000001"]
    assert sorted(os.listdir(tmp_path / "outs")) == ["20260101T000000Z-000001"]
    fresh = VersionedFolder(tmp_path / "new", "out", "outs")
    (tmp_path / "new").mkdir()
    with pytest.raises(ValueError):
        with fresh.new_version():
            raise ValueError("first version fails")
    assert os.listdir(tmp_path / "new") == []  # not even an empty store


def test_what_a_killed_writer_leaves_is_ignored_then_removed(tmp_path):
    vf = VersionedFolder(tmp_path, "out", "outs", keep=2)
    publish(vf, "20260101T000000Z-000001", "v1")
    store = tmp_path / "outs"
    (store / ".20260102T000000Z-000002.partial").mkdir()  # killed while writing
    (store / ".20260102T000000Z-000002.partial" / "a.txt").write_text("half")
    (store / "20260103T000000Z-000003").mkdir()  # killed between the two renames: complete, never current
    (store / "20260103T000000Z-000003" / "a.txt").write_text("orphan")
    os.symlink("outs/20260103T000000Z-000003", tmp_path / ".out.20260103T000000Z-000003.link")
    assert read(vf) == ("v1", "v1")  # readers see the current version only
    publish(vf, "20260104T000000Z-000004", "v4")
    assert sorted(os.listdir(store)) == ["20260101T000000Z-000001", "20260104T000000Z-000004"]
    assert not [n for n in os.listdir(tmp_path) if n.endswith(".link")]
    assert read(vf) == ("v4", "v4")


def test_an_older_plain_folder_is_read_then_adopted_even_when_the_move_was_cut_short(tmp_path):
    vf = VersionedFolder(tmp_path, "out", "outs", keep=None)
    (tmp_path / "out").mkdir()
    for name in ("a.txt", "b.txt"):
        (tmp_path / "out" / name).write_text("plain")
    assert read(vf) == ("plain", "plain")
    # killed after moving the plain folder into the store, before the link existed
    (tmp_path / "outs").mkdir()
    os.rename(tmp_path / "out", tmp_path / "outs" / "20250101T000000Z-legacy")
    assert read(vf) == ("plain", "plain")
    publish(vf, "20260101T000000Z-000001", "new")
    assert read(vf) == ("new", "new") and vf.versions() == ["20250101T000000Z-legacy", "20260101T000000Z-000001"]
    # a plain folder adopted by the next version: moved, kept (keep=None: diagnoses keep every one)
    vf2 = VersionedFolder(tmp_path / "r2", "out", "outs", keep=None)
    (tmp_path / "r2" / "out").mkdir(parents=True)
    (tmp_path / "r2" / "out" / "a.txt").write_text("plain")
    publish(vf2, "20260101T000000Z-000009", "next")
    legacy = [v for v in vf2.versions() if v.endswith("-legacy")]
    assert len(legacy) == 1 and (tmp_path / "r2" / "outs" / legacy[0] / "a.txt").read_text() == "plain"
