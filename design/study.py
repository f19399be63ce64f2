"""A whole design study in one call: run (or resume) the sweep and write its outputs (what
``wvr design optimise`` runs). One output folder, locked against a second run and marked
INCOMPLETE until the outputs are written (kinematics.outdir)."""

from __future__ import annotations

from pathlib import Path

from kinematics.outdir import output_folder

from .report import DesignOutputs, write_outputs
from .sweep import SWEEP, check_client_options, check_sweep_folder, open_client, run_options, run_sweep
from .sweep_file import SweepSpec


def optimise(spec: SweepSpec, out: str | Path, *, evaluations: int | None = None, seed: int | None = None,
             algorithm: str | None = None, resume: bool = False, workers: int | None = None,
             scheduler: str | None = None, dashboard: str | None = None, progress: bool = True,
             pictures: bool = True) -> DesignOutputs:
    """Run (or, with ``resume``, continue) the sweep into ``out`` and write its outputs.

    evaluations, seed, algorithm : the run's options (default: the sweep file's). workers : a
    local Dask cluster of that many processes; scheduler : an existing one (tcp://HOST:PORT);
    neither: this process; dashboard : HOST:PORT for the local cluster's dashboard (default
    loopback). Everything that can be refused is refused before anything is
    written: the options, the folder (a file, not writable, another run in it, a sweep there
    without ``resume``, a different sweep to resume).
    """
    out = Path(out)
    check_client_options(workers, scheduler, dashboard)
    budget, seed, algorithm = run_options(spec, evaluations, seed, algorithm)
    with output_folder(out, check=lambda d: check_sweep_folder(spec, d, seed, algorithm, resume, budget), kind=SWEEP,
                       reuse=True):
        client = open_client(workers, scheduler, dashboard)
        try:
            result = run_sweep(spec, out, evaluations=budget, seed=seed, algorithm=algorithm, resume=resume,
                               client=client, progress=progress)
        finally:
            if client is not None:
                client.close()
        return write_outputs(result, spec, out, pictures)
