"""Output folders: checked before work, marked INCOMPLETE until done, one writer at a time."""

import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from kinematics.outdir import INCOMPLETE, KIND_FILE, LOCK, OutputFolderError, check_complete, check_output, output_folder


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
