"""An evaluation suite: datasets x configurations x seeds, read from YAML and checked before anything runs.

::

    name: offline
    runs: 3                      # seeds 0..runs-1 (``evaluate --runs`` overrides)
    datasets:
      - name: euroc
        root: ../../../shared/data/euroc_mh05_sample   # relative to this file ($VARS expanded); a sequence or a folder of them
        sequences: all           # or a list of names (KITTI: 00, 05, ...; other roots: sub-folder names)
        layout: auto             # optional, as run --layout
        gt: null                 # optional ground-truth file (one-sequence datasets)
        stride: 1                # optional
        max_frames: null         # optional
      - name: block_loop
        synthetic: {scene: loop, frames: 600, width: 320, height: 240, seed: 0}   # rendered once into OUT/data
    configurations:
      - name: colmap
        preset: video-cpu        # a named preset (run --preset)
        overrides: {backend: false, frontend.submap_size: 32}   # RunConfig keys, nested or dotted
        datasets: [euroc]        # optional: where it applies (default: every dataset)

Every (sequence, configuration, seed) is one :class:`Task`. :func:`load_suite` raises
:class:`~vggt_slam_pp.errors.InputError` with one line for malformed YAML, a missing dataset, an unknown
sequence, an unknown preset or a configuration key that ``RunConfig`` does not know.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path

import yaml

from vggt_slam_pp.errors import InputError, VggtSlamError

__all__ = ["DatasetSpec", "ConfigSpec", "SuiteSpec", "Task", "load_suite", "expand", "sequences_of"]

_SCENES = ("loop", "figure8")


@dataclass(frozen=True)
class DatasetSpec:
    name: str
    root: Path | None  # a sequence or a folder of sequences (None for a synthetic one)
    sequences: tuple[str, ...] | None  # None: all
    layout: str = "auto"
    gt: Path | None = None
    stride: int = 1
    max_frames: int | None = None
    synthetic: dict | None = None  # make_scene arguments: scene, frames, width, height, seed


@dataclass(frozen=True)
class ConfigSpec:
    name: str
    preset: str
    overrides: dict
    datasets: tuple[str, ...] | None  # None: every dataset


@dataclass(frozen=True)
class SuiteSpec:
    name: str
    path: Path
    runs: int
    datasets: tuple[DatasetSpec, ...]
    configurations: tuple[ConfigSpec, ...]


@dataclass(frozen=True)
class Task:
    """One run: what to read, how to configure it (a ``RunConfig`` as a dictionary, its seed set) and where
    its outputs go (``folder``). Plain data: it travels to a process pool or a Ray worker."""

    dataset: str
    sequence: str
    config: str
    seed: int
    input: str
    layout: str
    gt: str | None
    stride: int
    max_frames: int | None
    run_config: dict
    folder: str

    @property
    def key(self) -> str:
        return f"{self.config}/{self.dataset}/{self.sequence}/seed{self.seed}"


def _fail(suite: Path, msg: str) -> InputError:
    return InputError(f"suite {suite}: {msg}")


def _nested(overrides: dict, suite: Path, where: str) -> dict:
    """Dotted keys (``frontend.submap_size: 8``) as nested dictionaries."""
    if not isinstance(overrides, dict):
        raise _fail(suite, f"{where}: overrides must be a mapping")
    out: dict = {}
    for key, value in overrides.items():
        node = out
        *parents, leaf = str(key).split(".")
        for p in parents:
            node = node.setdefault(p, {})
            if not isinstance(node, dict):
                raise _fail(suite, f"{where}: {key} conflicts with another override")
        node[leaf] = _nested(value, suite, where) if isinstance(value, dict) else value
    return out


def _path(value, base: Path) -> Path:
    """A path from the suite: ``~`` and ``$VARIABLES`` expanded, relative to the suite file's folder."""
    p = Path(os.path.expandvars(str(value))).expanduser()
    return (p if p.is_absolute() else (base / p)).resolve()


def load_suite(path: str | Path) -> SuiteSpec:
    """Read and check a suite file (everything that can be checked before a run starts)."""
    from vggt_slam_pp.configs import PRESETS, merged
    from vggt_slam_pp.io.datasets import LAYOUTS
    from vggt_slam_pp.pipeline import RunConfig

    path = Path(path)
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise InputError(f"cannot read suite {path}: {exc.strerror or exc}") from None
    except yaml.YAMLError as exc:
        where = getattr(exc, "problem_mark", None)
        at = f" (line {where.line + 1})" if where is not None else ""
        raise _fail(path, f"not valid YAML{at}: {getattr(exc, 'problem', None) or exc}") from None
    if not isinstance(data, dict):
        raise _fail(path, "expected a mapping with 'datasets' and 'configurations'")
    unknown = sorted(set(data) - {"name", "runs", "datasets", "configurations"})
    if unknown:
        raise _fail(path, f"unknown key(s) {', '.join(unknown)}; known: name, runs, datasets, configurations")
    base = path.parent
    datasets = []
    for i, d in enumerate(data.get("datasets") or []):
        if not isinstance(d, dict) or "name" not in d:
            raise _fail(path, f"datasets[{i}] needs a name")
        where = f"dataset {d['name']!r}"
        known = {"name", "root", "sequences", "layout", "gt", "stride", "max_frames", "synthetic"}
        if set(d) - known:
            raise _fail(path, f"{where}: unknown key(s) {', '.join(sorted(set(d) - known))}")
        if ("root" in d) == ("synthetic" in d):
            raise _fail(path, f"{where}: give either root or synthetic")
        seqs = d.get("sequences", "all")
        if seqs != "all" and not (isinstance(seqs, list) and seqs):
            raise _fail(path, f"{where}: sequences must be 'all' or a list of names")
        layout = d.get("layout", "auto")
        if layout != "auto" and layout not in LAYOUTS:
            raise _fail(path, f"{where}: unknown layout {layout!r}; expected auto or one of {', '.join(LAYOUTS)}")
        root = gt = None
        if "root" in d:
            root = _path(d["root"], base)
            if not root.exists():
                raise _fail(path, f"{where}: root not found: {root}")
        if d.get("gt") is not None:
            gt = _path(d["gt"], base)
            if not gt.is_file():
                raise _fail(path, f"{where}: ground-truth file not found: {gt}")
        syn = d.get("synthetic")
        if syn is not None and (not isinstance(syn, dict) or syn.get("scene", "loop") not in _SCENES
                                or set(syn) - {"scene", "frames", "width", "height", "seed"}):
            raise _fail(path, f"{where}: synthetic takes scene ({', '.join(_SCENES)}), frames, width, height, seed")
        datasets.append(DatasetSpec(str(d["name"]), root, None if seqs == "all" else tuple(str(s) for s in seqs),
                                    layout, gt, int(d.get("stride", 1)), d.get("max_frames"), syn))
    if not datasets:
        raise _fail(path, "no datasets")
    names = [d.name for d in datasets]
    if len(set(names)) != len(names):
        raise _fail(path, "dataset names must be unique")
    configs = []
    for i, c in enumerate(data.get("configurations") or []):
        if not isinstance(c, dict) or "name" not in c:
            raise _fail(path, f"configurations[{i}] needs a name")
        where = f"configuration {c['name']!r}"
        if set(c) - {"name", "preset", "overrides", "datasets"}:
            raise _fail(path, f"{where}: unknown key(s) {', '.join(sorted(set(c) - {'name', 'preset', 'overrides', 'datasets'}))}")
        preset = str(c.get("preset", "vggt"))
        if preset not in PRESETS:
            raise _fail(path, f"{where}: unknown preset {preset!r}; choose one of {', '.join(PRESETS)}")
        overrides = _nested(c.get("overrides") or {}, path, where)
        try:  # every key checked now, not when its first run starts
            RunConfig.from_dict(merged(dataclasses.asdict(RunConfig.preset(preset)), overrides))
        except VggtSlamError as exc:
            raise _fail(path, f"{where}: {exc}") from None
        only = c.get("datasets")
        if only is not None and (not isinstance(only, list) or set(map(str, only)) - set(names)):
            raise _fail(path, f"{where}: datasets must list names from: {', '.join(names)}")
        configs.append(ConfigSpec(str(c["name"]), preset, overrides, None if only is None else tuple(map(str, only))))
    if not configs:
        raise _fail(path, "no configurations")
    if len({c.name for c in configs}) != len(configs):
        raise _fail(path, "configuration names must be unique")
    runs = data.get("runs", 1)
    if not isinstance(runs, int) or runs < 1:
        raise _fail(path, "runs must be a positive integer")
    suite = SuiteSpec(str(data.get("name", path.stem)), path, runs, tuple(datasets), tuple(configs))
    for d in suite.datasets:
        sequences_of(d, suite)  # unknown sequence names and empty roots fail now
    return suite


def sequences_of(d: DatasetSpec, suite: SuiteSpec, data_dir: Path | None = None) -> list[tuple[str, Path]]:
    """(name, folder) of every sequence the dataset names. A root that is itself a sequence is one
    sequence, named as the dataset; a KITTI odometry root gives ``sequences/NN``; another folder gives its sub-folders (or their
    sub-folders, named ``a/b``) that are sequences of a known layout."""
    from vggt_slam_pp.io.datasets import _is_kitti_sequence, detect_layout

    if d.synthetic is not None:
        folder = (data_dir or Path("data")) / d.name
        return [(d.name, folder)]
    root = d.root
    try:  # (an explicit layout opens each sequence; it does not make a folder of sequences one sequence)
        detect_layout(root)
        found = [(d.name, root)]  # a root that is one sequence: named as the dataset
    except InputError:
        seq_dir = root / "sequences" if (root / "sequences").is_dir() else root

        def is_sequence(folder: Path) -> bool:
            if _is_kitti_sequence(folder):
                return True
            try:
                return detect_layout(folder) != "images"
            except InputError:
                return False

        def subdirs(folder: Path) -> list[Path]:
            return sorted(p for p in folder.iterdir() if p.is_dir() and not p.name.startswith("."))

        found = []
        for sub in subdirs(seq_dir):
            if is_sequence(sub):
                found.append((sub.name, sub))
            else:  # one level deeper: Virtual KITTI 2's SceneNN/variation, 7-Scenes' scene/seq-NN
                found += [(f"{sub.name}/{s.name}", s) for s in subdirs(sub) if is_sequence(s)]
    if not found:
        raise _fail(suite.path, f"dataset {d.name!r}: no sequence of a known layout in {root}")
    if d.sequences is None:
        return found
    by_name = dict(found)
    missing = [s for s in d.sequences if s not in by_name]
    if missing:
        raise _fail(suite.path, f"dataset {d.name!r}: no sequence {', '.join(missing)} in {root} "
                                f"(it has {', '.join(by_name)})")
    return [(s, by_name[s]) for s in d.sequences]


def expand(suite: SuiteSpec, out: Path, runs: int | None = None) -> list[Task]:
    """Every (sequence, configuration, seed) of the suite as a :class:`Task` whose outputs go to
    ``out/runs/CONFIG/DATASET/SEQUENCE/seedK``."""
    from vggt_slam_pp.configs import merged
    from vggt_slam_pp.pipeline import RunConfig

    tasks = []
    for c in suite.configurations:
        base = merged(dataclasses.asdict(RunConfig.preset(c.preset)), c.overrides)
        for d in suite.datasets:
            if c.datasets is not None and d.name not in c.datasets:
                continue
            for seq, folder in sequences_of(d, suite, out / "data"):
                for seed in range(runs or suite.runs):
                    cfg = merged(base, {"backbone": {"seed": seed}})
                    tasks.append(Task(d.name, seq, c.name, seed, str(folder), d.layout,
                                      str(d.gt) if d.gt else None, d.stride, d.max_frames, cfg,
                                      str(out / "runs" / c.name / d.name / seq / f"seed{seed}")))
    return tasks
