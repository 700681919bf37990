"""Scenarios: one typed YAML file per experiment of the paper, with variants for its sweeps.

A file holds a `base` scenario and optional `variants`, each a partial scenario deep-merged onto the base
(Table II: one variant per estimator; Table III: per noise model; Table IV: per fleet size and radius).
Every merged variant is validated like a whole scenario, so a typo in a variant is reported with its path.
`base.agent` holds the agent's parameters inline or names an AgentParams file (relative to the scenario's
folder, the shape of configs/agent.yaml); the variants' `agent` sections go over it.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
import yaml
from pydantic import Field, model_validator

from agent.config import (
    ConfigError,
    InlineOrFile,
    NonNegativeFloat,
    PositiveFloat,
    StrictModel,
    deep_merge,
    named_file,
    parse_mapping,
    read_yaml,
    updated,
)
from agent.core.build import InitialEstimates
from agent.core.params import AgentParams
from sim_bridge.noise import FILTER_NOISE_DESCRIPTION, FilterNoise, assumed_relative
from sim_bridge.world import Truth, WorldConfig


class InitialUncertainty(StrictModel):
    """How the vessels' first estimates are drawn (Sec. VI: p^_ij,0 ~ N(p_ij,0, P_ij,0), likewise x_io),
    and which vessels start cold, knowing nothing, as a fleet deployed without surveyed positions."""

    neighbour_variance: PositiveFloat = Field(0.04, description="P_ij,0 = value * I (Table II: 0.04)")
    target_variance: PositiveFloat = Field(1.0, description="P_io,0 = value * I (Table II: I)")
    # A cold vessel takes the target from its first bearing and its neighbours from the ranges and shares.
    cold: Literal["all"] | list[str] = Field(
        default_factory=list,
        description="vessels that start with no estimates: 'all', or a list of ids")


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
    filter_noise: FilterNoise = Field("world", description=FILTER_NOISE_DESCRIPTION)
    world: WorldConfig
    agent: Annotated[AgentParams, InlineOrFile(AgentParams)] = AgentParams()
    initial: InitialUncertainty = InitialUncertainty()
    paper: PaperRow = PaperRow()

    @model_validator(mode="after")
    def _same_period(self) -> Scenario:
        if abs(self.world.dt - self.agent.dt) > 1e-12:
            raise ValueError(f"world.dt ({self.world.dt}) and agent.dt ({self.agent.dt}) must agree")
        return self

    @model_validator(mode="after")
    def _cold_vessels_exist(self) -> Scenario:
        if self.initial.cold != "all":
            unknown = set(self.initial.cold) - {v.id for v in self.world.vessels}
            if unknown:
                raise ValueError(f"initial.cold names vessels the world does not have: {sorted(unknown)}")
        return self

    def starts_cold(self, vessel: str) -> bool:
        return self.initial.cold == "all" or vessel in self.initial.cold

    def agent_params(self) -> AgentParams:
        """The agent parameters the vessels run with: the filters assume the world's range noise unless
        `filter_noise` is 'configured' (the raw-range density only where the raw-range estimator runs)."""
        if self.filter_noise == "configured":
            return self.agent
        return updated(self.agent, relative=assumed_relative(self.agent.relative, self.world.range_noise))


class ScenarioFile(StrictModel):
    name: str
    description: str = ""
    base: dict
    variants: dict[str, dict] = Field(default_factory=dict)


def load_scenarios(path: str | Path) -> tuple[ScenarioFile, dict[str, Scenario]]:
    """Every scenario of a file: the base alone when there are no variants, else one per variant."""
    data = read_yaml(path)
    spec = parse_mapping(ScenarioFile, data, str(path))
    base = spec.base
    if isinstance(base.get("agent"), str):   # an AgentParams file: what it names, for the variants to go over
        named = named_file(base["agent"], Path(path).parent)
        given = read_yaml(named)
        parse_mapping(AgentParams, given, str(named))   # a fault in it is told in its own name
        base = {**base, "agent": given or {}}
    variants = spec.variants or {spec.name: {}}
    scenarios = {}
    for name, override in variants.items():
        merged = deep_merge(base, override)
        merged["name"] = name if spec.variants else spec.name
        where = f"{path} (variant '{name}')" if spec.variants else str(path)
        scenarios[name] = parse_mapping(Scenario, merged, where, Path(path).parent)
    return spec, scenarios


def with_duration(path: str | Path, folder: str | Path, duration: float) -> Path:
    """A copy of scenario file `path` in `folder` whose base lasts `duration` seconds (shorter test and
    benchmark runs of a shipped scenario)."""
    data = read_yaml(path)
    data["base"]["duration"] = duration
    if isinstance(data["base"].get("agent"), str):   # the parameters file stays where it is
        data["base"]["agent"] = str(named_file(data["base"]["agent"], Path(path).parent).resolve())
    copy = Path(folder) / Path(path).name
    copy.write_text(yaml.safe_dump(data))
    return copy


# Where the shipped scenarios are: configs/scenarios of the working directory if it has one (the repository's
# root, as the README runs things), else of the repository this package was installed from (editable).
_SHIPPED = (Path("configs/scenarios"), Path(__file__).resolve().parents[1] / "configs" / "scenarios")
SCENARIOS_DIR = next((folder for folder in _SHIPPED if folder.is_dir()), _SHIPPED[0])


def scenario_files(directory: Path = SCENARIOS_DIR) -> list[Path]:
    return sorted(Path(directory).glob("*.yaml"))


def scenario_file(name: str, directory: Path = SCENARIOS_DIR) -> Path:
    """The scenario file `name` stands for: a path, or the name of a file in `directory` (`table2_estimators`
    for configs/scenarios/table2_estimators.yaml); ConfigError that lists the known names otherwise."""
    path = Path(name)
    if path.is_file():
        return path
    candidate = Path(directory) / f"{name}.yaml"
    if candidate.is_file():
        return candidate
    known = ", ".join(p.stem for p in scenario_files(directory)) or "none"
    raise ConfigError(f"unknown scenario {name!r}: no such file and no {candidate}; known in {directory}: {known}")


def default_variant(path: str | Path) -> str:
    """The variant a user gets when naming none: the first that runs the product's default estimator, else
    the file's first (a file without variants: its one scenario)."""
    _, variants = load_scenarios(path)
    product = AgentParams().relative.estimator.name
    return next((name for name, scenario in variants.items()
                 if scenario.agent.relative.estimator.name == product), next(iter(variants)))


def select_scenario(path: str | Path, variant: str | None = None) -> tuple[str, Scenario]:
    """(name, scenario) of one variant of a file, the first when `variant` is None; a clear error otherwise."""
    _, variants = load_scenarios(path)
    if variant is not None and variant not in variants:
        raise ConfigError(f"{path}: no variant {variant!r}; it has {', '.join(variants)}")
    name = variant or next(iter(variants))
    return name, variants[name]


def initial_estimates(scenario: Scenario, truth: Truth, rng: np.random.Generator) -> dict[str, InitialEstimates]:
    """The deployment knowledge of the vessels there at the start (`truth` at time 0), drawn around the
    truth as in Sec. VI: x^_io,0 ~ N(x_io,0, P_io,0) for each, and p^_ij,0 ~ N(p_ij,0, P_ij,0) for each pair.
    A cold vessel (`initial.cold`) is left out, so it starts knowing nothing; its draws are made all the
    same, so the others get the numbers they would get in the warm scenario."""
    p_ij, p_io = scenario.initial.neighbour_variance, scenario.initial.target_variance
    estimates = {}
    for i in truth.positions:
        x_io = np.concatenate([truth.positions[i] - truth.target_position,
                               truth.velocities[i] - truth.target_velocity])
        target = x_io + rng.normal(0.0, math.sqrt(p_io), 4)
        neighbours = {}
        for j in truth.positions:
            if j != i:
                true = truth.positions[i] - truth.positions[j]
                neighbours[j] = tuple((true + rng.normal(0.0, math.sqrt(p_ij), 2)).tolist())
        if not scenario.starts_cold(i):
            estimates[i] = InitialEstimates(target=tuple(target.tolist()), target_variance=p_io,
                                            neighbours=neighbours, neighbour_variance=p_ij, stamp=truth.time)
    return estimates
