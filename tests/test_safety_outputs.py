"""Output folders under odd names, changed photographs, concurrent runs and a full disk (issue 13, items 1-4).

Each test was run against the code before the fix and failed there: outputs of `...CR2` landed in
the parent of --out and deleted the user's files; a different photograph with the same stem was
skipped; two runs wrote one folder at once; `--force` deleted the old result before the new one
existed.
"""

from __future__ import annotations

import errno
import json
import os
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from test_process import FULL_SET, fake_pipeline, files_under, make_png, make_tiff

from mca.capture import outputs
from mca.capture.batch import run_batch
from mca.capture.pipeline_app import RESULT_NAME, output_dir_for, process_file
from mca.devices.profiles import load_profile


@pytest.fixture(scope="module")
def profile():
    return load_profile("paper-70d")


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under `folder` (hidden ones included) with its bytes."""
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def visible(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir() if not p.name.startswith(".")}


def result_of(folder: Path) -> dict:
    return json.loads((folder / RESULT_NAME).read_text())


# --- item 1: names never leave --out, never touch what is not ours ---------------------------------------------------


@pytest.mark.parametrize(
    "file_name", ["...png", "..png", ".png", ". .png", "a\\b.png", "\x01ctl.png", "-.png", "   .png"]
)
def test_odd_names_stay_inside_out_and_touch_nothing_else(tmp_path, profile, file_name):
    inputs = tmp_path / "in"
    inputs.mkdir()
    source = make_png(inputs / "x.png")
    odd = inputs / file_name
    source.rename(odd)
    parent = tmp_path / "work"
    out = parent / "out"
    (parent / "layers").mkdir(parents=True)
    (parent / "layers" / "00.png").write_bytes(b"the user's own layer")
    (parent / "depth.tiff").write_bytes(b"the user's own depth map")
    before = snapshot(parent)
    outcome = process_file(odd, out, profile, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    assert outcome.output_dir.parent == out.resolve() and outcome.output_dir.name not in ("", ".", "..")
    assert not outcome.output_dir.name.startswith(".")
    assert files_under(outcome.output_dir) == FULL_SET
    after = snapshot(parent)
    assert {k: v for k, v in after.items() if not k.startswith("out/")} == before  # nothing outside --out changed


def test_safe_names() -> None:
    from mca.capture.output_folders import output_name_for, safe_folder_name

    assert output_name_for(Path("...CR2")) == "CR2"
    assert output_name_for(Path("/x/IMG_1.CR2")) == "IMG_1"
    assert output_name_for(Path("..")) == "photo"
    for text in ("..", ".", "", "/", "../../etc", ".hidden", "a/../b", "x" * 300):
        name = safe_folder_name(text)
        assert name and name not in (".", "..") and "/" not in name and not name.startswith(".")
        assert len(name) <= 100
    assert output_dir_for(Path("/in/...CR2"), Path("/out")) == Path("/out/CR2")


def test_a_users_folder_of_that_name_is_never_written_into(tmp_path, profile):
    out = tmp_path / "out"
    mine = out / "shot"
    (mine / "layers").mkdir(parents=True)
    (mine / "layers" / "00.png").write_bytes(b"user data")
    (mine / "notes.txt").write_text("keep me")
    before = snapshot(mine)
    outcome = process_file(make_png(tmp_path / "shot.png"), out, profile, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    assert outcome.output_dir == out.resolve() / "shot-2"
    assert snapshot(mine) == before


def test_a_symbolic_link_in_out_is_never_followed(tmp_path, profile):
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    (out / "shot").symlink_to(outside, target_is_directory=True)
    outcome = process_file(make_png(tmp_path / "shot.png"), out, profile, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    assert outcome.output_dir.name == "shot-2" and list(outside.iterdir()) == []


# --- item 2: results keyed by content and settings --------------------------------------------------------------------


def test_same_stem_different_photo_in_separate_runs_gets_its_own_folder(tmp_path, profile):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    first = make_png(tmp_path / "a" / "IMG_1.png", 48, 64)
    second = make_png(tmp_path / "b" / "IMG_1.png", 40, 56)
    out = tmp_path / "out"
    one = run_batch([first], out, profile, pipeline=fake_pipeline)
    two = run_batch([second], out, profile, pipeline=fake_pipeline)
    assert [o.status for o in one.outcomes] == ["done"]
    assert [o.status for o in two.outcomes] == ["done"], two.outcomes[0].reason
    assert visible(out) == {"IMG_1", "IMG_1-2"}
    assert result_of(out / "IMG_1")["source"]["path"] == str(first.resolve())
    assert result_of(out / "IMG_1-2")["source"]["path"] == str(second.resolve())
    # both are now finished: a third run of either skips it and finds its own folder
    again = run_batch([second, first], out, profile, pipeline=fake_pipeline)
    assert {o.input_path.parent.name: (o.status, o.output_dir.name) for o in again.outcomes} == {
        "a": ("skipped", "IMG_1"),
        "b": ("skipped", "IMG_1-2"),
    }


def test_a_reshot_photo_is_processed_again_an_unchanged_one_skipped(tmp_path, profile):
    source = make_png(tmp_path / "IMG_1.png", 48, 64)
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    unchanged = process_file(source, out, profile, pipeline=fake_pipeline)
    assert unchanged.status == "skipped" and "already finished" in unchanged.reason
    make_png(source, 40, 56)  # the same name, a new photograph
    redone = process_file(source, out, profile, pipeline=fake_pipeline)
    assert redone.status == "done", redone.reason
    assert redone.output_dir.name == "IMG_1" and visible(out) == {"IMG_1"}
    document = result_of(out / "IMG_1")
    assert document["input_size_px"] == [56, 40]
    import hashlib

    assert document["source"]["sha256"] == hashlib.sha256(source.read_bytes()).hexdigest()


def test_other_settings_are_processed_again(tmp_path, profile):
    import dataclasses

    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    other = dataclasses.replace(profile, lens=None, name="none")
    outcome = process_file(source, out, other, pipeline=fake_pipeline)
    assert outcome.status == "done", outcome.reason
    assert result_of(out / "IMG_1")["mode"] == "disparity-only"


def test_a_moved_photo_finds_its_result(tmp_path, profile):
    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    moved = tmp_path / "elsewhere"
    moved.mkdir()
    source = source.rename(moved / "IMG_1.png")
    outcome = process_file(source, out, profile, pipeline=fake_pipeline)
    assert outcome.status == "skipped" and outcome.output_dir.name == "IMG_1"


def test_a_result_of_an_earlier_mca_is_recognised(tmp_path, profile):
    """Folders written before results were keyed (result.json without 'source') are kept while the input is older."""
    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    document = result_of(out / "IMG_1")
    del document["source"], document["settings_sha256"]
    outputs.write_json(out / "IMG_1" / RESULT_NAME, document)
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "skipped"
    time.sleep(0.01)
    make_png(source, 40, 56)
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"


# --- item 3: one run at a time per output folder ----------------------------------------------------------------------


def test_two_runs_into_one_folder_at_once_do_not_mix(tmp_path, profile):
    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    inside = threading.Event()
    release = threading.Event()

    def slow_pipeline(*args, **kwargs):
        inside.set()
        release.wait(10)
        return fake_pipeline(*args, **kwargs)

    outcomes = {}

    def run(key, pipeline):
        outcomes[key] = process_file(source, out, profile, pipeline=pipeline)

    first = threading.Thread(target=run, args=("first", slow_pipeline))
    first.start()
    assert inside.wait(10)
    second = threading.Thread(target=run, args=("second", fake_pipeline))
    second.start()
    time.sleep(0.6)
    assert second.is_alive(), "the second run must wait for the folder, not write into it"
    release.set()
    first.join(20)
    second.join(20)
    assert outcomes["first"].status == "done", outcomes["first"].reason
    assert outcomes["second"].status == "skipped", outcomes["second"].reason
    assert visible(out) == {"IMG_1"} and files_under(out / "IMG_1") == FULL_SET


def test_different_photos_with_one_stem_at_once_get_separate_folders(tmp_path, profile):
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    sources = [make_png(tmp_path / "a" / "IMG.png", 48, 64), make_tiff(tmp_path / "b" / "IMG.tiff", 40, 56)]
    out = tmp_path / "out"
    barrier = threading.Barrier(2)

    def together(*args, **kwargs):
        barrier.wait(10)
        return fake_pipeline(*args, **kwargs)

    outcomes = []
    threads = [
        threading.Thread(target=lambda s=s: outcomes.append(process_file(s, out, profile, pipeline=together)))
        for s in sources
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(20)
    assert sorted(o.status for o in outcomes) == ["done", "done"], [o.reason for o in outcomes]
    assert visible(out) == {"IMG", "IMG-2"}
    paths = {result_of(out / n)["source"]["path"] for n in ("IMG", "IMG-2")}
    assert paths == {str(s.resolve()) for s in sources}


# --- item 4: --force replaces, then deletes ---------------------------------------------------------------------------


def test_force_on_a_full_disk_keeps_the_old_result(tmp_path, profile, monkeypatch):
    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    before = snapshot(out / "IMG_1")
    real = outputs.write_bytes_atomic
    calls = {"n": 0}

    def fills_up(path, data):
        calls["n"] += 1
        if calls["n"] > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return real(path, data)

    monkeypatch.setattr(outputs, "write_bytes_atomic", fills_up)
    outcome = process_file(source, out, profile, force=True, pipeline=fake_pipeline)
    assert outcome.status == "failed"
    assert "disk is full" in outcome.reason and str(source) in outcome.reason
    assert snapshot(out / "IMG_1") == before  # every old file, byte for byte
    assert {p.name for p in out.iterdir()} <= {"IMG_1", ".mca.lock"}  # no staging or lock left behind


def test_force_replaces_every_file(tmp_path, profile):
    source = make_png(tmp_path / "IMG_1.png")
    out = tmp_path / "out"
    assert process_file(source, out, profile, pipeline=fake_pipeline).status == "done"
    (out / "IMG_1" / "layers" / "07.png").write_bytes(b"a layer of an older run")
    stamp = (out / "IMG_1" / RESULT_NAME).stat().st_mtime_ns
    outcome = process_file(source, out, profile, force=True, pipeline=fake_pipeline)
    assert outcome.status == "done"
    assert files_under(out / "IMG_1") == FULL_SET and (out / "IMG_1" / RESULT_NAME).stat().st_mtime_ns > stamp


def test_a_failure_half_way_leaves_no_partial_folder(tmp_path, profile):
    def broken(planes, *args, **kwargs):
        result = fake_pipeline(planes, *args, **kwargs)
        result.all_in_focus = np.zeros((3,), np.float32)  # the writers fail on this, after some files exist
        return result

    outcome = process_file(make_png(tmp_path / "IMG_1.png"), tmp_path / "out", profile, pipeline=broken)
    assert outcome.status == "failed"
    assert visible(tmp_path / "out") == set()
    assert [p.name for p in (tmp_path / "out").iterdir()] == [".mca.lock"]


def test_watch_takes_a_reshot_file_again(tmp_path, profile):
    """In watch mode a file replaced by a new photograph of the same name is processed again once settled."""
    inbox = tmp_path / "inbox"
    inbox.mkdir()
    make_png(inbox / "IMG_1.png", 48, 64)
    holder: dict = {}

    def watch() -> None:
        holder["report"] = run_batch(
            [inbox],
            tmp_path / "out",
            profile,
            watch=True,
            watch_timeout_s=3.0,
            poll_interval_s=0.1,
            settle_s=0.5,
            pipeline=fake_pipeline,
        )

    thread = threading.Thread(target=watch)
    thread.start()
    try:
        deadline = time.monotonic() + 30
        while not (tmp_path / "out" / "IMG_1" / RESULT_NAME).exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert result_of(tmp_path / "out" / "IMG_1")["input_size_px"] == [64, 48]
        reshot = make_png(tmp_path / "new.png", 40, 56)
        os.replace(reshot, inbox / "IMG_1.png")
    finally:
        thread.join(timeout=60)
    assert not thread.is_alive()
    assert [o.status for o in holder["report"].outcomes] == ["done", "done"]
    assert result_of(tmp_path / "out" / "IMG_1")["input_size_px"] == [56, 40]
