"""Scenarios: one typed YAML file per experiment of the paper, with variants for its sweeps.

A file holds a `base` scenario and optional `variants`, each a partial scenario deep-merged onto the base
(Table II: one variant per estimator; Table III: per noise model; Table IV: per fleet size and radius).
Every merged variant is validated like a whole scenario, so a typo in a variant is reported with its path.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import yaml
from pydantic import Field, model_validator

from agent.params import (
    AgentParams, ConfigError, NonNegativeFloat, PositiveFloat, StrictModel, parse_mapping, read_yaml,
)
from sim_bridge.world import WorldConfig


class InitialEstimates(StrictModel):
    """How the vessels' first estimates are drawn (Sec. VI: p^_ij,0 ~ N(p_ij,0, P_ij,0), likewise x_io)."""

    neighbour_covariance: PositiveFloat = Field(0.04, description="P_ij,0 = value * I (Table II: 0.04)")
    target_covariance: PositiveFloat = Field(1.0, description="P_io,0 = value * I (Table II: I)")


class PaperRow(StrictModel):
    """The paper's printed figures for this scenario, shown beside ours."""

    table: str = ""
    mean_e_ij: NonNegativeFloat | None = None
    mean_e_io: NonNegativeFloat | None = None
    mean_e_c: NonNegativeFloat | None = None
    settling_time: NonNegativeFloat | None = None
    run_time_ms: NonNegativeFloat | None = None


class Scenario(StrictModel):
    name: str = ""
    duration: PositiveFloat = Field(60.0, description="simulated seconds")
    runs: int = Field(1, ge=1, le=10_000, description="Monte Carlo runs")
    seed: int = Field(0, ge=0)
    filter_range_variance: Literal["from_noise", "configured"] = Field(
        "from_noise",
        description="'from_noise': the filters get the variance of the world's range noise model",
    )
    world: WorldConfig
    agent: AgentParams = AgentParams()
    initial: InitialEstimates = InitialEstimates()
    paper: PaperRow = PaperRow()

    @model_validator(mode="after")
    def _same_period(self) -> Scenario:
        if abs(self.world.dt - self.agent.dt) > 1e-12:
            raise ValueError(f"world.dt ({self.world.dt}) and agent.dt ({self.agent.dt}) must agree")
        return self

    def agent_params(self) -> AgentParams:
        """The agent parameters the vessels run with, R_z's range variance filled in from the world."""
        if self.filter_range_variance == "configured":
            return self.agent
        data = self.agent.model_dump()
        data["relative"]["range_variance"] = self.world.range_noise.total_variance
        return AgentParams.model_validate(data)


class ScenarioFile(StrictModel):
    name: str
    description: str = ""
    base: dict
    variants: dict[str, dict] = Field(default_factory=dict)


def deep_merge(base: dict, override: dict) -> dict:
    """`override` onto `base`, recursing into mappings; lists and values replace, and so does a tagged
    mapping whose `kind` changes (a log-normal noise model shares no field with a mixture)."""
    merged = dict(base)
    for key, value in override.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict) and value.get(
                "kind", merged[key].get("kind")) == merged[key].get("kind"):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def load_scenarios(path: str | Path) -> tuple[ScenarioFile, dict[str, Scenario]]:
    """Every scenario of a file: the base alone when there are no variants, else one per variant."""
    data = read_yaml(path)
    spec = parse_mapping(ScenarioFile, data, str(path))
    variants = spec.variants or {spec.name: {}}
    scenarios = {}
    for name, override in variants.items():
        merged = deep_merge(spec.base, override)
        merged["name"] = name if spec.variants else spec.name
        where = f"{path} (variant '{name}')" if spec.variants else str(path)
        scenarios[name] = parse_mapping(Scenario, merged, where)
    return spec, scenarios


def with_duration(path: str | Path, folder: str | Path, duration: float) -> Path:
    """A copy of scenario file `path` in `folder` whose base lasts `duration` seconds (shorter test and
    benchmark runs of a shipped scenario)."""
    data = read_yaml(path)
    data["base"]["duration"] = duration
    copy = Path(folder) / Path(path).name
    copy.write_text(yaml.safe_dump(data))
    return copy


def select_scenario(path: str | Path, variant: str | None = None) -> tuple[str, Scenario]:
    """(name, scenario) of one variant of a file, the first when `variant` is None; a clear error otherwise."""
    _, variants = load_scenarios(path)
    if variant is not None and variant not in variants:
        raise ConfigError(f"{path}: no variant {variant!r}; it has {', '.join(variants)}")
    name = variant or next(iter(variants))
    return name, variants[name]
