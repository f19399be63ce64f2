"""Bad input for design sweeps (issue 48): no unpickling, damaged logs, work-size bounds."""

import pickle
from dataclasses import replace

import pytest

from kinematics.outdir import OutputFolderError

from design.sweep import SweepStateError, open_client, run_sweep
from design.sweep_file import SweepFileError, spec_from_dict, spec_to_dict
from test_sweep import read_rows, tiny_spec
from wvr.cli import main


class _Payload:
    """Unpickling this writes a file: proof that the pickle's code ran."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


def test_resume_never_unpickles(tmp_path):
    spec = tiny_spec(7)
    out = tmp_path / "s"
    run_sweep(spec, out, progress=False)
    (out / "state.json").unlink()
    proof = tmp_path / "ran"
    (out / "state.pkl").write_bytes(pickle.dumps(_Payload(proof)))
    with pytest.raises(SweepStateError, match="never loaded"):
        run_sweep(spec, out, resume=True, progress=False)
    assert not proof.exists()


def test_damaged_checkpoint_refused_in_one_line(tmp_path):
    spec = tiny_spec(7)
    run_sweep(spec, tmp_path, progress=False)
    (tmp_path / "state.json").write_bytes((tmp_path / "state.json").read_bytes()[:20])
    with pytest.raises(SweepStateError, match="damaged checkpoint") as e:
        run_sweep(spec, tmp_path, resume=True, progress=False)
    assert "\n" not in str(e.value)


def test_empty_log_loses_nothing(tmp_path, capsys):
    spec = tiny_spec(7)
    run_sweep(spec, tmp_path, progress=False)
    (tmp_path / "evaluations.csv").write_text("")
    r = run_sweep(spec, tmp_path, evaluations=7, resume=True, progress=False)
    assert "was empty" in capsys.readouterr().err
    rows = read_rows(tmp_path / "evaluations.csv")      # the header is back: DictReader reads every row
    assert len(rows) == 7 == len(r.F) and r.evaluated == 7


def test_damaged_row_named_and_the_rows_after_it_kept(tmp_path, capsys):
    spec = tiny_spec(9)
    run_sweep(spec, tmp_path, progress=False)
    path = tmp_path / "evaluations.csv"
    lines = path.read_text().splitlines(keepends=True)
    lines[3] = lines[3][:40] + "garbage" + lines[3][60:]   # line 4 of the file, the third row
    path.write_text("".join(lines))
    r = run_sweep(spec, tmp_path, evaluations=9, resume=True, progress=False)
    err = capsys.readouterr().err
    assert "line(s) 4" in err and "1 damaged row" in err
    assert r.evaluated == 1 and r.reused == 8 and len(r.F) == 9
    assert len(read_rows(path)) == 9


def test_resume_with_a_smaller_budget_is_refused(tmp_path):
    spec = tiny_spec(9)
    run_sweep(spec, tmp_path, progress=False)
    with pytest.raises(SweepStateError, match="already holds 9 evaluations"):
        run_sweep(spec, tmp_path, evaluations=4, resume=True, progress=False)
    assert not (tmp_path / "INCOMPLETE").exists()      # refused before anything was written


def test_folder_of_another_run_is_not_overwritten(tmp_path):
    (tmp_path / "report.md").write_text("a sim run's report")
    # The shared output-folder check refuses it before the sweep's own (kinematics.outdir).
    with pytest.raises(OutputFolderError, match="no wvr run wrote it"):
        run_sweep(tiny_spec(3), tmp_path, progress=False)
    assert (tmp_path / "report.md").read_text() == "a sim run's report"


@pytest.mark.parametrize("section, key, value, named", [
    ("criteria", "collision_steps", 100000, "collision_steps"),
    ("criteria", "voxel_m", 1e-9, "voxel_m"),
    ("workload", "rate_hz", 1e9, "samples"),
    ("workload", "saccade_amplitudes_deg", [5.0, 1e6], "saccade_amplitudes_deg"),
    ("sweep", "partitions", 40, "partitions"),
    ("sweep", "seed", -1, "seed"),
])
def test_work_size_bounds_named_up_front(section, key, value, named):
    d = spec_to_dict(tiny_spec())
    d[section][key] = value
    with pytest.raises(SweepFileError, match=named):
        spec_from_dict(d)


def test_negative_seed_names_the_flag(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        main(["design", "optimise", "--out", str(tmp_path / "o"), "--seed", "-1"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--seed" in err and "'-1'" in err and len(err.strip().splitlines()) == 1


def test_dashboard_on_loopback():
    client = open_client(workers=1)
    try:
        assert "127.0.0.1" in client.dashboard_link
        assert client.scheduler.address.startswith("tcp://127.0.0.1:")
    finally:
        client.close()
