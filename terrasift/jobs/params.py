"""Job parameters: the contract names of DESIGN §8, validated when a job arrives.

Keys are the same in ``--param k=v``, in a job's JSON and in ``report.json``.
Besides the fixed keys, any ``<stage id>.<field>`` key (for example
``ground.nist.z_tol=0.4``) overrides one field of that stage's parameter model
and is validated against it, so a worker never meets a bad option.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping, Sequence
from typing import Annotated, Any, Literal

import pyproj
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from terrasift.errors import ParameterError
from terrasift.workers.block import BlockModels
from terrasift.workers.registry import block_steps, get_stage, ground_methods, stages

DEFAULT_GROUND = "nist"
DEFAULT_BUFFER = 20.0  # metres of halo when the ground method asks for no more
MAX_COORDINATE = 1e9  # metres: bound of a sensor origin's coordinates
MAX_FEATURE_NAMES = 64  # filters in one job; each one searches the whole mosaic twice


class JobParams(BaseModel):
    """The fixed job parameters (DESIGN §8), with limits."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True)

    ground: str = Field(
        DEFAULT_GROUND,
        description="ground method",
        json_schema_extra={"enum": [*ground_methods()]},
    )
    ground_preset: Literal["default", "conservative", "aggressive"] = Field(
        "default", alias="ground.preset", description="named parameter set of the ground method"
    )
    rotation: Literal["auto", "off", "always"] = Field(
        "auto", description="rotated classification: steep blocks only, never, or every block"
    )
    sensor_origin: list[tuple[float, float, float]] | None = Field(
        None,
        description="X,Y,Z of a ground-based scanner in the tile CRS; several scan positions as "
        "X,Y,Z;X,Y,Z (point i uses the origin numbered by its scan_dimension value)",
    )
    features: str = Field("all", description="comma list of filter names, 'all' or 'none'")
    filters: dict[str, str] | None = Field(
        None, description="user feature filters: name -> filter text in the filter language"
    )
    block_size: float = Field(200.0, ge=20.0, le=5000.0, description="block edge in metres")
    buffer: Annotated[float, Field(ge=0.0, le=500.0)] | Literal["auto"] = Field(
        "auto",
        description=f"halo around each block in metres; auto: {DEFAULT_BUFFER:g} m or what the ground "
        "method needs at the tiles' density, below half the block size",
    )
    resolution: float = Field(0.5, ge=0.05, le=100.0, description="DTM/DSM cell size in metres")
    crs: str | None = Field(
        None, description="CRS of the tiles when missing or wrong, e.g. EPSG:32632"
    )
    workers: int | None = Field(None, ge=1, le=256, description="worker processes for `process`")
    scan_dimension: str | None = Field(
        None,
        max_length=64,  # LAS names a dimension in at most 32 bytes
        description="LAS dimension holding a scan-position id (default point_source_id)",
    )

    @field_validator("sensor_origin", mode="before")
    @classmethod
    def _split_origin(cls, v: Any) -> Any:
        if isinstance(v, str):
            origins = []
            for item in v.replace(" ", "").split(";"):
                parts = [p for p in item.split(",") if p]
                if len(parts) != 3:
                    raise ValueError("sensor_origin must be X,Y,Z (several: X,Y,Z;X,Y,Z)")
                origins.append(tuple(float(p) for p in parts))
            return origins
        if (
            isinstance(v, (list, tuple))
            and len(v) == 3
            and all(isinstance(c, (int, float)) for c in v)
        ):
            return [tuple(v)]
        return v

    @field_validator("sensor_origin")
    @classmethod
    def _finite_origin(
        cls, v: list[tuple[float, float, float]] | None
    ) -> list[tuple[float, float, float]] | None:
        # a NaN or infinite origin would turn every range and angle of its points into NaN,
        # and squares of coordinates beyond ~1e154 overflow; no CRS of the Earth needs 1e9 m
        if v is not None and not all(
            math.isfinite(c) and abs(c) <= MAX_COORDINATE for origin in v for c in origin
        ):
            raise ValueError(
                f"sensor_origin coordinates must be finite numbers within ±{MAX_COORDINATE:g}"
            )
        return v

    @field_validator("ground")
    @classmethod
    def _registered_method(cls, v: str) -> str:
        # the registry's ground.* methods are the choices (JSON schema: enum)
        if v not in ground_methods():
            raise ValueError(f"Input should be {' or '.join(map(repr, ground_methods()))}")
        return v

    @field_validator("buffer", mode="before")
    @classmethod
    def _buffer_metres_or_auto(cls, v: Any) -> Any:
        if isinstance(v, str) and v.strip().lower() == "auto":
            return "auto"
        try:
            return float(v)
        except (TypeError, ValueError, OverflowError):  # an integer too large for a float
            raise ValueError(f"buffer must be metres or 'auto', not {str(v)[:40]!r}") from None

    @field_validator("crs")
    @classmethod
    def _known_crs(cls, v: str | None) -> str | None:
        if v is None:
            return v
        try:
            pyproj.CRS.from_user_input(v)
        except pyproj.exceptions.CRSError:
            raise ValueError(f"unknown CRS {v!r}") from None
        return v

    @field_validator("features")
    @classmethod
    def _feature_list(cls, v: str) -> str:
        v = v.strip()
        if not v:
            raise ValueError("features must be 'all', 'none' or a comma list of filter names")
        if v in ("all", "none"):
            return v
        # each filter searches the whole mosaic, so a repeated name repeats that work
        names = list(dict.fromkeys(n.strip() for n in v.split(",") if n.strip()))
        if len(names) > MAX_FEATURE_NAMES:
            raise ValueError(
                f"features names {len(names)} distinct filters; at most {MAX_FEATURE_NAMES}"
            )
        return ",".join(names)

    @field_validator("filters")
    @classmethod
    def _bounded_filters(cls, v: dict[str, str] | None) -> dict[str, str] | None:
        if v is not None and len(v) > MAX_FEATURE_NAMES:
            raise ValueError(f"filters holds {len(v)} filters; at most {MAX_FEATURE_NAMES}")
        return v

    @model_validator(mode="after")
    def _buffer_fits(self) -> JobParams:
        if self.buffer != "auto" and self.buffer >= self.block_size / 2:
            raise ValueError(
                f"buffer ({self.buffer}) must be less than half the block size ({self.block_size})"
            )
        if self.resolution > self.block_size / 2:
            raise ValueError("resolution must be at most half the block size")
        return self


_FIXED_KEYS = {f.alias or name for name, f in JobParams.model_fields.items()}


def validate_params(raw: Mapping[str, Any] | None) -> dict[str, Any]:
    """Check every key and value; return the normalised parameters as plain JSON.

    Fixed keys are filled with their defaults; stage overrides are kept only
    when given. Raises ParameterError naming the first bad key.
    """
    raw = dict(raw or {})
    fixed = {k: v for k, v in raw.items() if k in _FIXED_KEYS}
    rest = {k: v for k, v in raw.items() if k not in _FIXED_KEYS}
    try:
        job = JobParams.model_validate(fixed)
    except ValidationError as exc:
        msgs = []
        for err in exc.errors():
            # Union members show up in the location as tags such as "constrained-float".
            loc = (
                ".".join(str(p) for p in err["loc"] if not (isinstance(p, str) and "-" in p))
                or "params"
            )
            msgs.append(f"parameter {loc}: {err['msg']}")
        raise ParameterError("; ".join(dict.fromkeys(msgs))) from None
    out = job.model_dump(by_alias=True, mode="json")
    overrides = _stage_overrides(rest)
    # Build each stage's model once with the overrides on top, so a bad value
    # is reported now rather than inside a worker.
    for stage_id, values in overrides.items():
        stage = get_stage(stage_id)
        preset = job.ground_preset if stage_id == f"ground.{job.ground}" else "default"
        try:
            stage.params.preset(preset, **values)
        except ParameterError as exc:
            raise ParameterError(f"parameter {stage_id}.{exc}") from None
        for k, v in values.items():
            out[f"{stage_id}.{k}"] = v
    # Bin and tile sizes the job leaves out follow the resolution; given ones
    # that contradict it are refused together.
    from terrasift.workers.resolution import follow_resolution

    derived, conflicts = follow_resolution(job.resolution, out)
    if conflicts:
        raise ParameterError("; ".join(conflicts))
    out.update(derived)
    block_models(out)  # presets, the rotation's included, exist for the chosen method
    grid_alignment(out)
    from terrasift.workers.features import check_filters, resolve_filters

    # unknown names, bad filter text and lengths that do not fit the tile size fail now
    check_filters(
        resolve_filters(job.features, job.filters), float(out.get("categories.tile_size", 2.0))
    )
    return out


def effective_stage_params(params: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """The full parameter set of every stage of a job (defaults, preset, overrides), for the report.

    Of the ground methods only the job's own appears, with its preset; zeros
    that mean "automatic" stay zero (the stage resolves them per block).
    """
    methods = set(ground_methods())
    chosen = f"ground.{params['ground']}"
    out: dict[str, dict[str, Any]] = {}
    for stage in stages():
        if (
            stage.id.startswith("ground.")
            and stage.id[len("ground.") :] in methods
            and stage.id != chosen
        ):
            continue
        preset = params.get("ground.preset", "default") if stage.id == chosen else "default"
        out[stage.id] = stage_params(params, stage.id, preset).model_dump(mode="json")
    return out


def resolve_buffer(params: Mapping[str, Any], density: float) -> tuple[float, str | None]:
    """The job's halo in metres, and a warning when ``auto`` had to be cut short.

    ``auto`` is the larger of DEFAULT_BUFFER and the largest halo a block step
    asks for at ``density`` (sparse data needs wider bins, so wider halos, for
    blocks to label their cores as one run over the tile would), kept below
    half the block size.
    """
    if params["buffer"] != "auto":
        return float(params["buffer"]), None
    models = block_models(params)
    needs = {
        models.ground.id if step.id == "ground" else step.id: step.halo(models, density)
        for step in block_steps()
    }
    # the ground method names the need unless another step needs more
    method = max(needs, key=lambda k: (needs[k], k == models.ground.id))
    need = needs[method]
    res = float(params["resolution"])
    want = max(DEFAULT_BUFFER, math.ceil(need / res) * res)
    cap = (math.ceil(float(params["block_size"]) / 2 / res) - 1) * res
    if want <= cap:
        return want, None
    return cap, (
        f"buffer: {method} needs {want:.0f} m of halo at {density:.2g} points/m², cut to {cap:g} m by "
        f"block_size {params['block_size']:g}; a larger block_size labels block edges more reliably"
    )


def block_models(params: Mapping[str, Any]) -> BlockModels:
    """The block stages' parameter models for a job's validated parameters.

    Unknown presets raise ParameterError; the rotation takes the preset it
    names for the job's ground method (``RotationParams.presets``) when it has one.
    """
    stage = get_stage(f"ground.{params['ground']}")
    rotation = rotation_params(params, stage.id)
    origins = params.get("sensor_origin")
    return BlockModels(
        ground=stage,
        ground_params=stage_params(params, stage.id, params.get("ground.preset", "default")),
        rotation_ground_params=stage_params(params, stage.id, rotation.ground_preset),
        lowpoints=stage_params(params, "ground.lowpoints"),
        steep=stage_params(params, "ground.steep"),
        rotation=rotation,
        rotation_mode=params.get("rotation", "auto"),
        vegetation=stage_params(params, "vegetation"),
        terrain=stage_params(params, "terrain"),
        mixed=stage_params(params, "mixed"),
        objects=stage_params(params, "objects"),
        sensor_origin=tuple((float(x), float(y), float(z)) for x, y, z in origins)
        if origins
        else None,
        landforms=stage_params(params, "ground.landforms"),
        lowveg=stage_params(params, "ground.lowveg"),
    )


def with_ground_density(models: BlockModels, density: float | None) -> BlockModels:
    """``models`` with the job's occupied-area ``density`` given to the ground
    method when it has a ``density`` parameter left at 0 (measure per block):
    every block then derives its bins, masking and radii from one value, so
    blocks cut from one tile label alike. A density set by the job stays."""
    if not density:
        return models
    update = {}
    for name in ("ground_params", "rotation_ground_params"):
        p = getattr(models, name)
        if "density" in type(p).model_fields and not p.density:
            update[name] = p.model_copy(update={"density": float(density)})
    return dataclasses.replace(models, **update) if update else models


def with_ground_anchor(models: BlockModels, anchor: Sequence[float] | None) -> BlockModels:
    """``models`` with the job's ``anchor`` (``job_anchor``) given to a ground method that
    lays its bins from the data (``bin_anchor="data"``, ``anchor`` unset): every block
    then bins alike, and a translated job labels as the original does."""
    if anchor is None:
        return models
    update = {}
    for name in ("ground_params", "rotation_ground_params"):
        p = getattr(models, name)
        if getattr(p, "bin_anchor", None) == "data" and getattr(p, "anchor", 0) is None:
            update[name] = p.model_copy(update={"anchor": (float(anchor[0]), float(anchor[1]))})
    return dataclasses.replace(models, **update) if update else models


def job_anchor(job: Mapping[str, Any], plan: Mapping[str, Any]) -> tuple[float, float] | None:
    """The x, y that data-anchored ground bins of a job are laid from: its survey's
    anchor (fixed at the survey's first run), else the centre of its tiles' bounds."""
    survey = job.get("survey")
    if survey and survey.get("anchor"):
        return float(survey["anchor"][0]), float(survey["anchor"][1])
    tiles = plan.get("tiles") or []
    if not tiles:
        return None
    lo = [min(float(t["mins"][k]) for t in tiles) for k in (0, 1)]
    hi = [max(float(t["maxs"][k]) for t in tiles) for k in (0, 1)]
    return (lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2


def rotation_params(params: Mapping[str, Any], method: str) -> Any:
    """The rotation's parameters for ground method ``method`` (a stage id):
    its preset for that method when it has one, else its defaults; job overrides on top."""
    presets = get_stage("ground.rotation").params.presets
    return stage_params(params, "ground.rotation", method if method in presets else "default")


def grid_alignment(params: Mapping[str, Any]) -> float:
    """Metres that the job raster's corner, size and blocks are multiples of.

    The vegetation bins and the 2 m category tiles are laid on the DTM grid's
    origin, so both must be whole multiples of ``resolution``.
    """
    res = float(params["resolution"])
    cells = []
    for stage_id, field in (
        ("vegetation", "cell"),
        ("terrain", "cell"),
        ("categories", "tile_size"),
    ):
        size = float(getattr(stage_params(params, stage_id), field))
        k = size / res
        if round(k) < 1 or abs(k - round(k)) > 1e-6:
            raise ParameterError(
                f"{stage_id}.{field} ({size}) must be a whole multiple of resolution ({res})"
            )
        cells.append(int(round(k)))
    return math.lcm(*cells) * res


def _stage_overrides(rest: dict[str, Any]) -> dict[str, dict[str, Any]]:
    ids = sorted((s.id for s in stages()), key=len, reverse=True)
    grouped: dict[str, dict[str, Any]] = {}
    for key, value in rest.items():
        stage_id = next((i for i in ids if key.startswith(i + ".")), None)
        if stage_id is None:
            known = ", ".join(sorted(_FIXED_KEYS))
            raise ParameterError(
                f"unknown parameter {key!r} (known: {known}, or <stage>.<field> for a stage of: "
                f"{', '.join(sorted(ids))})"
            )
        field = key[len(stage_id) + 1 :]
        if field not in stages_params_fields(stage_id):
            raise ParameterError(
                f"unknown parameter {key!r}: stage {stage_id} has no field {field!r}"
            )
        grouped.setdefault(stage_id, {})[field] = value
    return grouped


def stages_params_fields(stage_id: str) -> set[str]:
    fields = get_stage(stage_id).params.model_fields
    return set(fields) | {f.alias for f in fields.values() if f.alias}


def stage_params(params: Mapping[str, Any], stage_id: str, preset: str = "default") -> Any:
    """The validated parameter model of ``stage_id`` for a job: preset plus overrides."""
    stage = get_stage(stage_id)
    prefix = stage_id + "."
    overrides = {
        k[len(prefix) :]: v
        for k, v in params.items()
        if k.startswith(prefix) and "." not in k[len(prefix) :]
    }
    try:
        return stage.params.preset(preset, **overrides)
    except ParameterError as exc:
        raise ParameterError(f"parameter {stage_id}: {exc}") from None


def parse_cli_params(pairs: list[str]) -> dict[str, Any]:
    """``k=v`` strings from the command line to a raw parameter mapping.

    Values stay strings except JSON-looking numbers; pydantic coerces them.
    """
    out: dict[str, Any] = {}
    for pair in pairs:
        if "=" not in pair:
            raise ParameterError(f"parameter {pair!r} is not key=value")
        k, v = pair.split("=", 1)
        out[k.strip()] = v.strip()
    return out
