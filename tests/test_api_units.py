"""Pieces of the service on their own: byte ranges, media types, problems, names, tokens."""

from __future__ import annotations

from pathlib import Path

import pytest

from terrasift import errors
from terrasift.service.auth import load_tokens
from terrasift.service.outputs import ByteRange, RangeNotSatisfiable, media_type, parse_range
from terrasift.service.problems import PROBLEM_TYPES, problem_for
from terrasift.service.settings import Settings, is_loopback
from terrasift.service.uploads import safe_name


@pytest.mark.parametrize(
    ("header", "expected"),
    [
        ("bytes=0-99", (0, 99)),
        ("bytes=100-", (100, 999)),
        ("bytes=-10", (990, 999)),
        ("bytes=-5000", (0, 999)),  # suffix longer than the file: whole file
        ("bytes=990-5000", (990, 999)),  # last position clipped
        ("bytes= 5 - 9 ", (5, 9)),
        ("bytes=999-999", (999, 999)),
    ],
)
def test_single_ranges(header: str, expected: tuple[int, int]) -> None:
    rng = parse_range(header, 1000)
    assert (rng.first, rng.last) == expected
    assert rng.length == expected[1] - expected[0] + 1
    assert rng.content_range == f"bytes {expected[0]}-{expected[1]}/1000"


@pytest.mark.parametrize(
    "header",
    [None, "", "items=0-5", "bytes=0-1,5-9", "bytes=9-5", "bytes=a-b", "bytes=5", "bytes=-"],
)
def test_ranges_we_ignore_give_the_whole_file(header: str | None) -> None:
    assert parse_range(header, 1000) is None


@pytest.mark.parametrize(
    ("header", "size"),
    [("bytes=1000-", 1000), ("bytes=2000-3000", 1000), ("bytes=-0", 1000), ("bytes=-1", 0)],
)
def test_unsatisfiable_ranges(header: str, size: int) -> None:
    with pytest.raises(RangeNotSatisfiable):
        parse_range(header, size)


def test_byte_range_is_inclusive() -> None:
    assert ByteRange(0, 0, 1).length == 1


def test_media_types_of_the_output_contract() -> None:
    assert media_type("dtm.tif") == "image/tiff; application=geotiff; profile=cloud-optimized"
    assert media_type("classified.laz") == "application/vnd.laszip"
    assert media_type("features.geojson") == "application/geo+json"
    assert media_type("report.json") == "application/json"
    assert media_type("item.json") == "application/geo+json"
    assert media_type("whatever.bin") == "application/octet-stream"


def test_problem_table_walks_the_class_hierarchy() -> None:
    assert problem_for(errors.FilterSyntaxError("x", line=3)).status == 400
    assert problem_for(errors.FilterSyntaxError("x")).slug == "invalid-filter"
    assert problem_for(errors.ParameterError("x")).slug == "invalid-parameter"
    assert problem_for(errors.InputError("x")).status == 422
    assert problem_for(errors.TerrasiftError("x")).status == 400
    assert problem_for(KeyError("x")).status == 500


def test_ogc_problem_types_keep_ogc_uris() -> None:
    assert PROBLEM_TYPES["no-such-job"].uri.startswith(
        "http://www.opengis.net/def/exceptions/ogcapi-processes-1/1.0/"
    )
    assert PROBLEM_TYPES["result-not-ready"].uri.endswith("/result-not-ready")
    assert PROBLEM_TYPES["invalid-input"].uri == "/problems/invalid-input"


def test_upload_names_are_safe_and_unique() -> None:
    taken: set[str] = set()
    assert safe_name("../../etc/passwd", 0, taken) == "passwd"
    assert safe_name("C:\\data\\tile 1.laz", 1, taken) == "tile_1.laz"
    assert safe_name("tile 1.laz", 2, taken) == "tile_1-1.laz"
    assert safe_name("", 3, taken) == "upload-3.las"
    assert safe_name("..", 4, taken) == "upload-4.las"
    # a name longer than a file system takes (a 5000-character name was a 500): shortened
    long = safe_name("a" * 5000 + ".laz", 5, taken)
    assert long == "a" * 124 + ".laz" and len(long) == 128
    assert safe_name("a" * 5000 + ".laz", 6, taken) == "a" * 124 + "-1.laz"
    assert len(safe_name("é" * 300, 7, taken)) <= 128


def test_token_file(tmp_path: Path) -> None:
    path = tmp_path / "tokens"
    path.write_text("# token tenant\nabc123 alice\n\nxyz bob  # ops\n")
    assert load_tokens(path) == {"abc123": "alice", "xyz": "bob"}
    path.write_text("only-a-token\n")
    with pytest.raises(ValueError, match="line 1"):
        load_tokens(path)
    path.write_text('{"abc123": "alice", "xyz": "bob"}')
    assert load_tokens(path) == {"abc123": "alice", "xyz": "bob"}
    path.write_text('{"abc123": 7}')
    with pytest.raises(ValueError, match="tenant strings"):
        load_tokens(path)
    with pytest.raises(ValueError, match="missing"):
        load_tokens(tmp_path / "missing")


def test_auth_defaults(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert is_loopback("127.0.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("example.org")
    assert not Settings(host="127.0.0.1").auth_enabled
    assert Settings(host="0.0.0.0").auth_enabled
    assert Settings(host="127.0.0.1", token_file=tmp_path / "t").auth_enabled
    assert not Settings(host="0.0.0.0", auth="off").auth_enabled


def test_settings_from_environment(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("TERRASIFT_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("TERRASIFT_DASK_SCHEDULER", "tcp://sched:8786")
    monkeypatch.setenv("TERRASIFT_MAX_UPLOAD_BYTES", "1234")
    s = Settings()
    assert (
        s.data_dir == tmp_path
        and s.dask_scheduler == "tcp://sched:8786"
        and s.max_upload_bytes == 1234
    )
    assert s.db_path == tmp_path / "jobs.sqlite"
    assert Settings.model_config["env_file"] == ".env"


class _Pool:
    """A one-thread pool with the executor interface's wait_any."""

    def __init__(self) -> None:
        from concurrent.futures import ThreadPoolExecutor

        self.pool = ThreadPoolExecutor(1)

    def submit(self, fn, *args):
        return self.pool.submit(fn, *args)

    def wait_any(self, futures, timeout):
        from concurrent.futures import FIRST_COMPLETED, wait

        return wait(list(futures), timeout=timeout, return_when=FIRST_COMPLETED)[0]


def test_a_cancelled_job_stops_waiting_at_once() -> None:
    import threading
    import time

    from terrasift.errors import JobCancelled
    from terrasift.service.scheduler import JobExecutor

    inner = _Pool()
    release = threading.Event()
    ex = JobExecutor(inner)
    running = ex.submit(release.wait, 10)
    queued = ex.submit(time.sleep, 0)
    assert ex.cancel() == 1 and queued.cancelled() and not running.done()
    t0 = time.monotonic()
    # the pool alone would report the cancelled future only after the running one ends
    assert ex.wait_any([running, queued], timeout=5) == {queued}
    assert time.monotonic() - t0 < 0.5
    with pytest.raises(JobCancelled):
        ex.submit(time.sleep, 0)
    release.set()
    inner.pool.shutdown()
