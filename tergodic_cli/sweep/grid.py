"""The sweep grid: GRID.toml -> objects and the list of runs (objects x starts x options).

The format (paths relative to the grid file) is in docs/speed.md and ``tergodic sweep --help``.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path

from tergodic_cli.errors import TergodicError, check_seed, require
from tergodic_cli.explore.config import ExploreConfig, validate_config

#: Keys of an object table that say where its cloud comes from.
SOURCES = ("file", "capture", "synthetic")
#: Capture options an object table may carry (CaptureConfig fields).
CAPTURE_KEYS = ("voxel", "voxel_rule", "units", "target", "marking", "seed", "noise", "crop", "outliers")
EXPLORE_KEYS = tuple(f.name for f in fields(ExploreConfig) if f.name not in ("steps", "seed"))
FIX = "see the grid format in 'tergodic sweep --help' or docs/speed.md"


@dataclass
class ObjectSpec:
    """One object of the grid: where its cloud comes from and its own explore options."""

    name: str
    source: str  # "file" | "capture" | "synthetic"
    location: str  # path, or the synthetic kind
    capture_options: dict = field(default_factory=dict)
    neighbors: int = 30
    starts_file: str | None = None
    explore: dict = field(default_factory=dict)


@dataclass
class Grid:
    """A parsed grid: objects, the option lists, the start indices, steps and seed."""

    path: Path
    steps: int
    seed: int
    objects: list[ObjectSpec]
    starts: list[int]
    options: dict[str, list]  # ExploreConfig field -> values (nk and alpha always present)

    @property
    def varied(self) -> list[str]:
        """Option names with more than one value (besides nk and alpha), in grid order."""
        return [k for k, v in self.options.items() if k not in ("nk", "alpha") and len(v) > 1]

    @property
    def max_nk(self) -> int:
        return max(int(v) for v in self.options["nk"])

    def combos(self) -> list[dict]:
        return [dict(zip(self.options, values)) for values in itertools.product(*self.options.values())]

    @property
    def n_runs(self) -> int:
        return len(self.objects) * len(self.starts) * len(self.combos())


def load_grid(path: str | Path) -> Grid:
    """Parse and validate GRID.toml (one-line errors naming the offending key)."""
    path = Path(path)
    require(path.is_file(), f"grid file {path} does not exist", "give a GRID.toml (see 'tergodic sweep --help')")
    try:
        data = tomllib.loads(path.read_text())
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise TergodicError(f"{path} is not valid TOML ({str(exc).splitlines()[0][:80]})", "fix the syntax") from None
    base = path.resolve().parent
    unknown = set(data) - {"steps", "seed", "objects", "grid"}
    require(not unknown, f"{path.name}: unknown top-level key(s) {', '.join(sorted(unknown))}",
            "top level takes steps, seed, [objects.NAME] and [grid]")
    steps = data.get("steps", 1000)
    require(isinstance(steps, int) and steps >= 1, f"{path.name}: steps must be an integer >= 1, got {steps!r}",
            "e.g. steps = 1000")
    seed = data.get("seed", 0)
    check_seed(seed, f"{path.name}: seed")
    objs = data.get("objects")
    require(isinstance(objs, dict) and objs, f"{path.name}: no [objects.NAME] table",
            "add one, e.g. [objects.bunny] with file = \"bunny.ply\"")
    objects = [_parse_object(name, spec, base, path.name) for name, spec in objs.items()]

    grid = data.get("grid", {})
    require(isinstance(grid, dict), f"{path.name}: [grid] must be a table", "e.g. [grid] nk = [50, 100]")
    starts = grid.get("start", 1)
    if isinstance(starts, int) and not isinstance(starts, bool):
        require(starts >= 1, f"{path.name}: [grid] start = {starts} must be >= 1", "e.g. start = 10 (indices 0..9)")
        starts = list(range(starts))
    require(isinstance(starts, list) and starts and all(isinstance(s, int) and s >= 0 for s in starts),
            f"{path.name}: [grid] start must be a count or a list of indices >= 0", "e.g. start = 10 or [0, 3]")
    require(len(set(starts)) == len(starts), f"{path.name}: [grid] start has repeated indices", "list each once")
    options: dict[str, list] = {"nk": [200], "alpha": ["10"]}
    for key, values in grid.items():
        if key == "start":
            continue
        require(key not in ("steps", "seed", "basis_neighbors"), f"{path.name}: [grid] {key} cannot vary per run",
                "set steps/seed at the top level and neighbors per object")
        require(key in EXPLORE_KEYS, f"{path.name}: [grid] {key} is not an explore option",
                f"use nk, alpha or one of: {', '.join(k for k in EXPLORE_KEYS if k not in ('nk', 'alpha'))}")
        values = values if isinstance(values, list) else [values]
        require(len(values) > 0, f"{path.name}: [grid] {key} is an empty list", "give at least one value")
        require(len(set(map(str, values))) == len(values), f"{path.name}: [grid] {key} has repeated values",
                "list each value once")
        options[key] = [str(v) for v in values] if key == "alpha" else values
    for v in options["nk"]:
        require(isinstance(v, int) and not isinstance(v, bool) and v >= 1,
                f"{path.name}: [grid] nk values must be integers >= 1, got {v!r}", "e.g. nk = [25, 50, 100, 200]")
    g = Grid(path=path, steps=steps, seed=seed, objects=objects, starts=starts, options=options)
    for obj in objects:  # every combination must be a valid config for every object
        for combo in g.combos():
            try:
                validate_config(run_config(g, obj, combo))
            except TergodicError as exc:
                raise TergodicError(f"{path.name}: object {obj.name}: {exc.problem}", exc.fix) from None
            except (TypeError, ValueError) as exc:
                raise TergodicError(f"{path.name}: object {obj.name}: bad option value ({exc})", FIX) from None
    return g


def _parse_object(name: str, spec, base: Path, fname: str) -> ObjectSpec:
    require(isinstance(spec, dict), f"{fname}: [objects.{name}] must be a table", "e.g. file = \"bunny.ply\"")
    given = [k for k in SOURCES if k in spec]
    require(len(given) == 1, f"{fname}: [objects.{name}] needs exactly one of {', '.join(SOURCES)}",
            "e.g. file = \"bunny.ply\", capture = \"captures/cup\" or synthetic = \"mug\"")
    source = given[0]
    location = str(spec[source])
    if source in ("file", "capture"):
        p = base / location  # an absolute location stays as it is
        require(p.exists(), f"{fname}: [objects.{name}] {source} {location} does not exist",
                "paths are relative to the grid file")
        location = str(p)
    obj = ObjectSpec(name=name, source=source, location=location)
    for key, value in spec.items():
        if key == source:
            continue
        if key in CAPTURE_KEYS:
            require(source != "capture", f"{fname}: [objects.{name}] {key} is a capture option, but the object is "
                    "an existing capture", "re-capture it with 'tergodic capture', or use file = ...")
            obj.capture_options[key] = tuple(value) if isinstance(value, list) else value
        elif key == "neighbors":
            require(isinstance(value, int) and value >= 3, f"{fname}: [objects.{name}] neighbors must be an integer "
                    ">= 3", "e.g. neighbors = 40")
            obj.neighbors = value
        elif key == "starts":
            p = base / str(value)
            require(p.is_file(), f"{fname}: [objects.{name}] starts {value} does not exist",
                    "give an .npz with key x0_arr, x0 or starts (n, 3) metres (or an .npy/.csv), relative to the grid file")
            obj.starts_file = str(p)
        elif key in EXPLORE_KEYS and key not in ("nk",):
            obj.explore[key] = str(value) if key == "alpha" else value
        else:
            raise TergodicError(f"{fname}: [objects.{name}] unknown key {key}",
                                f"use {'/'.join(SOURCES)}, neighbors, starts, capture options ({', '.join(CAPTURE_KEYS)}) "
                                "or explore options (agent_radius, a_max, ...)")
    return obj


def run_config(grid: Grid, obj: ObjectSpec, combo: dict) -> ExploreConfig:
    """The ExploreConfig of one run: defaults < the object's options < the grid combination."""
    values = {**obj.explore, **combo}
    if "normal_hint" in values:
        values["normal_hint"] = tuple(values["normal_hint"])
    return ExploreConfig(steps=grid.steps, seed=grid.seed, basis_neighbors=obj.neighbors, **values)


def alpha_key(alpha) -> tuple:
    """Sort key of α values: numbers in order, then schedules ("50:10@200") by their text."""
    try:
        return (0, float(alpha), "")
    except (TypeError, ValueError):
        return (1, 0.0, str(alpha))


def run_id(object_key: str, start: int, config: dict) -> str:
    """A stable id of one run: the object's content key, the start and the whole config."""
    blob = json.dumps({"object": object_key, "start": start, "config": config}, sort_keys=True)
    return hashlib.sha1(blob.encode()).hexdigest()[:16]
