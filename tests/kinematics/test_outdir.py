"""Output folders: checked before work, marked INCOMPLETE until done, one writer at a time."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from kinematics.outdir import (INCOMPLETE, KIND_FILE, LOCK, OutputFolderError, check_complete, check_folder, check_output,
                               check_output_file, output_folder)


def test_marker_while_writing_gone_after(tmp_path):
    out = tmp_path / "run"
    with output_folder(out) as d:
        assert d == out and (out / INCOMPLETE).exists() and (out / LOCK).exists()
        with pytest.raises(OutputFolderError, match="still being written"):
            check_complete(out)
        (out / "result.csv").write_text("a\n")
    assert not (out / INCOMPLETE).exists() and not (out / LOCK).exists()
    check_complete(out)
    assert sorted(p.name for p in out.iterdir()) == [KIND_FILE, "result.csv"]


def test_a_failure_leaves_the_marker_and_an_empty_new_folder_goes(tmp_path):
    out = tmp_path / "run"
    with pytest.raises(RuntimeError):
        with output_folder(out):
            (out / "half.csv").write_text("a\n")
            raise RuntimeError("killed")
    with pytest.raises(OutputFolderError, match="stopped before the end") as e:
        check_complete(out, "sweep")
    assert "\n" not in str(e.value) and str(out / INCOMPLETE) in str(e.value)
    # Nothing written: the folder it created is removed, nothing is left behind.
    with pytest.raises(ValueError):
        with output_folder(tmp_path / "empty"):
            raise ValueError("bad input found late")
    assert not (tmp_path / "empty").exists()


def test_nested_use_is_one_write(tmp_path):
    with output_folder(tmp_path / "a"):
        with output_folder(tmp_path / "a"):
            pass
        assert (tmp_path / "a" / INCOMPLETE).exists()      # the inner block does not complete it
    assert not (tmp_path / "a" / INCOMPLETE).exists()


def test_unwritable_places_are_refused_before_work(tmp_path):
    f = tmp_path / "file.txt"
    f.write_text("x")
    with pytest.raises(OutputFolderError, match="is a file"):
        check_output(f)
    with pytest.raises(OutputFolderError, match="is a file"):
        check_output(f / "sub")
    with pytest.raises(OutputFolderError, match="cannot create") as e:
        with output_folder("/proc/wvr-out/x"):
            pass
    assert "\n" not in str(e.value)
    with pytest.raises(OutputFolderError):
        with output_folder("/sys/wvr-out"):
            pass


_HOLDER = textwrap.dedent("""
    import sys, time
    from kinematics.outdir import output_folder
    with output_folder(sys.argv[1]):
        print("holding", flush=True)
        time.sleep(60)
""")


def test_a_second_writer_is_refused_and_a_dead_ones_lock_taken_over(tmp_path):
    out = tmp_path / "run"
    p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(out)], stdout=subprocess.PIPE, text=True)
    try:
        assert p.stdout.readline().strip() == "holding"
        with pytest.raises(OutputFolderError, match="another run is writing") as e:
            with output_folder(out):
                pass
        assert f"pid {p.pid}" in str(e.value)
        with pytest.raises(OutputFolderError, match="still being written"):
            check_complete(out)
    finally:
        os.kill(p.pid, signal.SIGKILL)
        p.wait()
    # Killed: its lock file and marker stay, but no process holds the lock any more.
    assert (out / LOCK).exists() and (out / INCOMPLETE).exists()
    with pytest.raises(OutputFolderError, match="stopped before the end"):
        check_complete(out)
    t0 = time.perf_counter()
    with output_folder(out):
        pass
    assert time.perf_counter() - t0 < 1.0
    check_complete(out)


def test_another_commands_folder_is_refused_and_left_as_it_was(tmp_path):
    out = tmp_path / "rec"
    with output_folder(out, kind="sim record"):
        (out / "groundtruth.txt").write_text("1 0 0 0 0 0 0 1\n")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    for kind in ("sim run", "slam"):
        with pytest.raises(OutputFolderError, match="holds the results of another command, wvr sim record") as e:
            with output_folder(out, kind=kind):
                pytest.fail("entered")
        assert "\n" not in str(e.value) and "another --out" in str(e.value)
        with pytest.raises(OutputFolderError, match="another command"):
            check_folder(out, kind)
    # The same kind, finished: refused too (unless the kind continues its own folders).
    with pytest.raises(OutputFolderError, match="already holds the finished results"):
        with output_folder(out, kind="sim record"):
            pass
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before


def test_a_refusal_by_the_kinds_own_check_keeps_the_folders_record(tmp_path):
    out = tmp_path / "sweep"
    with output_folder(out, kind="design optimise", reuse=True):
        (out / "state.pkl").write_bytes(b"x")
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def refuse(d):
        raise ValueError("already holds a sweep; use --resume")

    for _ in range(2):
        with pytest.raises(ValueError, match="use --resume"):
            with output_folder(out, kind="design optimise", reuse=True, check=refuse):
                pass
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    with output_folder(out, kind="design optimise", reuse=True):      # reuse: its own folder, kept
        assert (out / "state.pkl").exists()


def test_a_killed_runs_folder_is_cleared_by_the_next_run_of_its_kind(tmp_path, capsys):
    out = tmp_path / "S"
    with pytest.raises(KeyboardInterrupt):
        with output_folder(out, kind="slam"):
            (out / "video").mkdir()
            (out / "video.mp4").write_bytes(b"half")
            raise KeyboardInterrupt
    with output_folder(out, kind="slam"):
        assert sorted(p.name for p in out.iterdir()) == sorted([INCOMPLETE, KIND_FILE, LOCK])
        (out / "trajectory.tum").write_text("")
    assert "killed wvr slam run left it incomplete" in capsys.readouterr().err
    assert sorted(p.name for p in out.iterdir()) == [KIND_FILE, "trajectory.tum"]


def test_a_folder_no_wvr_run_wrote_is_refused_unless_empty(tmp_path):
    mine = tmp_path / "mine"
    mine.mkdir()
    with output_folder(mine, kind="slam"):              # empty: accepted
        pass
    theirs = tmp_path / "theirs"
    theirs.mkdir()
    (theirs / "rgb.txt").write_text("")
    with pytest.raises(OutputFolderError, match="no wvr run wrote it .*rgb.txt"):
        with output_folder(theirs, kind="slam"):
            pass
    assert [p.name for p in theirs.iterdir()] == ["rgb.txt"]


def test_a_failure_before_any_file_leaves_an_existing_empty_folder_empty(tmp_path):
    out = tmp_path / "empty"
    out.mkdir()
    with pytest.raises(ValueError):
        with output_folder(out, kind="stabilise"):
            (out / "fovea").mkdir()                      # a folder made, no file written
            raise ValueError("none of the images could be read")
    assert list(out.iterdir()) == []


def test_output_files_are_checked_without_making_anything(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputFolderError, match="is a file"):
        check_output_file(f / "c.toml", "--out", ".toml")
    with pytest.raises(OutputFolderError, match="does not exist"):
        check_output_file(tmp_path / "missing" / "c.toml", "--out", ".toml")
    with pytest.raises(OutputFolderError, match="is a folder"):
        check_output_file(tmp_path, "--out", ".toml")
    with pytest.raises(OutputFolderError, match="ending in .png"):
        check_output_file(tmp_path / "x.jpg", "--out", ".png")
    assert check_output_file(tmp_path / "c.toml", "--out", ".toml") == tmp_path / "c.toml"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
