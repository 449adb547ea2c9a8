"""``terrasift survey DIR --server URL``: submit a folder of tiles, wait, download the outputs.

Made for cron or a systemd timer: a state file in the folder remembers each
tile's size and modification time and the job that processed it, so a re-run
submits only new or changed tiles (and tiles whose last job did not succeed).
"""

from __future__ import annotations

import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Any

import httpx

from terrasift.files import write_json

STATE_FILE = ".terrasift-survey.json"
OUT_DIR = "terrasift-out"
FINAL = {"successful", "failed", "dismissed"}


def tile_signature(path: Path) -> dict[str, int]:
    st = path.stat()
    return {"size": st.st_size, "mtime_ns": st.st_mtime_ns}


def changed_tiles(folder: Path, state: dict[str, Any]) -> list[Path]:
    """Tiles that are new, changed since their last job, or whose last job failed."""
    tiles = sorted(
        p for p in folder.iterdir() if p.suffix.lower() in {".las", ".laz"} and p.is_file()
    )
    out = []
    for p in tiles:
        seen = state.get(p.name)
        if (
            not seen
            or seen.get("signature") != tile_signature(p)
            or seen.get("status") != "successful"
        ):
            out.append(p)
    return out


def run_survey(
    folder: Path,
    server: str,
    params: dict[str, Any],
    *,
    token: str | None = None,
    poll: float = 2.0,
) -> int:
    """Submit the changed tiles of ``folder`` as one job and wait for it; 0 on success."""
    state_path = folder / STATE_FILE
    state = json.loads(state_path.read_text()) if state_path.exists() else {}
    todo = changed_tiles(folder, state)
    if not todo:
        print("terrasift survey: no new or changed tiles")
        return 0
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    base = server.rstrip("/")
    with httpx.Client(
        base_url=base, headers=headers, timeout=httpx.Timeout(60.0, read=600.0)
    ) as client:
        with contextlib.ExitStack() as stack:
            files = [
                ("file", (p.name, stack.enter_context(open(p, "rb")), "application/octet-stream"))
                for p in todo
            ]
            resp = client.post("/jobs", files=files, data={"params": json.dumps(params)})
        if resp.status_code != 201:
            print(
                f"terrasift survey: submission refused ({resp.status_code}): {resp.text}",
                file=sys.stderr,
            )
            return 2
        job_id = resp.json()["jobID"]
        print(f"terrasift survey: job {job_id} with {len(todo)} tile(s)")
        status: dict[str, Any] = resp.json()
        while status["status"] not in FINAL:
            time.sleep(poll)
            status = client.get(f"/jobs/{job_id}").json()
            print(f"\r{status['status']} {status.get('progress', 0)} %", end="", flush=True)
        print()
        if status["status"] == "successful":
            out = folder / OUT_DIR / job_id
            out.mkdir(parents=True, exist_ok=True)
            results = client.get(f"/jobs/{job_id}/results").json()
            for name in _output_names(results):
                with (
                    client.stream("GET", f"/jobs/{job_id}/outputs/{name}") as r,
                    open(out / name, "wb") as fh,
                ):
                    for chunk in r.iter_bytes():
                        fh.write(chunk)
            print(f"terrasift survey: outputs in {out}")
        else:
            print(
                f"terrasift survey: job {status['status']}: {status.get('message', '')}",
                file=sys.stderr,
            )
    for p in todo:
        state[p.name] = {"signature": tile_signature(p), "job": job_id, "status": status["status"]}
    write_json(state_path, state, indent=2)
    return 0 if status["status"] == "successful" else 1


def _output_names(results: Any) -> list[str]:
    # The results document maps output names to links; accept either a dict of
    # outputs or a list of links, and keep the last path segment.
    names: list[str] = []
    if isinstance(results, dict):
        for key, value in results.items():
            href = value.get("href") if isinstance(value, dict) else None
            names.append(href.rsplit("/", 1)[-1] if href else key)
    return names
