"""The malformed-file corpus through the real app (``make bench-malformed``).

Uploads every variant of ``terrasift.synthetic.malformed.corpus`` to ``POST /jobs``
of an app with two workers and a 1 GiB worker memory limit, waits for each
accepted job, and prints the counts by outcome, the peak RSS of the workers,
of the header readers and of the API process, and what each case gave
(``--verbose``). ``--full``: every field of the LAS 1.2 and 1.4 headers (LAS and
LAZ) flipped and set to its extremes besides (~900 files); ``--params``: the good
LAZ tile with every hostile parameter set of ``hostile_params`` (~960).
"""

from __future__ import annotations

import argparse
import resource
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from fastapi.testclient import TestClient  # noqa: E402

from terrasift.jobs.params import JobParams  # noqa: E402
from terrasift.service.app import create_app  # noqa: E402
from terrasift.service.settings import Settings  # noqa: E402
from terrasift.synthetic.malformed import (  # noqa: E402
    corpus,
    full_corpus,
    hostile_params,
    run_through_app,
    write_pair,
)

PARAMS = {"block_size": 40, "buffer": 4, "resolution": 1.0, "features": "none"}


def _peak_rss(pid: int) -> int:
    """A live process's peak resident bytes (VmHWM), 0 when unknown."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        pass
    return 0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--verbose", action="store_true")
    ap.add_argument("--full", action="store_true", help="every header field of LAS 1.2 and 1.4")
    ap.add_argument("--params", action="store_true", help="the hostile parameter sets too")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="terrasift-malformed-") as tmp:
        tmp = Path(tmp)
        cases: list = full_corpus(tmp) if args.full else list(corpus(*write_pair(tmp)))
        groups = {name: "files" for name, *_ in cases}
        if args.params:
            laz = write_pair(tmp)[1]
            for name, text in hostile_params(JobParams):
                cases.append((f"params:{name}", "laz", laz, text))
                groups[f"params:{name}"] = "params"
        settings = Settings(
            _env_file=None,
            data_dir=tmp / "data",
            workers=2,
            worker_memory=1024**3,
            max_concurrent_jobs=4,
            task_seconds=60,
        )
        t = time.monotonic()
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            outcomes = run_through_app(client, cases, PARAMS)
            pool = client.app.state.svc.scheduler.executor.pool
            worker_peak, replaced = pool.peak_rss, pool.replaced
            readers = client.app.state.svc.inspector
            reader_peak = max((_peak_rss(pid) for pid in readers.pids()), default=0)
            readers_replaced = readers.replaced
        seconds = time.monotonic() - t
    api_peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    print(f"{len(cases)} cases in {seconds:.0f} s")
    for group in sorted(set(groups.values())):
        counts = Counter(kind for name, (kind, _) in outcomes.items() if groups[name] == group)
        print(f"  {group}: {sum(counts.values())} cases: {dict(counts)}")
    print(
        f"peak RSS: workers {worker_peak / 2**20:.0f} MiB (polled), API process {api_peak / 2**20:.0f} MiB"
    )
    print(
        f"header readers: peak RSS {reader_peak / 2**20:.0f} MiB (those alive at the end), "
        f"replaced {readers_replaced}"
    )
    print(f"workers replaced: {replaced}")
    if args.verbose:
        for name, (kind, message) in outcomes.items():
            print(f"{kind:12s} {name}: {message}")


if __name__ == "__main__":
    main()
