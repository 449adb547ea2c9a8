"""The stage registry: a stage is an id, a validated parameter model and a function.

Ids read like a pipeline (``ground.ptd``, ``ground.nist``, ``mixed.ebw``). The
registry refuses duplicates, so two modules cannot silently claim one id.
Parameter models forbid unknown keys and carry named presets, so a job can say
``ground.preset=conservative`` and override single values on top.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Self, get_args

from pydantic import BaseModel, ConfigDict, ValidationError

from terrasift.errors import ParameterError


class StageParams(BaseModel):
    """Base of every stage's parameter model: frozen, unknown keys rejected."""

    # Attribute docstrings become the field descriptions of the published
    # process inputs (``/processes/terrain``), so they say what and why.
    model_config = ConfigDict(extra="forbid", frozen=True, use_attribute_docstrings=True)

    #: named parameter sets; ``default`` is implied by the field defaults
    presets: ClassVar[dict[str, dict[str, Any]]] = {}

    @classmethod
    def preset(cls, name: str = "default", **overrides: Any) -> Self:
        """Build the named preset with ``overrides`` on top; unknown names raise."""
        if name == "default":
            values: dict[str, Any] = {}
        elif name in cls.presets:
            values = dict(cls.presets[name])
        else:
            known = ", ".join(["default", *cls.presets])
            raise ParameterError(f"unknown preset {name!r} (known: {known})")
        values.update(overrides)
        # "none"/"null" from the command line or a form switch an optional field off.
        for key, value in values.items():
            field = cls.model_fields.get(key)
            if (
                isinstance(value, str)
                and value.lower() in ("none", "null")
                and field is not None
                and type(None) in get_args(field.annotation)
            ):
                values[key] = None
        try:
            return cls(**values)
        except ValidationError as exc:
            raise ParameterError(_describe(exc)) from None

    def halo(self, density: float) -> float:
        """Metres of data around a block's core this stage needs to decide the
        core's points like a run over the whole tile would, at ``density``
        points per m² (0: no more than the job's default buffer)."""
        return 0.0


@dataclass(frozen=True)
class Stage:
    """A registered processing stage."""

    id: str
    params: type[StageParams]
    run: Callable[..., Any]
    description: str
    role: str = ""
    """``ground`` for a ground method (a job's ``ground`` parameter names it), else empty."""


@dataclass(frozen=True)
class BlockStep:
    """A step of the block task: ``run(block, models)`` with one signature for all.

    ``halo(models, density)``: metres of data around a block's core the step
    needs to decide the core as a run over the whole tile would (0: none).
    """

    id: str
    order: float
    run: Callable[[Any, Any], None]
    halo: Callable[[Any, float], float]


_STAGES: dict[str, Stage] = {}
_STEPS: dict[str, BlockStep] = {}


def register(
    stage_id: str, params: type[StageParams], description: str, *, role: str = ""
) -> Callable:
    """Decorator registering ``fn`` under ``stage_id``; a duplicate id raises."""

    def decorate(fn: Callable[..., Any]) -> Callable[..., Any]:
        if stage_id in _STAGES:
            raise ValueError(f"stage {stage_id!r} is already registered")
        _STAGES[stage_id] = Stage(stage_id, params, fn, description, role)
        return fn

    return decorate


def _no_halo(models: Any, density: float) -> float:
    return 0.0


def block_step(
    step_id: str, *, order: float, halo: Callable[[Any, float], float] = _no_halo
) -> Callable:
    """Decorator registering ``fn(block, models)`` as a block step run at ``order``."""

    def decorate(fn: Callable[[Any, Any], None]) -> Callable[[Any, Any], None]:
        if step_id in _STEPS:
            raise ValueError(f"block step {step_id!r} is already registered")
        _STEPS[step_id] = BlockStep(step_id, order, fn, halo)
        return fn

    return decorate


def block_steps() -> list[BlockStep]:
    """The block task's steps in the order they run."""
    _load_all()
    return sorted(_STEPS.values(), key=lambda s: s.order)


def ground_methods() -> list[str]:
    """Names of the ground methods (``nist`` for ``ground.nist``), sorted."""
    return [s.id.removeprefix("ground.") for s in stages("ground.") if s.role == "ground"]


def get_stage(stage_id: str) -> Stage:
    """The stage registered as ``stage_id``; unknown ids raise ParameterError."""
    _load_all()
    try:
        return _STAGES[stage_id]
    except KeyError:
        known = ", ".join(sorted(_STAGES))
        raise ParameterError(f"unknown stage {stage_id!r} (known: {known})") from None


def stages(prefix: str = "") -> list[Stage]:
    """All registered stages whose id starts with ``prefix``, sorted by id."""
    _load_all()
    return [s for k, s in sorted(_STAGES.items()) if k.startswith(prefix)]


def _load_all() -> None:
    # Importing the stage modules registers them; kept here so callers never
    # depend on import order.
    import terrasift.workers.stages  # noqa: F401


def _describe(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "value"
        parts.append(f"{loc}: {err['msg']}")
    return "; ".join(parts)
