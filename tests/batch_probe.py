"""A job for the batch pool's tests (``rigmix.batch.run_pool(..., job=...)``): what a worker
process sees, instead of a composition. A module of its own, so that spawned workers import it."""

from __future__ import annotations

import os


def thread_limits(config: str, out_dir: str) -> dict:
    """The worker's numerical thread pools and thread variables, as a manifest-like entry."""
    from threadpoolctl import threadpool_info

    from rigmix.batch import THREAD_VARIABLES

    return {"config": config, "status": "ok", "pid": os.getpid(),
            "pools": {f"{d['internal_api']}:{os.path.basename(d['filepath'])}": d["num_threads"]
                      for d in threadpool_info()},
            "variables": {name: os.environ.get(name) for name in THREAD_VARIABLES}}
