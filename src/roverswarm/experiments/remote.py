"""Training a grid's runs on a Ray cluster (``--backend ray``)."""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

from roverswarm.config import config_from_json, config_to_json
from roverswarm.errors import UserError
from roverswarm.experiments.arms import GridRun
from roverswarm.experiments.live import Summary
from roverswarm.trainer import train


def train_remote(config_json: str) -> dict[str, bytes]:
    """A Ray task: train one run in a scratch folder, return its files {relative path: bytes}."""
    from roverswarm.jaxcache import enable_compilation_cache

    enable_compilation_cache()
    with tempfile.TemporaryDirectory() as scratch:
        out = Path(scratch) / "run"
        train(config_from_json(config_json), out=out, progress=False)
        return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


def run_ray(runs: list[GridRun], summary: Summary, address: str | None, retries: int) -> None:
    """Send each run to a Ray cluster as one task (retried if its worker dies); write the
    returned files into the run's folder as each task completes.

    A task trains its run from the start in the worker's scratch space (workers need not
    share a file system), so a retried or previously interrupted run starts over there. The
    summary shows submitted runs as running and updates as each one returns."""
    try:
        import ray
    except ImportError as error:
        raise UserError("--backend ray needs Ray: pip install 'roverswarm[ray]'") from error
    if not ray.is_initialized():
        ray.init(address=address, log_to_driver=False)
    task = ray.remote(num_cpus=1, max_retries=retries)(train_remote)
    pending = {task.remote(config_to_json(run.config)): run for run in runs}
    for run in runs:
        summary.progress(run, 0)
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        run = pending.pop(ready[0])
        files = ray.get(ready[0])
        staging = run.folder.with_name(run.folder.name + ".incoming")  # whole folders only
        if staging.exists():
            shutil.rmtree(staging)
        for name, content in files.items():
            path = staging / name
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(content)
        if run.folder.exists():
            shutil.rmtree(run.folder)
        staging.rename(run.folder)
        summary.finish(run)
