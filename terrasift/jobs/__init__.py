"""Everything that reads or writes a job directory: parameters, planning, running, finishing.

``params`` validates a job's parameters and builds its stage models;
``plan`` checks the inputs and lays the block grid; ``run`` runs (and
resumes) the tasks; ``block`` is the block task; ``finish`` the mosaics, COGs,
categories, features and classified copies; ``report`` the report, steep
blocks and STAC item; ``paths`` pitch and roll over a finished DTM; ``dirs``
the directory layout and the cancel marker; ``survey`` the runs of a survey
(incremental, seamless) and its one current product. The CLI and the service drive
jobs through the names exported here.
"""

from terrasift.files import load_json
from terrasift.jobs.dirs import (
    cancel_marker,
    check_cancel,
    clear_outputs,
    output_path,
    request_cancel,
)
from terrasift.jobs.params import validate_params
from terrasift.jobs.paths import dtm_path_profile, job_path_profile
from terrasift.jobs.plan import inspect_inputs, prepare_job, set_input_roots
from terrasift.jobs.run import run_job

__all__ = [
    "cancel_marker",
    "check_cancel",
    "clear_outputs",
    "dtm_path_profile",
    "inspect_inputs",
    "job_path_profile",
    "load_json",
    "output_path",
    "prepare_job",
    "set_input_roots",
    "request_cancel",
    "run_job",
    "validate_params",
]
