"""``terrasift survey DIR --server URL``: keep a server survey in step with a folder of tiles.

Made for cron or a systemd timer. A state file remembers the server's survey,
each tile's checksum as last sent, the parameters, the run in flight and the
product version downloaded. A call takes a lock (an overlapping call exits at
once), resumes a run in flight instead of submitting another, sends only the
tiles whose content changed (``PUT``; ``DELETE`` for tiles gone), starts an
incremental run (the server redoes changed tiles and their halo neighbours;
changed parameters redo all) and downloads the current product to ``--out``.
"""

from __future__ import annotations

import contextlib
import fcntl
import hashlib
import json
import os
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx

from terrasift.files import atomic_path, write_json

STATE_FILE = ".terrasift-survey.json"
LOCK_FILE = ".terrasift-survey.lock"
OUT_DIR = "terrasift-out"
FINAL = {"successful", "failed", "dismissed"}


class SurveyClientError(Exception):
    """The server refused a step; the message says which and why."""


def local_tiles(folder: Path) -> dict[str, Path]:
    return {
        p.name: p
        for p in sorted(folder.iterdir())
        if p.suffix.lower() in {".las", ".laz"} and p.is_file()
    }


def checksum(path: Path, known: dict[str, Any] | None) -> dict[str, Any]:
    """SHA-256 with size and mtime; reused when size and mtime match (a ``touch`` costs a read, not a run)."""
    st = path.stat()
    if known and known.get("size") == st.st_size and known.get("mtime_ns") == st.st_mtime_ns:
        return dict(known)
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return {"sha256": h.hexdigest(), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


@contextlib.contextmanager
def _lock(path: Path) -> Iterator[bool]:
    with open(path, "a") as fh:
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            yield False
            return
        try:
            yield True
        finally:
            fcntl.flock(fh, fcntl.LOCK_UN)


def _writable(folder: Path) -> bool:
    return os.access(folder, os.W_OK)


def run_survey(
    folder: Path,
    server: str,
    params: dict[str, Any],
    *,
    token: str | None = None,
    poll: float = 2.0,
    out: Path | None = None,
    server_path: str | None = None,
) -> int:
    """Bring the server's survey in step with ``folder``, run it, download the product.

    ``server_path``: the folder as the server sees it under its input root; tiles
    are then named by path instead of uploaded. Returns 0 on success (also when
    nothing changed), 1 when the run failed, 2 when the server refused a step,
    3 when another call holds the lock.
    """
    folder = Path(folder)
    if out is None:
        if not _writable(folder):
            print(
                f"terrasift survey: {folder} is not writable; give --out DIR for the product "
                "and the state",
                file=sys.stderr,
            )
            return 2
        out = folder / OUT_DIR
    out = Path(out)
    # state and lock beside the tiles, else beside the product (never inside it: it is replaced)
    home = folder if _writable(folder) else out.parent / f".{out.name}.terrasift"
    home.mkdir(parents=True, exist_ok=True)
    with _lock(home / LOCK_FILE) as held:
        if not held:
            print(
                f"terrasift survey: another call is working on {folder} (lock {home / LOCK_FILE})",
                file=sys.stderr,
            )
            return 3
        state_path = home / STATE_FILE
        state: dict[str, Any] = json.loads(state_path.read_text()) if state_path.exists() else {}
        base = server.rstrip("/")
        if state.get("server") != base:
            state = {"server": base}
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        with httpx.Client(
            base_url=base, headers=headers, timeout=httpx.Timeout(60.0, read=600.0)
        ) as client:
            session = _Session(client, folder, state, state_path, server_path, poll)
            try:
                return session.run(params, out)
            except SurveyClientError as exc:
                print(f"terrasift survey: {exc}", file=sys.stderr)
                return 2


class _Session:
    def __init__(
        self,
        client: httpx.Client,
        folder: Path,
        state: dict[str, Any],
        state_path: Path,
        server_path: str | None,
        poll: float,
    ):
        self.client = client
        self.folder = folder
        self.state = state
        self.state_path = state_path
        self.server_path = server_path
        self.poll = poll

    def save(self) -> None:
        write_json(self.state_path, self.state, indent=2)

    def run(self, params: dict[str, Any], out: Path) -> int:
        tiles = local_tiles(self.folder)
        if not tiles and "survey" not in self.state:
            raise SurveyClientError(f"no .las/.laz tiles in {self.folder}")
        for left in self._in_flight():  # a run a stopped call left: wait for it, never resubmit
            print(f"terrasift survey: resuming run {left}")
            self._wait(left)
        sums = {n: checksum(p, self.state.get("tiles", {}).get(n)) for n, p in tiles.items()}
        if "survey" not in self.state:
            self._create(tiles, sums, params)
        else:
            self._sync(tiles, sums)
        job_id = self._submit(params)
        status = self._wait(job_id) if job_id else "successful"
        while status == "successful":  # a survey over the server's limit runs in batches
            following = self._in_flight()
            if not following:
                break
            for left in following:
                print(f"terrasift survey: next batch {left}")
                status = self._wait(left)
        if status != "successful":
            return 1
        self._download(out)
        return 0

    def _create(self, tiles: dict[str, Path], sums: dict[str, Any], params: dict[str, Any]) -> None:
        if self.server_path is not None:
            files = [f"{self.server_path.rstrip('/')}/{n}" for n in tiles]
            resp = self.client.post("/surveys", json={"files": files, "params": params})
        else:
            with contextlib.ExitStack() as stack:
                parts = [
                    ("file", (n, stack.enter_context(open(p, "rb")), "application/octet-stream"))
                    for n, p in tiles.items()
                ]
                resp = self.client.post(
                    "/surveys", files=parts, data={"params": json.dumps(params)}
                )
        self._check(resp, 201, "creating the survey")
        self.state.update(survey=resp.json()["id"], tiles=sums)
        self.save()
        print(f"terrasift survey: survey {self.state['survey']} with {len(tiles)} tile(s)")

    def _sync(self, tiles: dict[str, Path], sums: dict[str, Any]) -> None:
        sid = self.state["survey"]
        known = self.state.setdefault("tiles", {})
        sent = 0
        for name, path in tiles.items():
            if known.get(name, {}).get("sha256") == sums[name]["sha256"]:
                known[name] = sums[name]  # same content: keep the new mtime
                continue
            if self.server_path is not None:
                href = f"{self.server_path.rstrip('/')}/{name}"
                resp = self.client.put(f"/surveys/{sid}/tiles/{name}", json={"href": href})
            else:
                with open(path, "rb") as fh:
                    resp = self.client.put(
                        f"/surveys/{sid}/tiles/{name}",
                        content=fh,
                        headers={"content-type": "application/octet-stream"},
                    )
            self._check(resp, (200, 201), f"sending {name}")
            known[name] = sums[name]
            sent += 1
            self.save()
        for name in [n for n in known if n not in tiles]:
            resp = self.client.delete(f"/surveys/{sid}/tiles/{name}")
            if resp.status_code != 404:
                self._check(resp, 200, f"removing {name}")
            del known[name]
            sent += 1
            self.save()
        self.save()
        if sent:
            print(f"terrasift survey: {sent} tile(s) sent or removed")

    def _in_flight(self) -> list[str]:
        """The recorded run, and any run of the survey the server has queued or running."""
        runs = [self.state["run"]] if self.state.get("run") else []
        if "survey" in self.state:
            resp = self.client.get(f"/surveys/{self.state['survey']}")
            self._check(resp, 200, "reading the survey")
            runs += [
                j["jobID"]
                for j in resp.json().get("jobs", [])
                if j["status"] in ("accepted", "running") and j["jobID"] not in runs
            ]
        return runs

    def _submit(self, params: dict[str, Any]) -> str | None:
        sid = self.state["survey"]
        resp = self.client.post(f"/surveys/{sid}/runs", json={"params": params})
        if resp.status_code == 409 and resp.json().get("type", "").endswith("survey-unchanged"):
            print("terrasift survey: nothing changed since the last run")
            return None
        if resp.status_code == 409 and resp.json().get("type", "").endswith("survey-busy"):
            # a run this client started but did not record (stopped right after submitting)
            active = [
                j["jobID"]
                for j in self.client.get(f"/surveys/{sid}").json().get("jobs", [])
                if j["status"] in ("accepted", "running")
            ]
            if active:
                print(f"terrasift survey: resuming run {active[-1]}")
                self.state["run"] = active[-1]
                self.save()
                self._wait(active[-1])
                return self._submit(params)
        self._check(resp, 201, "starting a run")
        job_id = str(resp.json()["jobID"])
        self.state["run"] = job_id
        self.save()
        print(f"terrasift survey: run {job_id}")
        return job_id

    def _wait(self, job_id: str) -> str:
        status: dict[str, Any] = {"status": "accepted"}
        while True:
            resp = self.client.get(f"/jobs/{job_id}")
            if resp.status_code == 404:
                status = {"status": "failed", "message": "the run is unknown to the server"}
                break
            status = resp.json()
            if status["status"] in FINAL:
                break
            print(f"\r{status['status']} {status.get('progress', 0)} %", end="", flush=True)
            time.sleep(self.poll)
        print()
        self.state.pop("run", None)
        self.save()
        if status["status"] != "successful":
            print(
                f"terrasift survey: run {job_id} {status['status']}: {status.get('message', '')}",
                file=sys.stderr,
            )
        return str(status["status"])

    def _download(self, out: Path) -> None:
        """The current product into ``out`` (replaced whole), unless that version is there."""
        sid = self.state["survey"]
        info = self.client.get(f"/surveys/{sid}").json()
        version = (info.get("product") or {}).get("version")
        if version and version == self.state.get("downloaded") and out.is_dir():
            print(f"terrasift survey: product {version} already in {out}")
            return
        results = self.client.get(f"/surveys/{sid}/results")
        self._check(results, 200, "listing the product")
        with atomic_path(out) as tmp:
            for name, ref in results.json().items():
                target = tmp / name
                target.parent.mkdir(parents=True, exist_ok=True)
                with self.client.stream("GET", ref["href"]) as r, open(target, "wb") as fh:
                    if r.status_code != 200:
                        raise SurveyClientError(f"downloading {name}: HTTP {r.status_code}")
                    for chunk in r.iter_bytes():
                        fh.write(chunk)
        self.state["downloaded"] = version
        self.save()
        print(f"terrasift survey: product in {out}")

    @staticmethod
    def _check(resp: httpx.Response, want: int | tuple[int, ...], what: str) -> None:
        ok = want if isinstance(want, tuple) else (want,)
        if resp.status_code not in ok:
            raise SurveyClientError(f"{what} refused ({resp.status_code}): {resp.text[:500]}")
