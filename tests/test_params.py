"""Job parameters are checked when the job arrives, with messages that name the key."""

from __future__ import annotations

import pytest

from terrasift.errors import FilterSyntaxError, ParameterError
from terrasift.jobs.params import (
    DEFAULT_BUFFER,
    effective_stage_params,
    grid_alignment,
    parse_cli_params,
    resolve_buffer,
    stage_params,
    validate_params,
)


def test_defaults_are_filled_and_json_ready():
    p = validate_params({})
    assert p["rotation"] == "auto" and p["features"] == "all" and p["resolution"] == 0.5
    assert p["ground"] in {"ptd", "nist"}
    assert grid_alignment(p) == 2.0


@pytest.mark.parametrize(
    "raw, message",
    [
        ({"bogus": 1}, "unknown parameter 'bogus'"),
        ({"resolution": -1}, "parameter resolution"),
        ({"block_size": 5}, "parameter block_size"),
        ({"buffer": 60, "block_size": 100}, "buffer"),
        ({"buffer": "wide"}, "parameter buffer: .*metres or 'auto'"),
        ({"buffer": -1}, "parameter buffer: Input should be greater"),
        ({"ground": "smrf"}, "parameter ground"),
        ({"rotation": "sometimes"}, "parameter rotation"),
        ({"crs": "EPSG:999999"}, "unknown CRS"),
        ({"sensor_origin": "1,2"}, "sensor_origin"),
        ({"vegetation.cell": 0}, "parameter vegetation.cell"),
        ({"vegetation.no_such_field": 1}, "stage vegetation has no field 'no_such_field'"),
        ({"resolution": 0.3, "vegetation.cell": 1}, "whole multiple of resolution"),
        ({"features": "ditch,volcano"}, "unknown filter 'volcano'"),
        ({"ground.preset": "bold"}, "parameter ground.preset"),
        ({"ground.rotation.preset": "steep"}, "unknown preset 'steep'"),
        ({"features.filters": "ditch"}, "stage features has no field 'filters'"),
    ],
)
def test_bad_values_name_the_problem(raw, message):
    with pytest.raises(ParameterError, match=message):
        validate_params(raw)


def test_user_filter_errors_carry_the_line():
    text = "// my ditch\nbeginsegment\n  bogus 3\nendsegment\n"
    with pytest.raises(FilterSyntaxError) as info:
        validate_params({"filters": {"mine": text}, "features": "mine"})
    assert info.value.line == 3


def test_stage_overrides_reach_the_stage_model():
    p = validate_params({"vegetation.tree_height": "4.5", "sensor_origin": "10,20,1.5;11,21,1.5"})
    assert p["vegetation.tree_height"] == "4.5"
    assert stage_params(p, "vegetation").tree_height == 4.5
    assert p["sensor_origin"] == [[10.0, 20.0, 1.5], [11.0, 21.0, 1.5]]


def test_none_switches_optional_stage_fields_off_and_only_those():
    p = validate_params(
        parse_cli_params(["ground.ptd.pit_depth=none", "ground.ptd.island_step=NULL"])
    )
    ptd = stage_params(p, "ground.ptd")
    assert ptd.pit_depth is None and ptd.island_step is None
    with pytest.raises(ParameterError, match="tail_fraction"):
        stage_params(validate_params({"ground.ptd.tail_fraction": "none"}), "ground.ptd")


def test_cli_pairs():
    assert parse_cli_params(["resolution=1.0", "ground.preset = conservative"]) == {
        "resolution": "1.0",
        "ground.preset": "conservative",
    }
    with pytest.raises(ParameterError, match="not key=value"):
        parse_cli_params(["resolution"])


def test_effective_stage_params_lists_the_jobs_ground_method_with_preset_and_overrides():
    params = validate_params(
        {"ground": "nist", "ground.preset": "conservative", "ground.nist.mow_tol_2": 0.25}
    )
    stages_out = effective_stage_params(params)
    assert "ground.nist" in stages_out and "ground.ptd" not in stages_out
    nist = stages_out["ground.nist"]
    assert nist["mow_tol_2"] == 0.25  # the override wins over the preset
    assert nist["ground_tol"] == 0.2  # from the conservative preset
    assert (
        nist["cell_3"] == stage_params(params, "ground.nist").cell_3
    )  # untouched defaults are listed too
    assert {"vegetation", "terrain", "ground.lowpoints"} <= set(stages_out)
    default = effective_stage_params(validate_params({}))
    assert "ground.nist" in default and "ground.ptd" not in default


def test_auto_buffer_widens_for_nist_on_sparse_data_only():
    nist = validate_params({"ground": "nist"})
    assert nist["buffer"] == "auto"
    dense, sparse = resolve_buffer(nist, 8.0), resolve_buffer(nist, 0.16)
    # 8 pts/m²: first-pass bins at their 6 m floor, 4 of them
    assert dense == (24.0, None)
    # 0.16 pts/m²: 2.5 m spacing, 25 m first-pass bins snapped to 24 m (a divisor of 240 m), 4 of them
    assert sparse[0] == pytest.approx(96.0, abs=0.5) and sparse[1] is None
    assert resolve_buffer(validate_params({"ground": "ptd"}), 0.16) == (DEFAULT_BUFFER, None)
    # cut below half the block size, with a warning that says so
    cut, warning = resolve_buffer(validate_params({"ground": "nist", "block_size": 60}), 0.16)
    assert cut < 30 and "block_size" in warning
    # a buffer in metres is taken as given
    assert resolve_buffer(validate_params({"ground": "nist", "buffer": 7}), 0.16) == (7.0, None)


def test_every_stage_input_says_what_it_is():
    from terrasift.service.ogc import parameter_inputs

    inputs = parameter_inputs()
    for key, value in inputs.items():
        if "." in key and key != "ground.preset":
            meaning = value["description"].split("): ", 1)[1]
            assert len(meaning) > 10, key


def test_ground_methods_come_from_the_registry():
    from terrasift.jobs.params import JobParams
    from terrasift.workers.registry import ground_methods

    assert ground_methods() == ["nist", "ptd"]
    schema = JobParams.model_json_schema(by_alias=True)["properties"]["ground"]
    assert schema["enum"] == ground_methods()


def test_auto_buffer_is_the_largest_halo_a_block_step_asks_for():
    from terrasift.jobs.params import block_models
    from terrasift.workers.registry import block_steps

    p = validate_params({"vegetation.cell": 4.0, "resolution": 1.0})
    models = block_models(p)
    halos = {s.id: s.halo(models, 8.0) for s in block_steps()}
    assert halos["vegetation"] == 28.0  # 7 bins of 4 m beyond the core
    assert resolve_buffer(p, 8.0) == (28.0, None)
    assert resolve_buffer(validate_params({}), 8.0) == (24.0, None)  # ground.nist: 4 × 6 m


def test_feature_names_are_deduplicated_and_bounded() -> None:
    from terrasift.jobs.params import MAX_FEATURE_NAMES

    assert validate_params({"features": "ditch, ridge,ditch,,ridge"})["features"] == "ditch,ridge"
    assert validate_params({"features": ",".join(["ditch"] * 80_000)})["features"] == "ditch"
    many = ",".join(f"f{i}" for i in range(MAX_FEATURE_NAMES + 1))
    with pytest.raises(ParameterError, match="at most 64"):
        validate_params({"features": many})
