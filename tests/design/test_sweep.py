"""Sweeps: killed and resumed with nothing lost or repeated; identical on any number of workers."""

import csv
import os
import signal
import subprocess
import sys
import time
from dataclasses import replace

import numpy as np
import pytest

from design.report import write_outputs
from design.sweep import SweepStateError, open_client, run_sweep
from design.sweep_file import CRITERIA, SweepFileError, dump_spec, load_sweep, spec_from_dict, spec_to_dict
from kinematics import forward_kinematics, load_head


def tiny_spec(evaluations=21):
    s = load_sweep()
    return replace(s, name="tiny", evaluations=evaluations, partitions=1, voxel_m=0.008, collision_steps=4,
                   workload=replace(s.workload, saccade_amplitudes_deg=(10.0,), walk_seconds=0.3, rate_hz=40.0))


def read_rows(path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_sweep_writes_outputs_and_chosen_head_loads(tmp_path):
    spec = tiny_spec()
    r = run_sweep(spec, tmp_path, progress=False)
    assert len(r.F) == 21 and r.evaluated == 21 and r.reused == 0
    s = write_outputs(r, spec, tmp_path, pictures=False)
    rows = read_rows(tmp_path / "evaluations.csv")
    assert len(rows) == 21
    assert {"working_volume_cm3", "self_collision", "integrated_torque", "max_torque_nm", "radius_elevation_mm",
            "radius_pan_mm", "radius_cyclotorsion_mm"} <= set(rows[0])
    assert s.evaluations == 21 and s.evaluated == 21 and s.feasible == int(r.feasible.sum())
    if s.front_size:
        head = load_head(s.chosen.head_path)   # what kinematics, the twin and the runtime load
        assert s.chosen.head_path == tmp_path / "chosen_head.toml"
        assert forward_kinematics(head, np.zeros(3)).T_mount_cam.shape == (4, 4)
        front = read_rows(tmp_path / "front.csv")
        assert len(front) == s.front_size
        # The typed result is what the files hold: the chosen row's criteria, the report's table.
        np.testing.assert_allclose([s.chosen.criteria[c] for c in CRITERIA], r.F[s.chosen.index])
        assert f"{s.chosen.criteria['max_torque_nm']:.6g}" in (tmp_path / "report.md").read_text()
    else:
        assert s.chosen is None and "No feasible design" in (tmp_path / "report.md").read_text()
    assert not (tmp_path / "INCOMPLETE").exists()


def test_refusals(tmp_path):
    spec = tiny_spec(7)
    run_sweep(spec, tmp_path, progress=False)
    with pytest.raises(SweepStateError, match="already holds a sweep"):
        run_sweep(spec, tmp_path, progress=False)
    with pytest.raises(SweepStateError, match="sweep file differs"):
        run_sweep(replace(spec, clearance_m=0.002), tmp_path, resume=True, progress=False)
    with pytest.raises(SweepStateError, match="nothing to resume"):
        run_sweep(spec, tmp_path / "new", resume=True, progress=False)


KILL_AFTER_ROW = """
import os, signal, sys
import design.sweep as sweep
from wvr.cli import main
add = sweep._Log.add
def add_then_die(self, *a, **k):
    add(self, *a, **k)
    if self.next_id >= {n}:
        os.kill(os.getpid(), signal.SIGKILL)
sweep._Log.add = add_then_die
sys.exit(main({argv!r}))
"""

HOLD_AFTER_FIRST_ROW = """
import os, sys, time
import design.sweep as sweep
from wvr.cli import main
add = sweep._Log.add
def add_then_hold(self, *a, **k):
    add(self, *a, **k)
    while self.next_id == 1 and not os.path.exists({go!r}):
        time.sleep(0.05)
sweep._Log.add = add_then_hold
import design.study as study
write = study.write_outputs
# The refusal and the rows are checked here, not the pictures (they cost most of the run).
study.write_outputs = lambda result, spec, out, pictures: write(result, spec, out, False)
sys.exit(main({argv!r}))
"""


@pytest.mark.slow
def test_sigkill_then_resume_loses_and_repeats_nothing(tmp_path):
    spec = replace(tiny_spec(28), algorithm="nsga3")     # a population of 7: the kills fall in two batches
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(dump_spec(spec))
    # The uninterrupted run, for comparison.
    full = tmp_path / "full"
    run_sweep(spec, full, progress=False)
    ref_rows = read_rows(full / "evaluations.csv")
    cut = tmp_path / "cut"
    args = ["design", "optimise", "--sweep", str(sweep_file), "--out", str(cut)]
    for kill_after in (3, 12):     # mid-batch, and in a later batch
        # The process SIGKILLs itself right after its kill_after-th row is on disk: a real kill at a
        # known point, however fast or loaded the machine (polling from here could miss the window).
        launcher = KILL_AFTER_ROW.format(n=kill_after, argv=args + (["--resume"] if (cut / "state.json").exists() else []))
        proc = subprocess.run([sys.executable, "-c", launcher], capture_output=True, text=True, timeout=300)
        assert proc.returncode == -signal.SIGKILL, proc.stderr
        assert len(read_rows(cut / "evaluations.csv")) == kill_after
    cmd = [sys.executable, "-m", "wvr", *args]
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    rows = read_rows(cut / "evaluations.csv")
    keys = [(row["batch"], row["index"]) for row in rows]
    assert len(keys) == len(set(keys)) == 28          # nothing repeated, nothing lost
    strip = lambda rs: [{k: v for k, v in row.items() if k != "eval_id"} for row in rs]  # noqa: E731
    assert sorted(strip(rows), key=lambda d: (int(d["batch"]), int(d["index"]))) == \
        sorted(strip(ref_rows), key=lambda d: (int(d["batch"]), int(d["index"])))


def test_agemoea2_resumed_in_a_later_batch_equals_one_run(tmp_path):
    spec = replace(tiny_spec(40), algorithm="agemoea2")
    run_sweep(spec, tmp_path / "full", progress=False)
    run_sweep(spec, tmp_path / "cut", evaluations=30, progress=False)       # stops 2 designs into batch 1
    run_sweep(spec, tmp_path / "cut", resume=True, progress=False)
    strip = lambda rs: [{k: v for k, v in row.items() if k != "eval_id"} for row in rs]  # noqa: E731
    full, cut = read_rows(tmp_path / "full" / "evaluations.csv"), read_rows(tmp_path / "cut" / "evaluations.csv")
    assert len(full) == 40 and {r["batch"] for r in full} == {"0", "1"}
    assert strip(cut) == strip(full)


def test_surrogate_resumed_mid_screened_batch_equals_one_run(tmp_path):
    # Batches 0 and 1 are AGE-MOEA2's own (too few designs for the model); batch 2 is screened,
    # so the cut falls where the replay must refit the model on the logged values bit for bit.
    spec = tiny_spec(84)
    assert spec.algorithm == "surrogate"     # the default sweep's
    run_sweep(spec, tmp_path / "full", progress=False)
    run_sweep(spec, tmp_path / "cut", evaluations=70, progress=False)
    r = run_sweep(spec, tmp_path / "cut", resume=True, progress=False)
    assert (r.reused, r.evaluated) == (70, 14)
    strip = lambda rs: [{k: v for k, v in row.items() if k != "eval_id"} for row in rs]  # noqa: E731
    full, cut = read_rows(tmp_path / "full" / "evaluations.csv"), read_rows(tmp_path / "cut" / "evaluations.csv")
    assert len(full) == 84 and {r["batch"] for r in full} == {"0", "1", "2"}
    assert strip(cut) == strip(full)


@pytest.mark.slow
def test_same_results_with_two_dask_workers(tmp_path):
    spec = tiny_spec(14)
    local = run_sweep(spec, tmp_path / "local", progress=False)
    client = open_client(workers=2)
    try:
        dist = run_sweep(spec, tmp_path / "dask", client=client, progress=False)
    finally:
        client.close()
    np.testing.assert_array_equal(local.X, dist.X)
    np.testing.assert_array_equal(local.F, dist.F)
    np.testing.assert_array_equal(local.G, dist.G)


def test_random_variation_baseline_runs_on_the_same_budget(tmp_path):
    r = run_sweep(tiny_spec(14), tmp_path, algorithm="random", progress=False)
    assert len(r.F) == 14 and r.algorithm == "random"


def test_bad_options_are_refused_before_any_work(tmp_path):
    from design.study import optimise

    spec = tiny_spec(7)
    d = spec_to_dict(spec)
    d["sweep"]["clearance_m"] = -1.0       # would make every design feasible
    with pytest.raises(SweepFileError, match=r"clearance_m = -1.0 must be >= 0"):
        spec_from_dict(d)
    for kw, words in (({"evaluations": 0}, "at least 1 evaluation"), ({"workers": 0}, "at least 1 worker"),
                      ({"scheduler": "localhost"}, "tcp://HOST:PORT"), ({"algorithm": "grid"}, "unknown algorithm")):
        with pytest.raises(ValueError, match=words):
            optimise(spec, tmp_path / "o", progress=False, **kw)
        assert not (tmp_path / "o").exists()
    # A scheduler nobody runs: refused within a few seconds with one line, nothing left behind.
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="no Dask scheduler answered") as e:
        optimise(spec, tmp_path / "o", scheduler="tcp://127.0.0.1:9", progress=False)
    assert time.perf_counter() - t0 < 120 and "\n" not in str(e.value)
    assert not (tmp_path / "o").exists()
    # A refused second start leaves the finished sweep as it was: no INCOMPLETE marker on it.
    optimise(spec, tmp_path / "done", progress=False, pictures=False)
    with pytest.raises(SweepStateError, match="already holds a sweep"):
        optimise(spec, tmp_path / "done", progress=False, pictures=False)
    assert not (tmp_path / "done" / "INCOMPLETE").exists()


@pytest.mark.slow
def test_two_runs_into_one_folder_the_second_is_refused(tmp_path):
    """Two 'design optimise' into the same --out at once used to both 'succeed' and mix their
    evaluations.csv; now the second is refused while the first runs, and the first's files are
    its own."""
    spec = tiny_spec(21)      # the hold below makes the overlap certain: no long sweep is needed for it
    sweep_file = tmp_path / "sweep.toml"
    sweep_file.write_text(dump_spec(spec))
    out = tmp_path / "out"
    args = ["design", "optimise", "--sweep", str(sweep_file), "--out", str(out)]
    go = tmp_path / "go"
    # The first holds after its first row until the second has been answered: they overlap for sure.
    first = subprocess.Popen([sys.executable, "-c", HOLD_AFTER_FIRST_ROW.format(go=str(go), argv=args)],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and not (out / "evaluations.csv").exists():
        assert first.poll() is None, first.stderr.read()
        time.sleep(0.05)
    second = subprocess.run([sys.executable, "-m", "wvr", *args], capture_output=True, text=True)
    go.touch()
    assert first.wait(timeout=300) == 0, first.stderr.read()
    assert second.returncode == 2 and "another run is writing" in second.stderr, second.stderr
    assert second.stderr.count("\n") == 1 and "Traceback" not in second.stderr
    rows = read_rows(out / "evaluations.csv")
    assert len(rows) == 21 and len({r["eval_id"] for r in rows}) == 21
    assert not (out / "INCOMPLETE").exists()
