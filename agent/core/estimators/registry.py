"""The relative estimators by name, and the parameters that select one (Sec. III-A).

An estimator is a class with a `name`, a `Params` model (its own parameters, subclass of `EstimatorParams`,
tagged by `name`) and the `@register` decorator. `relative.estimator` is a tagged union of the registered
`Params`: `estimator: mckf`, or `estimator: {name: raw_range, window: 100}`. The list of names and the lookup
are derived from the registered classes; the modules of this package are imported on the first lookup of a
name not registered yet, so a new estimator is one new module (docs/architecture.md, "Adding an estimator").
"""

from __future__ import annotations

import importlib
import pkgutil
from typing import Annotated, Any, Literal

from pydantic import Field, SerializeAsAny, ValidationError, field_validator, model_validator
from pydantic_core import PydanticCustomError

from agent.config import PositiveFloat, StrictModel
from agent.core.observability import ObservabilityParams

MAX_LEVER_ARM = 20.0     # m: the largest antenna lever arm component (the wire contract's bound too)
LeverArmComponent = Annotated[float, Field(ge=-MAX_LEVER_ARM, le=MAX_LEVER_ARM, allow_inf_nan=False)]


class EstimatorParams(StrictModel):
    """Base of an estimator's own parameters; `name` is the tag of the union."""

    name: str = Field(description="the estimator")


_classes: dict[str, type] = {}
_discovered = False


def register(cls: type) -> type:
    """Class decorator: make the estimator `cls` (with `name` and `Params`) selectable by its name."""
    name = cls.__dict__.get("name")
    params = cls.__dict__.get("Params")
    if not name or params is None or not issubclass(params, EstimatorParams):
        raise TypeError(f"{cls.__name__}: an estimator declares its own `name` and `Params` "
                        "(an EstimatorParams)")
    if params.model_fields["name"].default != name:
        raise TypeError(f"{cls.__name__}: {params.__name__}.name must default to {name!r}")
    if _classes.get(name, cls) is not cls:
        raise TypeError(f"estimator {name!r} is registered twice ({_classes[name].__name__}, {cls.__name__})")
    _classes[name] = cls
    return cls


def _discover() -> None:
    """Import every module of this package (once), so that each registers its estimator."""
    global _discovered
    if _discovered:
        return
    _discovered = True
    package = __name__.rpartition(".")[0]
    for module in pkgutil.iter_modules(importlib.import_module(package).__path__):
        importlib.import_module(f"{package}.{module.name}")


def estimator_names() -> tuple[str, ...]:
    """Every estimator's name, in table order (the paper's Table II, then the others by name)."""
    _discover()
    return tuple(sorted(_classes, key=lambda name: (_classes[name].table_order, name)))


def estimator_class(name: str) -> type:
    """The estimator class registered as `name`; KeyError (listing the names) if there is none."""
    if name not in _classes:
        _discover()
    if name not in _classes:
        raise KeyError(f"unknown estimator {name!r}; the estimators are {', '.join(estimator_names())}")
    return _classes[name]


def estimator_params(value: object) -> EstimatorParams:
    """`value` (a name, a mapping with a `name`, or an estimator's parameters) as that estimator's parameters.
    Raises PydanticCustomError with one line naming what is wrong and what is valid."""
    if isinstance(value, EstimatorParams):
        return value
    data = {"name": value} if isinstance(value, str) else value
    if not isinstance(data, dict) or not isinstance(data.get("name"), str):
        raise _error(f"expected an estimator's name or {{name: ..., its parameters}}; the estimators are "
                     f"{', '.join(estimator_names())}")
    try:
        model = estimator_class(data["name"]).Params
    except KeyError as error:
        raise _error(error.args[0]) from None
    try:
        return model.model_validate(data)
    except ValidationError as error:
        raise _error(_explained(model, error)) from None


def _error(message: str) -> PydanticCustomError:
    return PydanticCustomError("estimator", "{message}", {"message": message})


def _explained(model: type[EstimatorParams], error: ValidationError) -> str:
    """The first problem of `error` in one line; a key of another estimator says whose it is."""
    first = error.errors()[0]
    field = ".".join(str(part) for part in first["loc"])
    own = ", ".join(name for name in model.model_fields if name != "name")
    estimator = model.model_fields["name"].default
    if first["type"] == "extra_forbidden":
        owners = [name for name in estimator_names() if field in estimator_class(name).Params.model_fields]
        whose = f" (it is {' and '.join(owners)}'s)" if owners else ""
        return (f"{field!r} is not a parameter of {estimator}{whose}; {estimator}'s parameters: "
                f"{own or 'none'}")
    problem = first["msg"].removeprefix("Value error, ")
    if not field:
        return f"{estimator}'s parameters: {problem}"
    return f"{estimator} parameter {field!r}: {problem} (got {first.get('input')!r})"


class RelativeEstimationParams(StrictModel):
    """Inter-vessel relative position estimation, Sec. III-A."""

    # raw_range: the ranges themselves, near the Cramér-Rao bound (docs/results/estimator_comparison.md);
    # the paper's five stay selectable, and its reproductions (configs/scenarios/) name the MCKF.
    estimator: SerializeAsAny[EstimatorParams] = Field(
        "raw_range", description="the estimator and its parameters: a name, or {name: ..., its parameters}")
    initial_covariance: PositiveFloat = Field(25.0, description="P_ij,0 = value * I (Table I)")
    displacement_variance: PositiveFloat = Field(
        1e-6, description="R_delta_i per axis over one sampling period dt (Table I)"
    )
    range_variance: PositiveFloat = Field(
        2.32, description="variance of one range error, for R_z of (14); default: Table II's 0.8 N(0, 0.4) + "
                          "0.2 N(0, 10)")
    noise_ranges: Literal["predicted", "measured"] = Field(
        "predicted", description="ranges R_z of (14) is evaluated at: predicted from the estimate (the "
                                 "paper's) or measured (docs/estimation.md)")
    max_range: PositiveFloat = Field(1000.0, description="ranges beyond this are rejected as invalid")
    antenna: tuple[LeverArmComponent, LeverArmComponent] = Field(
        (0.0, 0.0), description="own UWB antenna (forward, left) from the hull's centre (m), in the share")
    observability: ObservabilityParams = ObservabilityParams()

    @model_validator(mode="before")
    @classmethod
    def _no_estimator_blocks(cls, data: Any) -> Any:
        """A block named after an estimator (the shape before the union) says where its parameters go."""
        if isinstance(data, dict):
            for key in data:
                if key not in cls.model_fields and isinstance(key, str) and key in estimator_names():
                    raise _error(f"{key!r} is an estimator: its parameters go under estimator, as "
                                 f"estimator: {{name: {key}, ...}}")
        return data

    @field_validator("estimator", mode="before")
    @classmethod
    def _estimator(cls, value: object) -> EstimatorParams:
        return estimator_params(value)

    def params_of(self, name: str) -> EstimatorParams:
        """The parameters of estimator `name`: the configured ones if it is the configured estimator, else its
        defaults (the lab runs every estimator from one configuration)."""
        if self.estimator.name == name:
            return self.estimator
        return estimator_class(name).Params()

    def selecting(self, estimator: EstimatorParams) -> RelativeEstimationParams:
        """These parameters with `estimator` (already validated) as the estimator."""
        return self.model_copy(update={"estimator": estimator})
