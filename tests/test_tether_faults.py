"""The tethering session under every named fault scenario of the simulated 70D: one exposure per requested shot,
every exposure's file on disk byte-identical with a consistent catalog, nothing half-written, no button left down."""

from __future__ import annotations

import hashlib
import itertools
from pathlib import Path

import pytest

from mca.capture.tether import TetherSession, sanitize_filename
from mca.devices.cameras import make_sim_rig, open_camera
from mca.devices.ptp.codes import Op
from mca.devices.sim.eos70d.faults import SCENARIOS, FaultPlan, scenario
from mca.devices.sim.eos70d.responder import default_frame_source

#: Shots per scenario (the slow half press takes 6 s a shot).
SHOTS = {"slow-half-press": 1}


def _run(tmp_path: Path, faults: FaultPlan, count: int = 3, frame_source=default_frame_source, timeout_s: float = 0.3):
    rig = make_sim_rig(frame_source, faults=faults)
    session = TetherSession(open_camera("sim", rig=rig, timeout_s=timeout_s), tmp_path)
    session.connect()
    results = session.capture(count)
    assert [r.status for r in results] == ["downloaded"] * count
    return session, rig


def _check_card_against_disk(session: TetherSession, rig, out: Path, count: int) -> None:
    rows = session.catalog.rows()
    card = rig.camera.card_files()
    assert len(rows) == count
    for row in rows:
        data = (out / row.file_name).read_bytes()
        assert data == card[row.camera_filename]
        assert row.status == "downloaded" and row.size_bytes == len(data)
        assert row.sha256 == hashlib.sha256(data).hexdigest()
        assert row.camera_serial == "SIM70D0000001" and row.downloaded_at >= row.captured_at
    assert not list(out.glob(".*.part"))


@pytest.mark.parametrize("name", sorted(SCENARIOS))
def test_every_fault_scenario_gives_one_exposure_per_requested_shot_and_loses_nothing(
    tmp_path: Path, name: str
) -> None:
    chosen = scenario(name)
    shots = SHOTS.get(name, 3)
    rig = make_sim_rig(default_frame_source, scenario=name)
    sim = rig.camera
    session = TetherSession(open_camera("sim", rig=rig, timeout_s=chosen.host_timeout_s), tmp_path)
    session.connect()
    results = session.capture(shots)
    sim.wait_idle()
    session.close()
    presses_expected = 0 if name == "af-fail" else shots  # One-Shot AF without focus: refused before the full press
    assert sim.full_presses == presses_expected  # never a second release for one requested shot
    assert not sim.half_pressed  # no button left down
    assert not list(tmp_path.glob(".*.part"))
    if chosen.shots_succeed:
        assert sim.exposures == shots
        assert [r.status for r in results] == ["downloaded"] * shots
        card = sim.card_files()
        made = {f"IMG_{i:04d}.CR2" for i in range(1, shots + 1)}
        assert made <= set(card)
        for r in results:
            assert r.path is not None and r.path.read_bytes() == card[r.path.name]
        rows = [row for row in _rows(tmp_path)]
        assert sorted(row[0] for row in rows) == sorted(made) and all(row[1] == "downloaded" for row in rows)
    else:
        assert sim.exposures == 0 and [r.status for r in results] == ["refused"] * shots
        assert all("no picture was taken" in r.message for r in results)


def _rows(out: Path) -> list[tuple[str, str]]:
    import sqlite3

    db = sqlite3.connect(out / "catalog.sqlite")
    try:
        return db.execute("SELECT camera_filename, status FROM shots ORDER BY id").fetchall()
    finally:
        db.close()


@pytest.mark.parametrize(
    "faults",
    [
        FaultPlan(disconnect_after_in_bytes=100_000),
        FaultPlan(stall_op=Op.EOS_GET_PARTIAL_OBJECT),
        FaultPlan(busy_count=2),
        FaultPlan(short_read_bytes=1000),
        FaultPlan(corrupt_op=Op.EOS_GET_PARTIAL_OBJECT),
    ],
    ids=["disconnect-mid-download", "stall", "device-busy", "short-reads", "corrupt-container"],
)
def test_faults_end_with_every_shot_on_disk(tmp_path: Path, faults: FaultPlan) -> None:
    session, rig = _run(tmp_path, faults)
    _check_card_against_disk(session, rig, tmp_path, 3)
    assert rig.camera.exposures == 3
    session.close()


def test_disconnect_reconnects_and_fetches_missing(tmp_path: Path) -> None:
    session, rig = _run(tmp_path, FaultPlan(disconnect_after_in_bytes=10_000))
    assert session.reconnects >= 1 and rig.backend.device_id.address == 5  # re-enumerated at a new address
    _check_card_against_disk(session, rig, tmp_path, 3)
    session.close()


def test_delete_after_verify_empties_the_card(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    session = TetherSession(open_camera("sim", rig=rig), tmp_path, delete_after_verify=True)
    session.connect()
    session.capture(2)
    assert rig.camera.card_files() == {}
    assert len(list(tmp_path.glob("IMG_*.CR2"))) == 2
    session.close()


def test_hostile_file_names_stay_inside_the_output_folder(tmp_path: Path) -> None:
    names = iter(["../../etc/passwd", "..", "IMG\x00\x1b[31m.CR2", "a/b\\c.CR2", "IMG_0001.CR2", "img_0001.cr2"])
    source = lambda i: (next(names), b"x" * (100 + i))  # noqa: E731
    out = tmp_path / "out"
    session, _rig = _run(out, FaultPlan(), count=6, frame_source=source)
    files = sorted(p.name for p in out.iterdir() if p.name != "catalog.sqlite" and not p.name.startswith("catalog"))
    assert all("/" not in f and ".." not in f and f.isprintable() for f in files)
    assert len(files) == 6 and not (tmp_path / "etc").exists()
    assert "IMG_0001_1.CR2" in files or "img_0001_1.cr2" in files
    session.close()


def test_sanitize_filename_rules() -> None:
    assert sanitize_filename("../../x.CR2") == "x.CR2"
    assert sanitize_filename("..") == "shot"
    assert sanitize_filename("A.CR2", {"a.cr2"}) == "A_1.CR2"
    assert "\x1b" not in sanitize_filename("\x1bIMG.CR2")


def test_tethered_mode_downloads_shutter_button_shots(tmp_path: Path) -> None:
    rig = make_sim_rig(default_frame_source)
    session = TetherSession(open_camera("sim", rig=rig), tmp_path)
    session.connect()
    rig.camera.press_shutter_button()
    rig.camera.press_shutter_button()
    results = session.tethered(lambda: False, max_shots=2)
    assert [r.path.read_bytes() for r in results] == [rig.camera.file_on_card(f"IMG_000{i}.CR2") for i in (1, 2)]
    session.close()


def test_catalog_times_never_run_backwards_across_a_second_boundary() -> None:
    """Seconds and milliseconds come from one clock reading: the old `_now` read them separately and
    could write 28.001 s as '27.001' at a second boundary (a shot 'downloaded' before it was captured)."""
    import time

    from mca.capture.catalog import _now

    boundary = int(time.time()) + 1  # stamp continuously through the next whole second
    stamps = []
    while time.time() < boundary + 0.05:
        stamps.append(_now())
    assert any(stamp[17:19] != stamps[0][17:19] for stamp in stamps)  # the seconds field did change
    assert all(later >= earlier for earlier, later in itertools.pairwise(stamps))


class _Killed(BaseException):
    """A `kill -9` at one line of the session: nothing after it runs (no handler catches a BaseException)."""


@pytest.mark.parametrize("changed_since", [False, True])
def test_a_run_killed_between_renaming_a_shot_into_place_and_cataloguing_it_leaves_nothing_unlisted(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, changed_since: bool
) -> None:
    """The file was renamed into place, its row still said `captured`. The next run downloads the shot again,
    finds the file already there with the same bytes, and gives it its row: one file, listed, no `_1` copy
    (until the twenty-eighth stop it wrote `IMG_0001_1.CR2` and left the first unlisted for good; the main job's
    fault test hit it once with a random SIGKILL). A file of that name whose bytes are not the shot's is never
    taken for it: it stays as it is, unlisted, and the shot gets a name of its own."""
    rig = make_sim_rig(default_frame_source)
    first = TetherSession(open_camera("sim", rig=rig, timeout_s=0.3), tmp_path)
    first.connect()

    def killed(*args, **kwargs):
        raise _Killed

    monkeypatch.setattr(first.catalog, "mark_downloaded", killed)
    with pytest.raises(_Killed):
        first.capture(1)
    (on_disk,) = tmp_path.glob("*.CR2")
    assert [row.status for row in first.catalog.rows()] == ["captured"]
    assert any("does not list" in problem for problem in first.catalog.disagreements())
    first.close()  # the connection ends with the process (the simulated card outlives it, as a real one does)
    stranger = bytes(b ^ 0xFF for b in on_disk.read_bytes())  # the same size, other bytes
    if changed_since:
        on_disk.write_bytes(stranger)

    second = TetherSession(open_camera("sim", rig=rig, timeout_s=0.3), tmp_path)
    second.connect()  # fetches what the catalog says is still on the card
    try:
        (row,) = second.catalog.rows()
        assert row.status == "downloaded"
        _check_card_against_disk(second, rig, tmp_path, 1)
        if changed_since:
            assert row.file_name != on_disk.name and on_disk.read_bytes() == stranger
            assert [p for p in second.catalog.disagreements() if "does not list" in p] == [
                f"{on_disk}: a photograph in the folder that the catalog does not list"
            ]
        else:
            assert sorted(p.name for p in tmp_path.glob("*.CR2")) == [on_disk.name] == [row.file_name]
            assert second.catalog.disagreements() == []
    finally:
        second.close()
