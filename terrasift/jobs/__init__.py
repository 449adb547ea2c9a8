"""Everything that reads or writes a job directory: parameters, planning, running, finishing.

The CLI and the service drive jobs through the names exported here.
"""

from terrasift.jobs.params import validate_params
from terrasift.jobs.run import (
    check_cancel,
    clear_outputs,
    dtm_path_profile,
    inspect_inputs,
    job_path_profile,
    load_json,
    output_path,
    prepare_job,
    request_cancel,
    run_job,
)

__all__ = [
    "check_cancel",
    "clear_outputs",
    "dtm_path_profile",
    "inspect_inputs",
    "job_path_profile",
    "load_json",
    "output_path",
    "prepare_job",
    "request_cancel",
    "run_job",
    "validate_params",
]
