"""The SQLite job store: persistence, tenant filtering and guarded status changes."""

from __future__ import annotations

from pathlib import Path

import pytest

from terrasift.service.store import ACCEPTED, DISMISSED, FAILED, RUNNING, SUCCESSFUL, JobStore


@pytest.fixture
def store(tmp_path: Path) -> JobStore:
    s = JobStore(tmp_path / "jobs.sqlite")
    yield s
    s.close()


def test_job_survives_reopening(tmp_path: Path) -> None:
    s = JobStore(tmp_path / "db.sqlite")
    s.create_job("j1", "alice", {"resolution": 0.5}, ["/in/a.laz"])
    s.close()
    job = JobStore(tmp_path / "db.sqlite").get_job("j1")
    assert job is not None
    assert (job.status, job.tenant, job.params, job.inputs) == (
        ACCEPTED,
        "alice",
        {"resolution": 0.5},
        ["/in/a.laz"],
    )
    assert job.progress == 0 and job.started is None and job.created.endswith("Z")


def test_tenant_sees_only_its_jobs(store: JobStore) -> None:
    store.create_job("a1", "alice", {}, [])
    store.create_job("b1", "bob", {}, [])
    store.create_job("a2", "alice", {}, [])
    assert [j.id for j in store.list_jobs("alice")] == ["a2", "a1"]  # newest first
    assert store.get_job("b1", tenant="alice") is None
    assert store.get_job("b1", tenant="bob").id == "b1"
    assert len(store.list_jobs(None)) == 3


def test_list_filters_and_paging(store: JobStore) -> None:
    for i in range(5):
        store.create_job(f"j{i}", "t", {}, [])
    store.mark_running("j1")
    store.mark_running("j3")
    assert {j.id for j in store.list_jobs("t", statuses=[RUNNING])} == {"j1", "j3"}
    page1 = store.list_jobs("t", limit=2)
    page2 = store.list_jobs("t", limit=2, offset=2)
    assert [j.id for j in page1] == ["j4", "j3"] and [j.id for j in page2] == ["j2", "j1"]


def test_status_transitions_are_guarded(store: JobStore) -> None:
    store.create_job("j", "t", {}, [])
    assert store.mark_running("j")
    assert not store.mark_running("j")  # only from accepted
    store.set_progress("j", 40, "2 of 5 tasks done")
    job = store.get_job("j")
    assert (job.status, job.progress, job.message) == (RUNNING, 40, "2 of 5 tasks done")
    assert job.started is not None
    assert store.finish("j", SUCCESSFUL, "finished", ["dtm.tif"])
    job = store.get_job("j")
    assert (job.status, job.progress, job.outputs) == (SUCCESSFUL, 100, ["dtm.tif"])
    assert not store.finish("j", FAILED, "late report")  # a finished job stays finished
    store.set_progress("j", 10)  # ignored outside running
    assert store.get_job("j").progress == 100


def test_dismissed_job_is_never_revived(store: JobStore) -> None:
    store.create_job("j", "t", {}, [])
    store.mark_running("j")
    job = store.dismiss("j")
    assert job.status == DISMISSED and job.finished is not None
    assert not store.finish("j", SUCCESSFUL, "worker finished late", ["dtm.tif"])
    assert not store.mark_running("j")
    job = store.get_job("j")
    assert job.status == DISMISSED and job.outputs == []
    assert store.dismiss("nope") is None


def test_requeue_interrupted_jobs(store: JobStore) -> None:
    for name in ("run", "queued", "done"):
        store.create_job(name, "t", {}, [])
    store.mark_running("run")
    store.mark_running("done")
    store.finish("done", SUCCESSFUL, "ok")
    assert store.requeue_interrupted() == ["run"]
    assert [j.id for j in store.jobs_with_status(ACCEPTED)] == ["run", "queued"]  # oldest first
    assert store.get_job("run").message == "resumed after a service restart"
    store.mark_running("run")
    assert store.get_job("run").status == RUNNING


def test_progress_is_clamped(store: JobStore) -> None:
    store.create_job("j", "t", {}, [])
    store.mark_running("j")
    store.set_progress("j", 250)
    assert store.get_job("j").progress == 100
    store.set_progress("j", -3)
    assert store.get_job("j").progress == 0


def test_surveys(store: JobStore) -> None:
    store.create_survey("s", "alice", ["/a.laz", "/b.laz"], {"resolution": 1.0})
    assert store.get_survey("s", tenant="bob") is None
    survey = store.get_survey("s", tenant="alice")
    assert survey.files == ["/a.laz", "/b.laz"] and survey.params == {"resolution": 1.0}
    store.create_job("run1", "alice", {}, survey.files, survey_id="s")
    assert [j.id for j in store.survey_jobs("s")] == ["run1"]


def _records(tmp_path: Path) -> tuple[JobStore, Path]:
    jobs = tmp_path / "jobs"
    store = JobStore(tmp_path / "jobs.sqlite", jobs, tmp_path / "surveys")
    for i, status in enumerate(["successful", "running", "dismissed"]):
        (jobs / f"j{i}").mkdir(parents=True)
        store.create_job(f"j{i}", "alice", {"resolution": 1.0}, [f"/in/{i}.las"])
        if status != "dismissed":
            store.mark_running(f"j{i}")
        if status == "successful":
            store.finish(f"j{i}", "successful", "finished", ["dtm.tif"])
        elif status == "dismissed":
            store.dismiss(f"j{i}")
    store.create_survey("s1", "alice", ["/in/0.las"], {})
    return store, jobs


def test_a_deleted_store_file_is_restored_from_the_open_connection(tmp_path: Path) -> None:
    store, _ = _records(tmp_path)
    store.set_progress("j1", 40)  # progress is not in the records: it must survive anyway
    (tmp_path / "jobs.sqlite").unlink()
    assert store.check(thorough=False) == "restored"
    store.close()
    again = JobStore(tmp_path / "jobs.sqlite")
    assert again.get_job("j1").progress == 40
    assert [again.get_job(f"j{i}").status for i in range(3)] == [
        "successful",
        "running",
        "dismissed",
    ]


def test_a_lost_or_corrupt_store_is_rebuilt_from_the_job_directories(tmp_path: Path) -> None:
    store, jobs = _records(tmp_path)
    store.close()
    db = tmp_path / "jobs.sqlite"
    db.write_bytes(b"this is not a database" * 100)
    for suffix in ("-wal", "-shm"):
        (tmp_path / f"jobs.sqlite{suffix}").unlink(missing_ok=True)
    rebuilt = JobStore(db, jobs, tmp_path / "surveys")
    assert rebuilt.recovered and "corrupt" in rebuilt.recovered
    assert list(tmp_path.glob("jobs.sqlite.corrupt-*"))
    got = {j.id: j for j in rebuilt.list_jobs("alice")}
    # a job that was running is queued again; the others keep their state and outputs
    assert {k: j.status for k, j in got.items()} == {
        "j0": "successful",
        "j1": "accepted",
        "j2": "dismissed",
    }
    assert got["j0"].outputs == ["dtm.tif"] and got["j0"].params == {"resolution": 1.0}
    assert rebuilt.get_survey("s1", "alice").files == ["/in/0.las"]
    assert rebuilt._db.execute("PRAGMA journal_mode").fetchone()[0] == "wal"


def test_stage_and_warnings_live_in_the_row_and_its_record(tmp_path: Path) -> None:
    jobs = tmp_path / "jobs"
    (jobs / "j").mkdir(parents=True)
    store = JobStore(tmp_path / "jobs.sqlite", jobs)
    store.create_job("j", "t", {}, [])
    store.mark_running("j")
    store.set_progress("j", 30, "ground 3 of 9", stage="ground", warnings=["a.laz: 1 point short"])
    store.set_progress("j", 40, "ground 4 of 9")  # stage and warnings kept
    job = store.get_job("j")
    assert (job.progress, job.stage, job.warnings) == (40, "ground", ["a.laz: 1 point short"])
    assert store.queue_position(job) is None
    store.close()
    # the record follows a change of stage: a store rebuilt from it keeps both
    (tmp_path / "jobs.sqlite").unlink()
    again = JobStore(tmp_path / "jobs.sqlite", jobs)
    job = again.get_job("j")
    assert (job.status, job.stage, job.warnings) == (ACCEPTED, "ground", ["a.laz: 1 point short"])
    again.close()


def test_a_store_without_the_stage_columns_is_upgraded(tmp_path: Path) -> None:
    import sqlite3

    db = sqlite3.connect(tmp_path / "old.sqlite")
    db.execute(
        "CREATE TABLE jobs (id TEXT PRIMARY KEY, tenant TEXT NOT NULL, process_id TEXT NOT NULL,"
        " status TEXT NOT NULL, message TEXT, progress INTEGER NOT NULL DEFAULT 0,"
        " params TEXT NOT NULL, inputs TEXT NOT NULL, outputs TEXT NOT NULL DEFAULT '[]',"
        " survey_id TEXT, created TEXT NOT NULL, started TEXT, finished TEXT, updated TEXT NOT NULL)"
    )
    db.execute(
        "INSERT INTO jobs (id, tenant, process_id, status, params, inputs, created, updated)"
        " VALUES ('old', 't', 'terrain', 'accepted', '{}', '[]', '2026-01-01', '2026-01-01')"
    )
    db.commit()
    db.close()
    store = JobStore(tmp_path / "old.sqlite")
    store.create_job("new", "t", {}, [])
    old, new = store.get_job("old"), store.get_job("new")
    assert (old.stage, old.warnings) == (None, [])
    assert store.queue_position(old) == 0 and store.queue_position(new) == 1
    store.close()


def test_reads_do_not_wait_behind_a_check_waiting_for_a_commit(store: JobStore) -> None:
    """A status read runs on the event loop: a health check queued behind a slow commit
    (a WAL checkpoint on a busy disk) must not hold the readers meanwhile."""
    import threading
    import time

    store.create_job("j", "t", {}, [])
    store._lock.acquire()  # a commit that takes a while
    release = threading.Timer(1.0, store._lock.release)
    release.start()
    check = threading.Thread(target=store.check)
    check.start()
    time.sleep(0.2)  # the check is now waiting for the writer
    t = time.monotonic()
    assert store.get_job("j") is not None
    assert time.monotonic() - t < 0.5
    release.join()
    check.join(10)
    assert not check.is_alive()


def test_status_reads_come_from_the_rows_writes_leave_in_memory(store: JobStore) -> None:
    store.create_job("j1", "alice", {"resolution": 0.5}, ["/in/a.laz"])
    queries: list[str] = []
    store._rdb.set_trace_callback(queries.append)
    for _ in range(50):
        assert store.get_job("j1", tenant="alice").status == ACCEPTED
    assert store.get_job("j1", tenant="bob") is None  # the tenant is still checked
    store.mark_running("j1")
    store.set_progress("j1", 40, "tiles", stage="ground", warnings=["w"])
    job = store.get_job("j1")
    assert (job.status, job.progress, job.message, job.stage, job.warnings) == (
        RUNNING,
        40,
        "tiles",
        "ground",
        ["w"],
    )
    job.params["resolution"] = 9  # a caller's copy: the kept row is not changed
    assert store.get_job("j1").params == {"resolution": 0.5}
    store.finish("j1", SUCCESSFUL, "done", ["dtm.tif"])
    assert store.get_job("j1").outputs == ["dtm.tif"]
    assert store.dismiss("j1").status == DISMISSED
    assert queries == []  # not one SELECT on the reading connection
    # a row nobody wrote through this store is read once, then kept
    store._db.execute(
        "INSERT INTO jobs (id, tenant, process_id, status, params, inputs, created, updated)"
        " VALUES ('j2', 'bob', 'terrain', 'accepted', '{}', '[]', 'x', 'x')"
    )
    assert store.get_job("j2").tenant == "bob" and store.get_job("j2").status == ACCEPTED
    assert len(queries) == 1
    store.requeue_interrupted()  # changes rows in bulk: every kept row is dropped
    assert store.get_job("j2").status == ACCEPTED and len(queries) == 2
