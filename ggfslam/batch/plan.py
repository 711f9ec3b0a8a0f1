"""Batch plans: which sequences, which variants, how many seeds; expanded into one run per combination.

A plan is a YAML file (``ggfslam batch PLAN.yaml``)::

    sequences:                  # config files; globs; relative paths are read from the plan file's folder
      - ../configs/tum/*.yaml
      - config: ../configs/synthetic/default.yaml
        name: room-60           # the sequence's name in the table (default: the config's `name`)
        set: [dataset.synthetic.n_frames=60]
    set: [mapping.eval_width=320]          # overrides for every run
    variants:                              # named lists of overrides (default: one variant, `default`)
      base: [ggf.enabled=false, gcgr.enabled=false]
      full: [ggf.enabled=true, gcgr.enabled=true]
    sweep:                                 # every point becomes a variant (crossed with the named ones)
      mode: product                        # product: every combination; zip: the i-th value of each key
      values:
        mapping.steps_per_frame: [4, 8]
    repeats: 3                             # seeds 0, 1, 2 (runtime.seed); or `seeds: [3, 7]`
    num_cpus: 1                            # CPUs (and threads) of each run

Each run is an ordinary run folder ``OUT/<sequence>/<variant>`` (``.../seed<k>`` when a plan has several seeds).
Overrides apply in the order: config file, plan ``set``, the sequence's ``set``, the variant's, the sweep point's,
the seed.
"""
from __future__ import annotations

import glob
import itertools
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field

from ggfslam.config import Config, load_config, parse_override, read_yaml_mapping, validate_model
from ggfslam.errors import ConfigError, GGFSlamError

DEFAULT_VARIANT = "default"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True)


class SequenceEntry(_Strict):
    """One entry of ``sequences`` written as a mapping."""

    config: str
    """Config file (or glob of config files)."""
    name: str | None = None
    """Name of the sequence in the table and run folders (default: the config's ``name``); only for one file."""
    set: list[str] = []
    """Overrides for this sequence's runs."""


class SweepSpec(_Strict):
    """Values of config keys, each combination (``product``) or each position (``zip``) a variant."""

    mode: Literal["product", "zip"] = "product"
    """``product``: every combination of the values; ``zip``: the i-th value of every key together."""
    values: dict[str, list] = Field(min_length=1)
    """Dotted config key -> list of values."""


class PlanFile(_Strict):
    """A batch plan as written in its YAML file."""

    name: str | None = None
    """A name for the batch, shown in reports (default: the file's name)."""
    sequences: list[str | SequenceEntry] = Field(min_length=1)
    """Config files, globs, or mappings ``{config, name, set}``."""
    set: list[str] = []
    """Overrides for every run."""
    variants: dict[str, list[str]] = {}
    """Named lists of overrides; empty: one variant named ``default`` without overrides."""
    sweep: SweepSpec | None = None
    """Values to sweep; every point is a variant (with each named variant when there are some)."""
    repeats: int = Field(1, ge=1)
    """Runs of each (sequence, variant) with seeds 0 .. repeats-1 (``runtime.seed``)."""
    seeds: list[int] | None = None
    """Explicit seeds instead of ``repeats``."""
    num_cpus: float = Field(1, gt=0)
    """CPUs each run asks of Ray; its torch, numba and OpenMP threads are pinned to this number (at least 1)."""
    memory_gb: float | None = Field(None, gt=0)
    """Memory each run asks of Ray (a scheduling reservation, not a limit); none: not reserved."""


@dataclass
class RunSpec:
    """One run of a plan: where it goes and the configuration it runs."""

    sequence: str
    variant: str
    seed: int | None  # None when the plan has one seed and sets none
    config_path: Path
    overrides: list[str]
    run_dir: Path
    num_cpus: float
    memory_gb: float | None
    config: Config | None = None  # None when the configuration does not validate (``error`` says why)
    error: str | None = None

    @property
    def key(self) -> str:
        """The run's place under the batch folder, e.g. ``fr3_cabinet/base/seed1``."""
        return "/".join(p for p in (self.sequence, self.variant, None if self.seed is None else f"seed{self.seed}")
                        if p)

    @property
    def threads(self) -> int:
        """Threads the run is pinned to."""
        return max(1, int(self.num_cpus))


@dataclass
class Plan:
    """A validated plan: its name, source and the runs it expands to (in table order)."""

    name: str
    source: str
    runs: list[RunSpec] = field(default_factory=list)
    spec: dict = field(default_factory=dict)  # the plan as resolved (saved beside the results)


def _safe_name(text: str) -> str:
    """A folder name for a sequence or variant label (path separators and spaces replaced)."""
    return re.sub(r"[^A-Za-z0-9._=,+-]+", "_", text).strip("_") or "_"


def _check_overrides(items: list[str], where: str) -> None:
    for text in items:
        try:
            parse_override(text)
        except ConfigError as e:
            raise ConfigError(f"{where}: {e}") from None


def _sweep_points(sweep: SweepSpec | None, source: str) -> list[tuple[str, list[str]]]:
    """(label, overrides) of each sweep point; one empty point without a sweep."""
    if sweep is None:
        return [("", [])]
    keys = list(sweep.values)
    for k in keys:
        _check_overrides([f"{k}=0"], f"{source}: sweep.values")
        if not sweep.values[k]:
            raise ConfigError(f"{source}: sweep.values.{k}: expected a non-empty list of values")
    lists = [sweep.values[k] for k in keys]
    if sweep.mode == "zip":
        lengths = {k: len(v) for k, v in zip(keys, lists)}
        if len(set(lengths.values())) > 1:
            raise ConfigError(f"{source}: sweep.mode zip needs lists of one length; got "
                              + ", ".join(f"{k}: {n}" for k, n in lengths.items()))
        combos = list(zip(*lists))
    else:
        combos = list(itertools.product(*lists))
    # a label names keys by their last part unless two keys share it
    lasts = [k.rsplit(".", 1)[-1] for k in keys]
    short = [last if lasts.count(last) == 1 else k for k, last in zip(keys, lasts)]
    points = []
    for combo in combos:
        label = ",".join(f"{s}={_format_value(v)}" for s, v in zip(short, combo))
        points.append((label, [f"{k}={_format_value(v)}" for k, v in zip(keys, combo)]))
    return points


def _format_value(v) -> str:
    """A sweep value as ``--set`` text (YAML scalars: true/false, null, numbers, strings)."""
    import yaml

    if isinstance(v, str):
        return v
    return yaml.safe_dump(v, default_flow_style=True, width=10_000).strip().removesuffix("...").strip()


def _sequence_files(entry: str | SequenceEntry, base: Path, source: str, index: int) -> list[tuple[Path, SequenceEntry]]:
    e = entry if isinstance(entry, SequenceEntry) else SequenceEntry(config=entry)
    pattern = Path(e.config).expanduser()
    pattern = pattern if pattern.is_absolute() else base / pattern
    if glob.has_magic(str(pattern)):
        files = sorted(Path(p) for p in glob.glob(str(pattern), recursive=True) if Path(p).is_file())
        if not files:
            raise ConfigError(f"{source}: sequences[{index}]: {e.config!r} matches no file (looked in {base})")
        if e.name is not None and len(files) > 1:
            raise ConfigError(f"{source}: sequences[{index}]: name {e.name!r} given for a glob of {len(files)} files")
    else:
        if not pattern.is_file():
            raise ConfigError(f"{source}: sequences[{index}]: config file {pattern} not found")
        files = [pattern]
    _check_overrides(e.set, f"{source}: sequences[{index}].set")
    return [(f.resolve(), e) for f in files]


def build_plan(data: dict, source: str, base: Path, out: Path) -> Plan:
    """Validate a plan mapping and expand it into runs under ``out`` (relative paths read from ``base``)."""
    pf = validate_model(PlanFile, data, source)
    assert isinstance(pf, PlanFile)
    _check_overrides(pf.set, f"{source}: set")
    for name, items in pf.variants.items():
        _check_overrides(items, f"{source}: variants.{name}")
    named = list(pf.variants.items()) or [(DEFAULT_VARIANT, [])]
    points = _sweep_points(pf.sweep, source)
    variants = []
    for (vname, vset), (plabel, pset) in itertools.product(named, points):
        label = plabel if (plabel and not pf.variants) else "+".join(p for p in (vname, plabel) if p)
        variants.append((_safe_name(label), vset + pset))
    if pf.seeds is not None and not pf.seeds:
        raise ConfigError(f"{source}: seeds: expected a non-empty list")
    if pf.seeds is not None and pf.repeats != 1:
        raise ConfigError(f"{source}: give repeats or seeds, not both")
    labels = [v for v, _ in variants]
    twice = sorted({v for v in labels if labels.count(v) > 1})
    if twice:
        raise ConfigError(f"{source}: variant folder name {twice[0]!r} stands for two variants; rename one")
    if len(set(pf.seeds or [])) != len(pf.seeds or []):
        raise ConfigError(f"{source}: seeds: a seed is listed twice")
    seeds: list[int | None] = list(pf.seeds) if pf.seeds is not None else (
        list(range(pf.repeats)) if pf.repeats > 1 else [None])

    files = [f for i, entry in enumerate(pf.sequences) for f in _sequence_files(entry, base, source, i)]
    runs, names = [], {}
    for path, entry in files:
        seq_overrides = pf.set + entry.set
        try:
            cfg0 = load_config(path, seq_overrides)
            seq_name, seq_error = entry.name or cfg0.name or path.stem, None
        except GGFSlamError as e:  # a broken sequence config is that sequence's failed rows, not the batch's end
            seq_name, seq_error = entry.name or path.stem, str(e)
        seq_name = _safe_name(seq_name)
        if seq_name in names and names[seq_name] != path:
            raise ConfigError(f"{source}: two sequences are named {seq_name!r} ({names[seq_name]} and {path}); "
                              "give one a `name:` in its sequences entry")
        if seq_name in names:
            continue  # the same file listed twice (e.g. by two globs)
        names[seq_name] = path
        for (vname, vset), seed in itertools.product(variants, seeds):
            overrides = seq_overrides + vset + ([] if seed is None else [f"runtime.seed={seed}"])
            spec = RunSpec(seq_name, vname, seed, path, overrides, out, pf.num_cpus, pf.memory_gb)
            spec.run_dir = out / spec.key
            spec.error = seq_error
            if seq_error is None:
                try:
                    spec.config = load_config(path, overrides)
                except GGFSlamError as e:
                    spec.error = str(e)
            runs.append(spec)
    resolved = {"name": pf.name or Path(source).stem, "source": source,
                "variants": {n: s for n, s in variants}, "seeds": seeds, "num_cpus": pf.num_cpus,
                "memory_gb": pf.memory_gb, "set": pf.set,
                "runs": [{"key": r.key, "config": str(r.config_path), "overrides": r.overrides} for r in runs]}
    return Plan(pf.name or Path(source).stem, source, runs, resolved)


def load_plan(path: str | Path, out: str | Path) -> Plan:
    """Read and expand a plan file (see the module docstring) into runs under ``out``."""
    path = Path(path)
    data = read_yaml_mapping(path, "plan file")
    return build_plan(data, str(path), path.resolve().parent, Path(out).resolve())


__all__ = ["Plan", "PlanFile", "RunSpec", "SequenceEntry", "SweepSpec", "build_plan", "load_plan", "DEFAULT_VARIANT"]
