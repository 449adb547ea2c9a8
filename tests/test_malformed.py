"""Malformed tiles through the real app and process pool, under a worker memory limit:
every file is refused with a 4xx or its job ends (failed with a message, or successful with
a DTM); never a 5xx, never a stuck job. Then kill -9 of a worker mid-job, and a good job."""

from __future__ import annotations

import os
import signal
import struct
import time
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from terrasift.errors import InputError, ParameterError
from terrasift.service.app import create_app
from terrasift.service.settings import Settings
from terrasift.synthetic.malformed import corpus, laszip_items_at, run_through_app, write_pair
from terrasift.tiling.lasfile import iter_chunks, read_tile_info
from terrasift.workers.pool import TaskOutOfMemory, WorkerLost, WorkerPool

PARAMS = {"block_size": 40, "buffer": 4, "resolution": 1.0, "features": "none"}
MEMORY_LIMIT = 1024**3


@pytest.fixture(scope="module")
def good(tmp_path_factory: pytest.TempPathFactory) -> tuple[bytes, bytes]:
    return write_pair(tmp_path_factory.mktemp("malformed"))


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    data = tmp_path_factory.mktemp("malformed-app") / "data"
    settings = Settings(
        _env_file=None,
        data_dir=data,
        workers=2,
        worker_memory=MEMORY_LIMIT,
        max_concurrent_jobs=4,
        task_seconds=60,
    )
    with TestClient(create_app(settings), raise_server_exceptions=False) as c:
        yield c


def test_malformed_corpus_through_the_app(client: TestClient, good: tuple[bytes, bytes]) -> None:
    cases = list(corpus(*good))
    assert len(cases) > 150
    outcomes = run_through_app(client, cases, PARAMS)
    counts = Counter(kind for kind, _ in outcomes.values())
    print("malformed corpus outcomes:", dict(counts))
    assert counts["http-5xx"] == 0 and counts["stuck"] == 0, outcomes
    assert counts["refused-4xx"] > 100
    for name, (kind, message) in outcomes.items():
        assert kind in ("refused-4xx", "failed", "successful"), (name, kind)
        if kind != "successful":
            # the message names the file (or the task reading it), never a bare "internal error"
            assert "t.la" in message, (name, message)
            assert "Traceback" not in message
    # the cases the issue found accepted or fatal are refused before any job runs
    for name in (
        "laz-chunk-count-2147483647",
        "laz-chunk-count-4294967295",
        "las-vlrs-0xffffffff",
        "laz-vlrs-0xffffffff",
        "laz-x_offset=1e+300",
        "laz-z_offset=nan",
        "las-point-count-1680-of-3360",
        "laz-laszip-items-0",
        "laz-laszip-item-sizes-0",
    ):
        assert outcomes[name][0] == "refused-4xx", (name, outcomes[name])
    for name in ("laz-payload-zeroed-0", "laz-payload-random-2", "las-point-outside-bounds"):
        assert outcomes[name][0] == "failed", (name, outcomes[name])
    # a count one point short of the data goes on, saying so in the status (and the report)
    kind, message = outcomes["laz-point-count-3359-of-3360"]
    assert kind == "successful" and "counts per return add up to 3360" in message, message
    pool = client.app.state.svc.scheduler.executor.pool
    print(f"peak worker RSS {pool.peak_rss / 2**20:.0f} MiB, workers replaced {pool.replaced}")
    assert pool.peak_rss < MEMORY_LIMIT


def test_kill_9_of_a_worker_then_jobs_succeed(
    client: TestClient, good: tuple[bytes, bytes]
) -> None:
    from terrasift.synthetic.terrain import make_scene, write_las

    scheduler = client.app.state.svc.scheduler
    tile = write_las(
        make_scene(size=80, density=6, seed=2),
        scheduler.jobs_dir.parent / "bigger.laz",
        crs="EPSG:32632",
    ).read_bytes()
    outcomes = {}
    for attempt in range(2):
        r = client.post(
            "/jobs",
            files=[("file", ("t.laz", tile))],
            data={
                "params": '{"block_size": 20, "buffer": 2, "resolution": 1.0, "features": "none"}'
            },
        )
        job_id = r.json()["jobID"]
        killed = None
        end = time.monotonic() + 60
        while time.monotonic() < end:
            pool = getattr(scheduler.executor, "pool", None)
            busy = pool.busy_pids() if pool else []
            if attempt == 0 and busy and killed is None:
                killed = busy[0]
                os.kill(killed, signal.SIGKILL)
            info = client.get(f"/jobs/{job_id}").json()
            if info["status"] not in ("accepted", "running"):
                break
            time.sleep(0.02)
        outcomes[attempt] = (info["status"], info.get("message"), killed)
    assert outcomes[0][2] is not None  # a worker was killed mid-job
    assert outcomes[0][0] == "successful", outcomes  # its task ran again on a replacement
    assert outcomes[1][0] == "successful", outcomes
    assert killed not in scheduler.executor.pool.worker_pids()


def _read_all(path: str) -> int:
    """Every point of the tile, as a shard task reads it (runs in a worker)."""
    return sum(len(c.xyz) for c in iter_chunks(path, 100_000))


@pytest.fixture(scope="module")
def reader_pool() -> Iterator[WorkerPool]:
    pool = WorkerPool(1, memory_limit=MEMORY_LIMIT)
    yield pool
    pool.shutdown(kill=True)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    which=st.sampled_from(["las", "laz"]),
    edits=st.lists(
        st.tuples(st.integers(0, 600), st.binary(min_size=1, max_size=8)), min_size=1, max_size=4
    ),
)
def test_header_fuzz_is_an_input_error_or_a_readable_tile(
    tmp_path_factory: pytest.TempPathFactory,
    good: tuple[bytes, bytes],
    reader_pool: WorkerPool,
    which: str,
    edits,
) -> None:
    """Random bytes anywhere in the header and VLRs: the header check (which runs in the API
    process) refuses cleanly or passes; reading the points then, in a disposable worker as the
    service does, gives every point, a clean refusal, or a lost worker (a decoder that aborts)
    that the pool replaces."""
    data = bytearray(good[0] if which == "las" else good[1])
    for at, raw in edits:
        data[at : at + len(raw)] = raw
    path = tmp_path_factory.getbasetemp() / f"fuzz.{which}"
    path.write_bytes(bytes(data))
    try:
        info = read_tile_info(path)
    except InputError:
        return
    assert info.point_count > 0
    try:
        read = reader_pool.submit(_read_all, str(path), timeout=30).result(timeout=120)
    except (InputError, WorkerLost, TaskOutOfMemory):
        return
    assert read == info.point_count


def test_a_decoder_panic_is_an_input_error_naming_the_file(
    tmp_path: Path, good: tuple[bytes, bytes], reader_pool: WorkerPool
) -> None:
    """A laszip record listing no items makes lazrs panic (a division by the point size,
    0): pyo3 raises PanicException, a BaseException that does not pickle. The header check
    refuses the file; a task reading it anyway (as a shard task does, without the header
    check) fails with an input error naming the file, and its worker lives on."""
    data = bytearray(good[1])
    struct.pack_into("<H", data, laszip_items_at(good[1]) - 2, 0)
    path = tmp_path / "panics.laz"
    path.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"panics\.laz: the laszip VLR lists 0 compressed items"):
        read_tile_info(path)
    assert reader_pool.submit(len, "ready").result(timeout=120) == 5
    before = reader_pool.worker_pids()
    with pytest.raises(InputError, match=r"panics\.laz: .*decoder crashed \(PanicException"):
        reader_pool.submit(_read_all, str(path), timeout=30).result(timeout=120)
    assert reader_pool.worker_pids() == before  # an error, not a lost worker
    with pytest.raises(InputError, match=r"panics\.laz: .*decoder crashed \(PanicException"):
        _read_all(str(path))  # in this process too


def test_every_header_field_flipped(
    tmp_path_factory: pytest.TempPathFactory, reader_pool: WorkerPool
) -> None:
    """Every field of the LAS 1.2 and 1.4 headers (LAS and LAZ) with all its bits flipped:
    the header check refuses it naming the file, or every point it declares is read (in a
    disposable worker, as the service reads them), or reading fails naming the file."""
    from terrasift.synthetic.malformed import HEADER_12, HEADER_14, full_corpus

    directory = tmp_path_factory.mktemp("flipped")
    cases = [case for case in full_corpus(directory) if case[0].endswith("-flipped")]
    assert len(cases) == 2 * 2 * len(HEADER_12) + 2 * len(HEADER_14)
    outcomes: Counter[str] = Counter()
    for name, suffix, data in cases:
        path = directory / f"flip.{suffix}"
        path.write_bytes(data)
        try:
            info = read_tile_info(path)
        except InputError as exc:
            assert str(exc).startswith("flip."), (name, str(exc))
            outcomes["refused"] += 1
            continue
        try:
            read = reader_pool.submit(_read_all, str(path), timeout=30).result(timeout=120)
        except InputError as exc:
            assert "flip." in str(exc), (name, str(exc))
            outcomes["unreadable"] += 1
            continue
        assert read == info.point_count, name
        outcomes["read"] += 1
    print("every header field flipped:", dict(outcomes))
    assert outcomes["refused"] > 50 and outcomes["read"] > 20


def test_hostile_parameter_sets_are_refused_or_valid() -> None:
    """Every hostile parameter set is refused with a parameter error at submission, or is
    a valid set whose block models build (no other exception reaches the request)."""
    from terrasift.jobs.params import JobParams, block_models, validate_params
    from terrasift.service.problems import Problem
    from terrasift.service.submit import parse_params
    from terrasift.synthetic.malformed import hostile_params

    cases = hostile_params(JobParams)
    assert len(cases) > 900
    accepted = []
    for name, text in cases:
        try:
            params = validate_params(parse_params(text))
        except (ParameterError, Problem):
            continue
        block_models(params)
        accepted.append(name)
    # bad values for a fixed parameter that pass are ones it can take (null, true as 1, 0)
    assert "sensor-origin-nan" not in accepted and "sensor-origin-huge" not in accepted
    assert (
        "features-80000-names" not in accepted and "ground.ptd.min_spacing=above-50" not in accepted
    )
    assert "scan_dimension=bad-17" not in accepted  # a 100 000-character name
    assert len(accepted) < 60, accepted


@pytest.mark.parametrize(
    "case", ["ground.ptd-all-smallest", "ground.ptd-all-largest", "features-80000-same-name"]
)
def test_extreme_parameters_end_a_job_with_a_reason(
    client: TestClient, good: tuple[bytes, bytes], case: str
) -> None:
    """Parameter sets at the edges of their bounds (cells of 5e-324 m, a PTD spacing the
    low-point test cannot take) ended jobs with "internal error": now a job that ends
    saying why, or succeeds."""
    from terrasift.jobs.params import JobParams
    from terrasift.service.scheduler import GENERIC_FAILURE
    from terrasift.synthetic.malformed import hostile_params

    text = dict(hostile_params(JobParams))[case]
    outcome = run_through_app(client, [(case, "laz", good[1], text)], PARAMS)[case]
    assert outcome[0] in ("refused-4xx", "failed", "successful"), outcome
    assert outcome[1] != GENERIC_FAILURE, outcome


def test_header_text_that_is_not_ascii_is_copied_as_it_is(
    tmp_path: Path, good: tuple[bytes, bytes]
) -> None:
    """A system identifier or generating software with bytes above 0x7F (every bit of the
    field flipped) passes the header check; the classified copy failed the job on it with
    an internal error (laspy's strict ASCII check when writing). Now the copy keeps the
    bytes as the file holds them."""
    import laspy
    import numpy as np

    from terrasift.tiling.classified import write_classified_copy

    for field, at in (("system_identifier", 26), ("generating_software", 58)):
        data = bytearray(good[1])
        data[at : at + 32] = bytes(b ^ 0xFF for b in data[at : at + 32])
        src = tmp_path / f"{field}.laz"
        src.write_bytes(bytes(data))
        info = read_tile_info(src)
        out = write_classified_copy(
            src, tmp_path / f"{field}-out.laz", np.full(info.point_count, 2, np.uint8)
        )
        with laspy.open(out) as reader:
            assert reader.header.point_count == info.point_count
        assert out.read_bytes()[at : at + 32] == bytes(data[at : at + 32])
